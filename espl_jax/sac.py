"""Functional SAC over task batches: ESPL (Algorithm 1 lines 9–18) and CSP/PEARL/Hyper
(Algorithm 2 lines 13–30) are the same update.

Every update asks the task set (``espl_jax.task_sets``) for a batch of tasks (single-task: the
one task), per task an RL batch from its replay buffer and, for meta-RL, a context from its
encoder buffer, and for the tasks' latents: PEARL's encoder turns the context into q(z|c); a
reparameterised sample z conditions the critic (whose loss, with β·KL(q‖N(0,I)), trains the
encoder); the policy side and the targets see stop_gradient(z). A single task's z is (0,).

- Critic: twin Q with target networks and clipped double-Q (Haarnoja et al. 2018, Eq. 5 with the
  min of two Qs), y = scale·r + γ(1 − term)(min Q'(s', a', z) − α log π(a'|s', z)); the next
  action uses a fresh Bernoulli mask, as the authors' code does. Loss: the mean over tasks.
- Actor: ``L_actor = L_actor^SAC + α1·L_penalty + α2·L_select`` (Algorithm 1 line 14,
  Algorithm 2 line 24) over the policy's params, the policy gradient clipped by global norm,
  then projected (ESPL: p back onto [0, 1], App. C.1). L_select is divided by |A| as in the
  authors' code.
- α: tuned towards −|A| (Haarnoja et al. 2018b, Eq. 18), or fixed (``auto_alpha: false``).
- ``critic: crossq`` (Bhatt et al., ICLR 2024) changes the critic only: batch-renormalised
  critics (networks.BatchRenorm), no target network, y from the same critics evaluated on
  (s, a) and (s′, a′) in one forward pass in training mode (so both halves share the batch's
  statistics), stop_gradient on y, the critics' Adam with β1 0.5. The actor reads the critics
  in evaluation mode (running statistics). ``target_critic`` is then unused.

Order in one step (docs/design.md "One trainer"): critic and encoder, actor against the updated
critic, α, Polyak.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import optax
from flax import struct

from espl_jax import pearl, replay
from espl_jax.networks import TwinQ
from espl_jax.policies import Actor

Metrics = dict[str, jax.Array]


@dataclass(frozen=True)
class SACConfig:
    """The config keys the update reads (``espl_jax.config.Config`` documents each)."""

    batch_size: int
    learning_rate: float
    gamma: float
    reward_scale: float
    polyak: float
    alpha: float
    auto_alpha: bool
    critic: str
    critic_hidden: tuple[int, ...]
    critic_layer_norm: bool
    crossq_momentum: float
    crossq_warmup: int
    penalty_scale: float
    select_scale: float
    kl_weight: float


@struct.dataclass
class TrainState:
    """All mutable state of one run (one seed); vmapped over seeds by the trainer.

    Buffers have a leading task axis (single-task: 1); ``rollout`` has one slot per task being
    collected on (single-task: the one env, whose episodes continue across iterations; meta-RL:
    the visited tasks, reset at every phase). ``encoder*`` are None for single-task runs.
    """

    actor: dict[str, Any]
    critic: Any
    target_critic: Any
    log_alpha: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState
    encoder: Any
    encoder_opt: optax.OptState | None
    buffer: replay.ReplayBuffer
    encoder_buffer: replay.ReplayBuffer | None
    rollout: Any  # rollout.Rollout with a leading slot axis
    key: jax.Array
    iteration: jax.Array  # int32, completed training iterations
    env_steps: jax.Array  # int32
    episodes: jax.Array  # int32, finished training episodes
    # ESPL's hall-of-fame anchor (espl_jax.halloffame): the actor whose exported formula scored
    # best on the selection episodes from the end of the schedule on. None for meta-RL.
    anchor: dict[str, Any] | None = None
    anchor_return: jax.Array | None = None
    anchor_iteration: jax.Array | None = None


class TaskBatches(Protocol):
    """What the update asks of the task set (``espl_jax.task_sets.SingleTask``, ``MetaTasks``)."""

    @property
    def encoder(self) -> pearl.Encoder | None:
        """PEARL's context encoder, trained by the critic loss; None for a single task."""

    def sample_batch(
        self, state: TrainState, key: jax.Array, batch_size: int
    ) -> tuple[replay.Transition, replay.Transition | None]:
        """(RL batch [tasks, B, ...], context [tasks, C, ...] or None) for one update."""

    def latents(
        self, encoder: Any, context: replay.Transition | None, key: jax.Array, tasks: int
    ) -> tuple[jax.Array, jax.Array]:
        """z [tasks, L] (reparameterised) and Σ_tasks KL(q ‖ N(0, I))."""


