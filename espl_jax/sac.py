"""Functional SAC with the symbolic actor (ESPL §3.3, Algorithm 1 lines 9–18).

Critic: twin Q with target networks and clipped double-Q (Haarnoja et al. 2018, Eq. 5 with the
min of two Qs). Actor: ``L_actor = L_actor^SAC + α1·L_penalty + α2·L_select`` (Algorithm 1, line 14)
over w, b, p and the std network θ_F, with the policy gradient clipped by global norm; p is
projected back onto [0, 1] after each step (App. C.1). Entropy temperature α is tuned
automatically towards a target entropy of −|A| (Haarnoja et al. 2018b, Eq. 18).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from espl_jax import replay, selector
from espl_jax.config import Config
from espl_jax.networks import Actor, TwinQ

Metrics = dict[str, jax.Array]


@struct.dataclass
class TrainState:
    """All mutable state of one run (one seed); vmapped over seeds by the trainer."""

    actor: dict[str, Any]
    critic: Any
    target_critic: Any
    log_alpha: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState
    buffer: replay.ReplayBuffer
    env_state: Any
    obs: jax.Array
    episode_return: jax.Array  # return of the episode in progress
    exploration_noise: jax.Array  # (action_dim,) the ε of the last collection step
    key: jax.Array
    iteration: jax.Array  # int32, completed training iterations
    env_steps: jax.Array  # int32
    episodes: jax.Array  # int32, finished training episodes


@dataclass(frozen=True)
class SAC:
    """Static parts of the algorithm: networks, optimizers and hyperparameters."""

    config: Config
    obs_dim: int
    action_dim: int

    @property
    def actor(self) -> Actor:
        return Actor(self.config, self.obs_dim, self.action_dim)

    @property
    def critic(self) -> TwinQ:
        return TwinQ(self.config.critic_hidden)

    @property
    def actor_tx(self) -> optax.GradientTransformation:
        cfg = self.config
        per_group = optax.multi_transform(
            {
                "probs": optax.adam(cfg.probs_learning_rate),
                "rest": optax.adam(cfg.actor_learning_rate),
            },
            lambda params: {
                k: jax.tree.map(lambda _, k=k: "probs" if k == "probs" else "rest", v)
                for k, v in params.items()
            },
        )
        return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), per_group)

    @property
    def critic_tx(self) -> optax.GradientTransformation:
        return optax.adam(self.config.learning_rate)

    @property
    def alpha_tx(self) -> optax.GradientTransformation:
        return optax.adam(self.config.learning_rate)

    @property
    def target_entropy(self) -> float:
        return -float(self.action_dim)

    def init_learner(self, key: jax.Array) -> dict[str, Any]:
        """Fresh actor, critics, targets, α and optimizer states."""
        k_actor, k_critic = jax.random.split(key)
        actor = self.actor.init(k_actor)
        critic = self.critic.init(
            k_critic, jnp.zeros((self.obs_dim,)), jnp.zeros((self.action_dim,))
        )
        log_alpha = jnp.zeros(())
        return {
            "actor": actor,
            "critic": critic,
            "target_critic": critic,
            "log_alpha": log_alpha,
            "actor_opt": self.actor_tx.init(actor),
            "critic_opt": self.critic_tx.init(critic),
            "alpha_opt": self.alpha_tx.init(log_alpha),
        }

    # Losses --------------------------------------------------------------------------------

    def critic_loss(
        self, critic: Any, state: TrainState, batch: replay.Transition, key: jax.Array
    ) -> tuple[jax.Array, Metrics]:
        """Σ_i mean (Q_i(s, a) − y)², y = r·scale + γ (1 − term)(min Q'(s', a') − α log π(a'|s')).

        The next action uses a fresh Bernoulli mask, as the authors' implementation does.
        """
        k_mask, k_act = jax.random.split(key)
        actor, cfg = self.actor, self.config
        mask = actor.collect_mask(k_mask, state.actor)
        keys = jax.random.split(k_act, batch.reward.shape[0])
        next_action, next_log_prob, _ = jax.vmap(actor.sample, (0, None, None, 0))(
            keys, state.actor, mask, batch.next_obs
        )
        next_q = self.critic.apply(state.target_critic, batch.next_obs, next_action).min(-1)
        soft_next = next_q - jnp.exp(state.log_alpha) * next_log_prob
        target = cfg.reward_scale * batch.reward + cfg.gamma * (1.0 - batch.terminated) * soft_next
        q = self.critic.apply(critic, batch.obs, batch.action)
        loss = jnp.sum(jnp.mean((q - jax.lax.stop_gradient(target)[:, None]) ** 2, axis=0))
        return loss, {"critic_loss": loss, "q": jnp.mean(q)}

    def actor_loss(
        self,
        params: dict,
        state: TrainState,
        batch: replay.Transition,
        key: jax.Array,
        tau: jax.Array,
        l_min: jax.Array,
    ) -> tuple[jax.Array, Metrics]:
        """mean(α log π − min Q) + α1·mean(L_penalty) + α2·L_select (Algorithm 1, line 14).

        L_select is divided by the number of action dimensions, as in the authors' code, so α2
        keeps its meaning across environments. For the L1 ablation α2 weighs Σ|w| instead.
        """
        k_mask, k_act = jax.random.split(key)
        actor, cfg = self.actor, self.config
        mask = actor.train_mask(k_mask, params, tau)
        keys = jax.random.split(k_act, batch.reward.shape[0])
        action, log_prob, penalty = jax.vmap(actor.sample, (0, None, None, 0))(
            keys, params, mask, batch.obs
        )
        q = self.critic.apply(state.critic, batch.obs, action).min(-1)
        sac_loss = jnp.mean(jnp.exp(state.log_alpha) * log_prob - q)
        if actor.uses_selector:
            regularizer = selector.select_loss(params["probs"], l_min)
        elif actor.symbolic is not None:
            regularizer = selector.l1_loss(params["mean"]["w"])
        else:
            regularizer = jnp.zeros(())
        penalty = jnp.mean(penalty)
        loss = (
            sac_loss
            + cfg.penalty_scale * penalty
            + cfg.select_scale * regularizer / self.action_dim
        )
        if actor.symbolic is not None and cfg.bias_l1_scale > 0:
            biases = jnp.concatenate([b.ravel() for b in params["mean"]["b"]])
            loss = loss + cfg.bias_l1_scale * jnp.mean(jnp.abs(biases))
        metrics = {
            "actor_loss": sac_loss,
            "penalty": penalty,
            "select_loss": regularizer,
            "log_prob": jnp.mean(log_prob),
        }
        return loss, metrics

    # One gradient step ----------------------------------------------------------------------

    def update(
        self, state: TrainState, key: jax.Array, tau: jax.Array, l_min: jax.Array
    ) -> tuple[TrainState, Metrics]:
        """One SAC step on a sampled batch: critic, actor (w, b, p, θ_F), α, then Polyak."""
        k_batch, k_critic, k_actor = jax.random.split(key, 3)
        batch = replay.sample(state.buffer, k_batch, self.config.batch_size)

        (_, c_metrics), c_grads = jax.value_and_grad(self.critic_loss, has_aux=True)(
            state.critic, state, batch, k_critic
        )
        c_updates, critic_opt = self.critic_tx.update(c_grads, state.critic_opt, state.critic)
        critic = optax.apply_updates(state.critic, c_updates)
        state = state.replace(critic=critic, critic_opt=critic_opt)

        (_, a_metrics), a_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor, state, batch, k_actor, tau, l_min
        )
        a_updates, actor_opt = self.actor_tx.update(a_grads, state.actor_opt, state.actor)
        actor = optax.apply_updates(state.actor, a_updates)
        actor = {**actor, "probs": selector.project_probs(actor["probs"])}

        def alpha_loss(log_alpha):
            entropy_gap = jax.lax.stop_gradient(a_metrics["log_prob"] + self.target_entropy)
            return -log_alpha * entropy_gap

        alpha_grad = jax.grad(alpha_loss)(state.log_alpha)
        alpha_updates, alpha_opt = self.alpha_tx.update(alpha_grad, state.alpha_opt)
        log_alpha = optax.apply_updates(state.log_alpha, alpha_updates)

        target = optax.incremental_update(critic, state.target_critic, self.config.polyak)
        state = state.replace(
            actor=actor,
            actor_opt=actor_opt,
            log_alpha=log_alpha,
            alpha_opt=alpha_opt,
            target_critic=target,
        )
        metrics = {**c_metrics, **a_metrics, "alpha": jnp.exp(log_alpha)}
        return state, metrics
