"""The policy kinds the one trainer learns, behind one interface (docs/design.md "One trainer").

Every kind is a tanh-squashed Gaussian a = tanh(μ + σ ε) whose mean and std come from a *task
policy*: the pytree that acts on one task. ``Actor.at(params, z)`` turns the learned params and a
task latent z (shape (latent_dim,); (0,) for single-task runs) into that task policy:

- ``StoredSymbolic`` (ESPL, §3): w, b and the path probabilities p are learned leaves; z unused.
- ``GeneratedSymbolic`` (CSP, §4): w, b = Φ(z), p = σ(Ψ(z)) for all action dims, std net F(s, z).
- ``MLPActor`` (single-task SAC baseline): an MLP mean and the std net F(s).
- ``PearlActor`` (PEARL): one MLP on s ⊕ z with μ and log σ heads (rlkit ``TanhGaussianPolicy``).
- ``HyperActor`` (Hyper, Sarafian et al. 2021): a hypernetwork from z generates a
  one-hidden-layer policy on s.

The symbolic kinds also give the path-selector masks (Algorithm 1 lines 4 and 11, Algorithm 2):
a Bernoulli mask for collection and for the critic's target action, the gumbel-sigmoid mask for
the actor loss, the deterministic mask p > 0.5 (|w| > 1e-3) of the exported formula. The SAC
losses (``espl_jax.sac``) see only this interface. The z a policy receives from the trainer is
always ``stop_gradient``-ed: only the critic trains the encoder (Algorithm 2, docs/design.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax

from espl_jax import config as config_lib
from espl_jax import selector
from espl_jax.networks import MLP, EnsembleMLP, HyperNetwork, generated_policy
from espl_jax.symbolic import SymbolicNetwork, get_layout

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # clamp of log σ (authors' code, as in SAC)
PSI_LAST_BIAS = 3.0  # σ(3.0) ≈ 0.95: most CSP paths start active (paper App. C.2)
LOGIT_BOUND = 6.0  # CSP: the authors' penalty keeps Ψ's logits within ±6 (trainable gradients)

Params = dict[str, Any]
TaskPolicy = dict[str, Any]


@dataclass(frozen=True)
class PolicyConfig:
    """The config keys the policy kinds read (``espl_jax.config.Config`` documents each)."""

    layout: str
    selector: str
    std_hidden: tuple[int, ...]
    mlp_actor_hidden: tuple[int, ...]
    generator_hidden: tuple[int, ...]
    pearl_hidden: tuple[int, ...]
    hyper_trunk: tuple[int, ...]
    hyper_policy_hidden: int
    squash_epsilon: float
    grad_clip: float
    actor_learning_rate: float
    probs_learning_rate: float
    finetune: bool
    finetune_learning_rate: float
    schedule_iterations: int
    updates_per_iteration: int
    csp_relaxed_mask: str
    bias_l1_scale: float
    logit_clamp_scale: float
    weight_l1_scale: float


def no_latent() -> jax.Array:
    """The z of a single-task run's policy: (0,)."""
    return jnp.zeros((0,))


def _mean_abs(arrays: list[jax.Array]) -> jax.Array:
    """mean |x| over every entry of a list of arrays (the L1 terms on w and b)."""
    return jnp.mean(jnp.abs(jnp.concatenate([a.ravel() for a in arrays])))


