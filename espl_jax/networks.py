"""Neural pieces around the symbolic policy: twin critics, the std network F(s), the MLP baseline.

The ``Actor`` bundles a mean function (symbolic network, or an MLP for the neural baseline) with the
std network F(s) (§3.3: "a small neural network F(s) ... to output the standard deviation") and the
path-selector masks, so the SAC losses treat both actor kinds alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from espl_jax import selector
from espl_jax.config import Config
from espl_jax.symbolic import SymbolicNetwork, get_layout

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # clamp of log σ (authors' code, as in SAC)


class MLP(nn.Module):
    """ReLU MLP with a linear output layer."""

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.out)(x)


class TwinQ(nn.Module):
    """Two independent Q(s, a) MLPs (clipped double-Q of SAC). Returns shape (..., 2)."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        q1 = MLP(self.hidden, 1, name="q1")(x)
        q2 = MLP(self.hidden, 1, name="q2")(x)
        return jnp.concatenate([q1, q2], axis=-1)


@dataclass(frozen=True)
class Actor:
    """The policy a ~ tanh(N(mean(s), exp(log_std(s)))) with a maskable symbolic mean.

    Params pytree: {"mean": symbolic {"w", "b"} or MLP params, "probs": selector probabilities
    shaped like the symbolic weights (empty for the MLP actor or the L1 ablation), "std": F(s)}.
    """

    config: Config
    obs_dim: int
    action_dim: int

    @property
    def symbolic(self) -> SymbolicNetwork | None:
        if self.config.actor != "symbolic":
            return None
        return SymbolicNetwork(get_layout(self.config.layout), self.obs_dim, self.action_dim)

    @property
    def uses_selector(self) -> bool:
        return self.symbolic is not None and self.config.selector == "probabilistic"

    def _mlp_mean(self) -> MLP:
        return MLP(self.config.mlp_actor_hidden, self.action_dim)

    def _std_net(self) -> MLP:
        return MLP(self.config.std_hidden, self.action_dim)

    def init(self, key: jax.Array) -> dict[str, Any]:
        k_mean, k_std = jax.random.split(key)
        dummy = jnp.zeros((self.obs_dim,))
        std = self._std_net().init(k_std, dummy)
        if self.symbolic is None:
            return {"mean": self._mlp_mean().init(k_mean, dummy), "probs": [], "std": std}
        mean = self.symbolic.init(k_mean)
        probs = selector.init_probs(mean["w"]) if self.uses_selector else []
        return {"mean": mean, "probs": probs, "std": std}

    # Masks ---------------------------------------------------------------------------------

    def train_mask(self, key: jax.Array, params: dict, tau: jax.Array) -> list | None:
        """Gumbel-sigmoid straight-through mask (Algorithm 1, line 11)."""
        if self.symbolic is None:
            return None
        if not self.uses_selector:
            return selector.ones_mask(params["mean"]["w"])
        return selector.gumbel_sigmoid_mask(key, params["probs"], tau)

    def collect_mask(self, key: jax.Array, params: dict) -> list | None:
        """Bernoulli mask for data collection (Algorithm 1, line 4)."""
        if self.symbolic is None:
            return None
        if not self.uses_selector:
            return selector.ones_mask(params["mean"]["w"])
        return selector.bernoulli_mask(key, params["probs"])

    def eval_mask(self, params: dict) -> list | None:
        """The exported formula's mask: p > 0.5 and |w| > 1e-3."""
        if self.symbolic is None:
            return None
        probs = params["probs"] if self.uses_selector else selector.ones_mask(params["mean"]["w"])
        return selector.deterministic_mask(probs, params["mean"]["w"])

    # Forward -------------------------------------------------------------------------------

    def mean(self, params: dict, mask: list | None, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Pre-tanh mean (action_dim,) and operator penalty (scalar) for one observation."""
        if self.symbolic is None:
            return self._mlp_mean().apply(params["mean"], obs), jnp.zeros(())
        return self.symbolic.apply(params["mean"], mask, obs)

    def log_std(self, params: dict, obs: jax.Array) -> jax.Array:
        return jnp.clip(self._std_net().apply(params["std"], obs), LOG_STD_MIN, LOG_STD_MAX)

    def sample(
        self, key: jax.Array, params: dict, mask: list | None, obs: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """a = tanh(μ + σ ε) with its log-probability and the operator penalty, for one obs."""
        mean, penalty = self.mean(params, mask, obs)
        log_std = self.log_std(params, obs)
        u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        return jnp.tanh(u), tanh_gaussian_log_prob(u, mean, log_std), penalty

    def act_with_noise(
        self, params: dict, mask: list | None, obs: jax.Array, eps: jax.Array
    ) -> jax.Array:
        """a = tanh(μ + σ ε) for a given standard-normal ε (action_dim,): collection's action."""
        mean, _ = self.mean(params, mask, obs)
        return jnp.tanh(mean + jnp.exp(self.log_std(params, obs)) * eps)

    def deterministic(self, params: dict, mask: list | None, obs: jax.Array) -> jax.Array:
        return jnp.tanh(self.mean(params, mask, obs)[0])


def tanh_gaussian_log_prob(u: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """log π(tanh(u)) for u ~ N(mean, σ²): Gaussian log-density minus Σ log(1 − tanh(u)²).

    Uses log(1 − tanh(u)²) = 2 (log 2 − u − softplus(−2u)), stable for large |u| (SAC, App. C).
    """
    gauss = -0.5 * ((u - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)
    correction = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return jnp.sum(gauss - correction, axis=-1)