def task_keys(key: jax.Array, n: int) -> jax.Array:
    """One key per task: ``key`` itself for one task (so a single-task run draws what it drew
    before runs had a task axis), else ``split(key, n)``."""
    return key[None] if n == 1 else jax.random.split(key, n)


@dataclass(frozen=True)
class SAC:
    """Static parts of the algorithm: networks, optimizers and hyperparameters.

    Attributes:
        config: the keys of the run's config the update reads.
        actor: the policy kind.
        tasks: the task set the batches and latents come from.
    """

    config: SACConfig
    actor: Actor
    tasks: TaskBatches

    @property
    def encoder(self) -> pearl.Encoder | None:
        """PEARL's context encoder (a task family's), trained here; None for a single task."""
        return self.tasks.encoder

    @property
    def obs_dim(self) -> int:
        return self.actor.obs_dim

    @property
    def action_dim(self) -> int:
        return self.actor.action_dim

    @property
    def crossq(self) -> bool:
        return self.config.critic == "crossq"

    @property
    def critic(self) -> TwinQ:
        cfg = self.config
        renorm = (cfg.crossq_momentum, cfg.crossq_warmup) if self.crossq else None
        return TwinQ(cfg.critic_hidden, cfg.critic_layer_norm, renorm)

    @property
    def critic_tx(self) -> optax.GradientTransformation:
        # The critic variables may hold batch statistics: their gradient is zero, and so is
        # Adam's step for them; update() then replaces them with the forward pass's.
        if self.crossq:
            return optax.adam(self.config.learning_rate, b1=0.5)
        return optax.adam(self.config.learning_rate)

    @property
    def alpha_tx(self) -> optax.GradientTransformation:
        return optax.adam(self.config.learning_rate)

    @property
    def encoder_tx(self) -> optax.GradientTransformation:
        return optax.adam(self.config.learning_rate)

    @property
    def target_entropy(self) -> float:
        return -float(self.action_dim)

    @property
    def context_dim(self) -> int:
        use_next = self.encoder is not None and self.encoder.use_next_obs
        return (2 if use_next else 1) * self.obs_dim + self.action_dim + 1

    def init_learner(self, key: jax.Array) -> dict[str, Any]:
        """Fresh actor, critics, targets, α, encoder and optimizer states."""
        k_actor, k_critic = jax.random.split(key)
        actor = self.actor.init(k_actor)
        z = jnp.zeros((self.actor.latent_dim,))
        critic = self.critic.init(
            k_critic, jnp.zeros((self.obs_dim,)), jnp.zeros((self.action_dim,)), z
        )
        log_alpha = jnp.asarray(math.log(self.config.alpha), jnp.float32)
        learner = {
            "actor": actor,
            "critic": critic,
            "target_critic": critic,
            "log_alpha": log_alpha,
            "actor_opt": self.actor.optimizer().init(actor),
            "critic_opt": self.critic_tx.init(critic),
            "alpha_opt": self.alpha_tx.init(log_alpha),
            "encoder": None,
            "encoder_opt": None,
        }
        if self.encoder is not None:  # the encoder's params live in the state with its optimizer
            encoder = self.encoder.init(jax.random.fold_in(key, 1), self.context_dim)
            learner.update(encoder=encoder, encoder_opt=self.encoder_tx.init(encoder))
        return learner

    # Losses --------------------------------------------------------------------------------

    def critic_loss(
        self,
        critic: Any,
        encoder: Any,
        state: TrainState,
        batch: replay.Transition,
        context: replay.Transition | None,
        key: jax.Array,
    ) -> tuple[jax.Array, tuple[Metrics, jax.Array, Any]]:
        """mean over tasks of Σ_i mean_batch (Q_i(s, a, z) − y)² + β Σ_tasks KL (Algorithm 2).

        Returns (loss, (metrics, z, batch statistics after the pass or None))."""
        actor, cfg = self.actor, self.config
        tasks, size = batch.reward.shape[:2]
        k_mask, k_act = jax.random.split(key)
        z, kl = self.tasks.latents(encoder, context, jax.random.fold_in(key, 1), tasks)
        alpha = jnp.exp(state.log_alpha)

        def next_action(b, z_t, k_mask_t, k_act_t):
            policy = actor.at(state.actor, jax.lax.stop_gradient(z_t))
            mask = actor.collect_mask(k_mask_t, policy)
            keys = jax.random.split(k_act_t, size)
            return jax.vmap(actor.sample, (0, None, None, 0))(keys, policy, mask, b.next_obs)[:2]

        next_act, next_log_prob = jax.vmap(next_action)(
            batch, z, task_keys(k_mask, tasks), task_keys(k_act, tasks)
        )
        if self.crossq:  # one pass over (s, a) and (s', a') of every task: shared statistics
            q_all, updated = self.critic.apply(
                critic,
                jnp.concatenate([batch.obs, batch.next_obs], axis=1),
                jnp.concatenate([batch.action, next_act], axis=1),
                z[:, None, :],
                train=True,
                mutable=["batch_stats"],
            )
            q, next_q = q_all[:, :size], q_all[:, size:].min(-1)
            batch_stats = updated["batch_stats"]
        else:
            next_q = jax.vmap(self.critic.apply, (None, 0, 0, 0))(
                state.target_critic, batch.next_obs, next_act, z
            ).min(-1)
            q = jax.vmap(self.critic.apply, (None, 0, 0, 0))(critic, batch.obs, batch.action, z)
            batch_stats = None
        soft_next = next_q - alpha * next_log_prob
        target = cfg.reward_scale * batch.reward + cfg.gamma * (1.0 - batch.terminated) * soft_next
        error = q - jax.lax.stop_gradient(target)[..., None]
        losses = jnp.sum(jnp.mean(error**2, axis=1), axis=-1)  # per task: Σ_i mean_batch
        critic_loss = jnp.mean(losses)
        loss, metrics = critic_loss, {"critic_loss": critic_loss, "q": jnp.mean(q)}
        if self.encoder is not None:  # the critic loss trains the encoder: + β·KL (Algorithm 2)
            loss = critic_loss + cfg.kl_weight * kl
            metrics["kl"] = kl / tasks
        return loss, (metrics, z, batch_stats)

    def actor_loss(
        self,
        params: dict,
        state: TrainState,
        batch: replay.Transition,
        z: jax.Array,
        key: jax.Array,
        tau: jax.Array,
        l_min: jax.Array,
    ) -> tuple[jax.Array, Metrics]:
        """mean(α log π − min Q) + α1·mean(L_penalty) + α2·L_select/|A| (+ the kind's extra
        terms), each averaged over the batch's tasks (Algorithm 1 line 14, Algorithm 2 line 24).
        ``z`` is already stop_gradient-ed."""
        actor, cfg = self.actor, self.config
        tasks, size = batch.reward.shape[:2]
        k_mask, k_act = jax.random.split(key)
        alpha = jnp.exp(state.log_alpha)

        def per_task(b, z_t, k_mask_t, k_act_t):
            policy = actor.at(params, z_t)
            mask = actor.train_mask(k_mask_t, policy, tau)
            keys = jax.random.split(k_act_t, size)
            action, log_prob, penalty = jax.vmap(actor.sample, (0, None, None, 0))(
                keys, policy, mask, b.obs
            )
            q = self.critic.apply(state.critic, b.obs, action, z_t).min(-1)
            select, extra = actor.regularizers(policy, l_min)
            sac = jnp.mean(alpha * log_prob - q)
            return sac, jnp.mean(penalty), select, extra, jnp.mean(log_prob), actor.l0_ratio(policy)

        sac, penalty, select, extra, log_prob, l0 = jax.vmap(per_task)(
            batch, z, task_keys(k_mask, tasks), task_keys(k_act, tasks)
        )
        sac_loss, penalty, select = jnp.mean(sac), jnp.mean(penalty), jnp.mean(select)
        loss = sac_loss + cfg.penalty_scale * penalty + cfg.select_scale * select / self.action_dim
        if actor.has_extra_loss:
            loss = loss + jnp.mean(extra)
        metrics = {
            "actor_loss": sac_loss,
            "penalty": penalty,
            "select_loss": select,
            "log_prob": jnp.mean(log_prob),
            "batch_l0_ratio": jnp.mean(l0),
        }
        return loss, metrics

    # One gradient step ----------------------------------------------------------------------

    def update(
        self,
        state: TrainState,
        key: jax.Array,
        tau: jax.Array,
        l_min: jax.Array,
        frozen: jax.Array | None = None,
    ) -> tuple[TrainState, Metrics]:
        """One SAC step: critic (and encoder), actor, α, then Polyak. ``frozen`` (ESPL's
        fine-tune phase) keeps the path probabilities where they are."""
        k_batch, k_critic, k_actor = jax.random.split(key, 3)
        batch, context = self.tasks.sample_batch(state, k_batch, self.config.batch_size)

        (_, (c_metrics, z, batch_stats)), (c_grads, e_grads) = jax.value_and_grad(
            self.critic_loss, argnums=(0, 1), has_aux=True
        )(state.critic, state.encoder, state, batch, context, k_critic)
        c_updates, critic_opt = self.critic_tx.update(c_grads, state.critic_opt, state.critic)
        critic = optax.apply_updates(state.critic, c_updates)
        if batch_stats is not None:
            critic = {**critic, "batch_stats": batch_stats}
        state = state.replace(critic=critic, critic_opt=critic_opt)
        if self.encoder is not None:  # the encoder's step, from the critic loss's gradient
            e_updates, encoder_opt = self.encoder_tx.update(
                e_grads, state.encoder_opt, state.encoder
            )
            state = state.replace(
                encoder=optax.apply_updates(state.encoder, e_updates), encoder_opt=encoder_opt
            )

        (_, a_metrics), a_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor, state, batch, jax.lax.stop_gradient(z), k_actor, tau, l_min
        )
        tx = self.actor.optimizer()
        a_updates, actor_opt = tx.update(a_grads, state.actor_opt, state.actor)
        actor = self.actor.project(optax.apply_updates(state.actor, a_updates))
        if frozen is not None:
            probs = jax.tree.map(
                lambda old, new: jnp.where(frozen, old, new), state.actor["probs"], actor["probs"]
            )
            actor = {**actor, "probs": probs}

        log_alpha, alpha_opt = state.log_alpha, state.alpha_opt
        if self.config.auto_alpha:

            def alpha_loss(log_alpha):
                entropy_gap = jax.lax.stop_gradient(a_metrics["log_prob"] + self.target_entropy)
                return -log_alpha * entropy_gap

            alpha_grad = jax.grad(alpha_loss)(state.log_alpha)
            alpha_updates, alpha_opt = self.alpha_tx.update(alpha_grad, state.alpha_opt)
            log_alpha = optax.apply_updates(state.log_alpha, alpha_updates)

        target = state.target_critic
        if not self.crossq:  # CrossQ has no target network
            target = optax.incremental_update(critic, target, self.config.polyak)
        state = state.replace(
            actor=actor,
            actor_opt=actor_opt,
            log_alpha=log_alpha,
            alpha_opt=alpha_opt,
            target_critic=target,
        )
        metrics = {**c_metrics, **a_metrics, "alpha": jnp.exp(log_alpha)}
        return state, metrics