def tanh_gaussian_log_prob(
    u: jax.Array, mean: jax.Array, log_std: jax.Array, squash_epsilon: float = 0.0
) -> jax.Array:
    """log π(tanh(u)) for u ~ N(mean, σ²): Gaussian log-density minus Σ log(1 − tanh(u)² + ε).

    With ε = 0 (SAC, App. C) it uses log(1 − tanh(u)²) = 2 (log 2 − u − softplus(−2u)), exact and
    stable, and unbounded: a mean of 10³ (a CSP network at initialisation on walker2d_params,
    whose velocities reach 10) gives log π ≈ 2|u| per action dim, an entropy term of −10³ per
    step in the critic's target, which then diverges. ε > 0 is rlkit's TanhNormal (PEARL's and
    the authors' CSP code use 1e-6): log(1 − tanh² + ε) = logaddexp(exact, log ε) ≥ log ε.
    """
    gauss = -0.5 * ((u - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)
    correction = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    if squash_epsilon > 0.0:
        correction = jnp.logaddexp(correction, math.log(squash_epsilon))
    return jnp.sum(gauss - correction, axis=-1)


@dataclass(frozen=True)
class Actor:
    """Static description of a policy kind; all methods are pure functions of their arguments.

    Attributes:
        config: the keys of the run's config the kinds read.
        obs_dim, action_dim: env sizes.
        latent_dim: size of z (0 for single-task runs).
    """

    config: PolicyConfig
    obs_dim: int
    action_dim: int
    latent_dim: int = 0

    # What the kind is --------------------------------------------------------------------------

    @property
    def symbolic(self) -> SymbolicNetwork | None:
        """The symbolic network of a symbolic kind (for masks and export), else None."""
        return None

    @property
    def uses_selector(self) -> bool:
        return False

    @property
    def one_formula(self) -> bool:
        """The learned params are one formula for every task (ESPL), so a run can keep the best
        one it has seen (the hall of fame, ``espl_jax.halloffame``)."""
        return False

    @property
    def freezes_mask(self) -> bool:
        """The kind has learned path probabilities to freeze for fine-tuning (``freeze``)."""
        return False

    def init(self, key: jax.Array) -> Params:
        raise NotImplementedError

    def at(self, params: Params, z: jax.Array) -> TaskPolicy:
        """The task policy for latent z (L,): ``policy(params, generate(params, z))``."""
        return self.policy(params, self.generate(params, z))

    def generate(self, params: Params, z: jax.Array) -> Any:
        """The part of the task policy that depends on z (CSP: w, b, p; PEARL: z itself; Hyper:
        the generated weights). Scans over env steps carry this, not the whole policy, so the
        learned params are not copied at every step."""
        return z

    def policy(self, params: Params, part: Any) -> TaskPolicy:
        """The task policy from the learned params and a ``generate``-d part."""
        del part  # single-task kinds: the params are the policy
        return params

    def mean_and_log_std(
        self, policy: TaskPolicy, mask: list | None, obs: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Pre-tanh mean (A,), clamped log σ (A,) and the operator penalty () for one obs."""
        raise NotImplementedError

    def optimizer(self) -> optax.GradientTransformation:
        cfg = self.config
        return optax.chain(
            optax.clip_by_global_norm(cfg.grad_clip), optax.adam(cfg.actor_learning_rate)
        )

    # Path selector (symbolic kinds) ---------------------------------------------------------------

    def train_mask(self, key: jax.Array, policy: TaskPolicy, tau: jax.Array) -> list | None:
        """Gumbel-sigmoid mask for the actor loss (Algorithm 1, line 11)."""
        return None

    def collect_mask(self, key: jax.Array, policy: TaskPolicy) -> list | None:
        """Bernoulli(p) mask for collection and the critic's target (Algorithm 1, line 4)."""
        return None

    def eval_mask(self, policy: TaskPolicy) -> list | None:
        """The exported formula's mask: p > 0.5 and |w| > 1e-3."""
        return None

    def regularizers(self, policy: TaskPolicy, l_min: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(L_select or its ablation, extra terms already weighted) for one task policy."""
        return jnp.zeros(()), jnp.zeros(())

    @property
    def has_extra_loss(self) -> bool:
        return False

    def project(self, params: Params) -> Params:
        """Back onto the feasible set after an optimizer step (ESPL: p ∈ [0, 1])."""
        return params

    def l0_ratio(self, policy: TaskPolicy) -> jax.Array:
        """E||m||_0 / N, the fraction of paths the selector keeps in expectation (1 without one)."""
        if not self.uses_selector:
            return jnp.ones(())
        return selector.expected_l0(policy["probs"]) / selector.count(policy["probs"])

    def select_loss(self, policy: TaskPolicy, l_min: jax.Array) -> jax.Array:
        """L_select on the task policy's path probabilities; without a selector (the ESPL_l1 and
        CSP_L1 ablations) L1 on the symbolic weights w takes its place."""
        if self.uses_selector:
            return selector.select_loss(policy["probs"], l_min)
        return selector.l1_loss(policy["mean"]["w"])

    # Acting (shared) --------------------------------------------------------------------------

    def sample(
        self, key: jax.Array, policy: TaskPolicy, mask: list | None, obs: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """a = tanh(μ + σ ε) with its log-probability and the operator penalty, for one obs."""
        mean, log_std, penalty = self.mean_and_log_std(policy, mask, obs)
        u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        log_prob = tanh_gaussian_log_prob(u, mean, log_std, self.config.squash_epsilon)
        return jnp.tanh(u), log_prob, penalty

    def act_with_noise(
        self, policy: TaskPolicy, mask: list | None, obs: jax.Array, eps: jax.Array
    ) -> jax.Array:
        """a = tanh(μ + σ ε) for a given standard-normal ε (action_dim,): collection's action."""
        mean, log_std, _ = self.mean_and_log_std(policy, mask, obs)
        return jnp.tanh(mean + jnp.exp(log_std) * eps)

    def deterministic(self, policy: TaskPolicy, mask: list | None, obs: jax.Array) -> jax.Array:
        return jnp.tanh(self.mean_and_log_std(policy, mask, obs)[0])

    def _std_net(self) -> MLP:
        return MLP(self.config.std_hidden, self.action_dim)

    def _log_std(self, std_params: Any, inputs: jax.Array) -> jax.Array:
        return jnp.clip(self._std_net().apply(std_params, inputs), LOG_STD_MIN, LOG_STD_MAX)


def _probs_and_rest_optimizer(config: PolicyConfig) -> optax.GradientTransformation:
    """ESPL: the selector's probabilities keep the paper's step while w, b and θ_F may take a
    larger one (config.py); one global-norm clip over all of them. With ``finetune`` the step
    of w, b and θ_F becomes ``finetune_learning_rate`` once the schedule is over."""
    rest_lr: float | optax.Schedule = config.actor_learning_rate
    if config.finetune:
        boundary = config.schedule_iterations * config.updates_per_iteration
        rest_lr = optax.piecewise_constant_schedule(
            config.actor_learning_rate,
            {boundary: config.finetune_learning_rate / config.actor_learning_rate},
        )
    per_group = optax.multi_transform(
        {
            "probs": optax.adam(config.probs_learning_rate),
            "rest": optax.adam(rest_lr),
        },
        lambda params: {
            k: jax.tree.map(lambda _, k=k: "probs" if k == "probs" else "rest", v)
            for k, v in params.items()
        },
    )
    return optax.chain(optax.clip_by_global_norm(config.grad_clip), per_group)


@dataclass(frozen=True)
class SymbolicActor(Actor):
    """What both symbolic kinds share: the network of the config's layout, and whether the
    probabilistic path selector or the L1 ablation prunes it."""

    @property
    def symbolic(self) -> SymbolicNetwork:
        return SymbolicNetwork(get_layout(self.config.layout), self.obs_dim, self.action_dim)

    @property
    def uses_selector(self) -> bool:
        return self.config.selector == "probabilistic"


@dataclass(frozen=True)
class StoredSymbolic(SymbolicActor):
    """ESPL: params {"mean": {"w", "b"}, "probs": like w (empty for the L1 ablation), "std"}."""

    @property
    def one_formula(self) -> bool:
        return True

    @property
    def freezes_mask(self) -> bool:
        return self.uses_selector

    def init(self, key: jax.Array) -> Params:
        k_mean, k_std = jax.random.split(key)
        std = self._std_net().init(k_std, jnp.zeros((self.obs_dim,)))
        mean = self.symbolic.init(k_mean)
        probs = selector.init_probs(mean["w"]) if self.uses_selector else []
        return {"mean": mean, "probs": probs, "std": std}

    def mean_and_log_std(self, policy, mask, obs):
        mean, penalty = self.symbolic.apply(policy["mean"], mask, obs)
        return mean, self._log_std(policy["std"], obs), penalty

    def optimizer(self) -> optax.GradientTransformation:
        return _probs_and_rest_optimizer(self.config)

    def _probs(self, policy: TaskPolicy) -> list:
        return policy["probs"] if self.uses_selector else selector.ones_mask(policy["mean"]["w"])

    def train_mask(self, key, policy, tau):
        if not self.uses_selector:
            return selector.ones_mask(policy["mean"]["w"])
        return selector.gumbel_sigmoid_mask(key, policy["probs"], tau)

    def collect_mask(self, key, policy):
        if not self.uses_selector:
            return selector.ones_mask(policy["mean"]["w"])
        return selector.bernoulli_mask(key, policy["probs"])

    def eval_mask(self, policy):
        return selector.deterministic_mask(self._probs(policy), policy["mean"]["w"])

    def regularizers(self, policy, l_min):
        select = self.select_loss(policy, l_min)
        extra = jnp.zeros(())
        if self.has_extra_loss:
            extra = self.config.bias_l1_scale * _mean_abs(policy["mean"]["b"])
        return select, extra

    @property
    def has_extra_loss(self) -> bool:
        return self.config.bias_l1_scale > 0

    def project(self, params):
        return {**params, "probs": selector.project_probs(params["probs"])}

    def freeze(self, params: Params) -> Params:
        """p := the exported mask as 0/1 (``finetune``): every mask is then that mask."""
        if not self.uses_selector:
            return params
        probs = selector.deterministic_mask(params["probs"], params["mean"]["w"])
        return {**params, "probs": probs}


@dataclass(frozen=True)
class MLPActor(Actor):
    """The single-task neural baseline (plain SAC): {"mean": MLP, "probs": [], "std": F(s)}."""

    def init(self, key: jax.Array) -> Params:
        k_mean, k_std = jax.random.split(key)
        dummy = jnp.zeros((self.obs_dim,))
        std = self._std_net().init(k_std, dummy)
        mean = MLP(self.config.mlp_actor_hidden, self.action_dim).init(k_mean, dummy)
        return {"mean": mean, "probs": [], "std": std}

    def mean_and_log_std(self, policy, mask, obs):
        mean = MLP(self.config.mlp_actor_hidden, self.action_dim).apply(policy["mean"], obs)
        return mean, self._log_std(policy["std"], obs), jnp.zeros(())

    def optimizer(self) -> optax.GradientTransformation:
        return _probs_and_rest_optimizer(self.config)


@dataclass(frozen=True)
class GeneratedSymbolic(SymbolicActor):
    """CSP: w, b = Φ(z) and p = σ(Ψ(z)) for all action dims; std net F(s, z) (§4, App. C.2).

    Params {"phi_w", "phi_b", "psi": one z → 64 → 64 → n MLP per action dim, "std"}. The task
    policy is {"mean": {"w", "b"}, "probs", "logits", "std", "z"}, laid out like ESPL's so the
    symbolic network, the masks and the export are the same code.

    ``selector: l1`` is the paper's CSP_L1 ablation (App. "Ablation study for meta-RL"): no Ψ,
    every path on, and L1 on Φ(z)'s w in L_select's place, as ESPL_l1 does for ESPL; the task
    policy's "probs" are then all ones, so the export keeps every path with |w| above the
    threshold.
    """

    def _generators(self) -> tuple[EnsembleMLP, EnsembleMLP, EnsembleMLP]:
        net, a, hidden = self.symbolic, self.action_dim, self.config.generator_hidden
        return (
            EnsembleMLP(a, hidden, net.num_weights),
            EnsembleMLP(a, hidden, net.num_biases),
            EnsembleMLP(a, hidden, net.num_weights, last_bias=PSI_LAST_BIAS),
        )

    def init(self, key: jax.Array) -> Params:
        k_w, k_b, k_psi, k_std = jax.random.split(key, 4)
        z = jnp.zeros((self.latent_dim,))
        phi_w, phi_b, psi = self._generators()
        std = self._std_net().init(k_std, jnp.zeros((self.obs_dim + self.latent_dim,)))
        params = {"phi_w": phi_w.init(k_w, z), "phi_b": phi_b.init(k_b, z), "std": std}
        if self.uses_selector:
            params["psi"] = psi.init(k_psi, z)
        return params

    def _split(self, flat: jax.Array, rows_only: bool) -> list[jax.Array]:
        """(A, total) → one (A, rows, cols) array per layer, or (A, rows) for biases."""
        out, start = [], 0
        for rows, cols in self.symbolic.layer_shapes:
            size = rows if rows_only else rows * cols
            piece = flat[:, start : start + size]
            out.append(piece if rows_only else piece.reshape(self.action_dim, rows, cols))
            start += size
        return out

    def generate(self, params, z):
        phi_w, phi_b, psi = self._generators()
        mean = {
            "w": self._split(phi_w.apply(params["phi_w"], z), rows_only=False),
            "b": self._split(phi_b.apply(params["phi_b"], z), rows_only=True),
        }
        if not self.uses_selector:  # CSP_L1: every path on
            return {"mean": mean, "probs": selector.ones_mask(mean["w"]), "logits": [], "z": z}
        logits = self._split(psi.apply(params["psi"], z), rows_only=False)
        return {
            "mean": mean,
            "probs": [jax.nn.sigmoid(s) for s in logits],
            "logits": logits,
            "z": z,
        }

    def policy(self, params, part):
        return {**part, "std": params["std"]}

    def mean_and_log_std(self, policy, mask, obs):
        mean, penalty = self.symbolic.apply(policy["mean"], mask, obs)
        log_std = self._log_std(policy["std"], jnp.concatenate([obs, policy["z"]]))
        return mean, log_std, penalty

    def train_mask(self, key, policy, tau):
        if not self.uses_selector:
            return policy["probs"]  # all ones
        if self.config.csp_relaxed_mask == "soft":  # the authors' code: no straight-through
            return selector.soft_gumbel_sigmoid_mask(key, policy["probs"], tau)
        return selector.gumbel_sigmoid_mask(key, policy["probs"], tau)

    def collect_mask(self, key, policy):
        if not self.uses_selector:
            return policy["probs"]  # all ones
        return selector.bernoulli_mask(key, policy["probs"])

    def eval_mask(self, policy):
        return selector.deterministic_mask(policy["probs"], policy["mean"]["w"])

    def regularizers(self, policy, l_min):
        """L_select on σ(Ψ(z)) (CSP_L1: Σ|w| of Φ(z)); the authors' logit clamp
        Σ relu(|s| − 6), L1 on Φ's w and (``bias_l1_scale``, as for ESPL) on Φ's b."""
        cfg = self.config
        select = self.select_loss(policy, l_min)
        clamp = sum(jnp.sum(jax.nn.relu(jnp.abs(s) - LOGIT_BOUND)) for s in policy["logits"])
        l1 = _mean_abs(policy["mean"]["w"])
        extra = cfg.logit_clamp_scale * clamp + cfg.weight_l1_scale * l1
        if cfg.bias_l1_scale > 0:  # skipped at 0: configs without it compute exactly as before
            b_l1 = _mean_abs(policy["mean"]["b"])
            extra = extra + cfg.bias_l1_scale * b_l1
        return select, extra

    @property
    def has_extra_loss(self) -> bool:
        cfg = self.config
        return cfg.logit_clamp_scale > 0 or cfg.weight_l1_scale > 0 or cfg.bias_l1_scale > 0


@dataclass(frozen=True)
class PearlActor(Actor):
    """PEARL's policy: one MLP (300×3) on s ⊕ z with μ and log σ heads."""

    def _net(self) -> MLP:
        return MLP(self.config.pearl_hidden, 2 * self.action_dim)

    def init(self, key: jax.Array) -> Params:
        return {"net": self._net().init(key, jnp.zeros((self.obs_dim + self.latent_dim,)))}

    def policy(self, params, part):
        return {"net": params["net"], "z": part}

    def mean_and_log_std(self, policy, mask, obs):
        out = self._net().apply(policy["net"], jnp.concatenate([obs, policy["z"]]))
        a = self.action_dim
        return out[:a], jnp.clip(out[a:], LOG_STD_MIN, LOG_STD_MAX), jnp.zeros(())


@dataclass(frozen=True)
class HyperActor(Actor):
    """Hyper: z → hypernetwork → the weights of a one-hidden-layer (256) policy on s."""

    def _hyper(self) -> HyperNetwork:
        cfg = self.config
        return HyperNetwork(self.obs_dim, self.action_dim, cfg.hyper_policy_hidden, cfg.hyper_trunk)

    def init(self, key: jax.Array) -> Params:
        return {"hyper": self._hyper().init(key, jnp.zeros((self.latent_dim,)))}

    def generate(self, params, z):
        return self._hyper().apply(params["hyper"], z)

    def policy(self, params, part):
        return {"weights": part}

    def mean_and_log_std(self, policy, mask, obs):
        mean, log_std = generated_policy(policy["weights"], obs)
        return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX), jnp.zeros(())


SINGLE_TASK_ACTORS = {"symbolic": StoredSymbolic, "mlp": MLPActor}
META_ACTORS = {"symbolic": GeneratedSymbolic, "pearl": PearlActor, "hyper": HyperActor}


def make_actor(config: config_lib.Config, obs_dim: int, action_dim: int, latent_dim: int) -> Actor:
    """The policy kind of ``config.actor``: single-task kinds for latent_dim 0, meta-RL otherwise.

    The config validates the combination (``config.actor`` against the env); this only maps.
    """
    kinds = META_ACTORS if latent_dim else SINGLE_TASK_ACTORS
    return kinds[config.actor](
        config_lib.view(PolicyConfig, config), obs_dim, action_dim, latent_dim
    )
