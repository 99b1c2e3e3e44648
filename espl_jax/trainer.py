"""Single-task ESPL trainer: Algorithm 1 as one jitted ``lax.scan`` per chunk, vmapped over seeds.

One *iteration* (Algorithm 1, lines 3–18): compute τ and l_min from the schedules, sample one
Bernoulli mask, collect ``steps_per_iteration`` env steps with a ~ tanh(N(SN(s), F(s))) (auto-reset
between episodes), append them to the replay buffer, then take ``updates_per_iteration`` SAC steps.
A *chunk* is ``lax.scan`` over iterations; it is compiled once and ``vmap``-ed over seeds. The host
only runs between chunks (see :mod:`espl_jax.run`).

An iteration is split into ``start_iteration`` (keys and mask), ``collect`` and ``learn`` (replay
insert and the SAC updates), with the exploration action in ``explore``: the host collector for
gymnasium (Box2D) envs (:mod:`espl_jax.host`) reuses all but ``collect``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp

import envs
from espl_jax import replay, selector
from espl_jax.config import Config, UserError
from espl_jax.sac import SAC, Metrics, TrainState


def make_env(name: str) -> envs.Environment | envs.HostEnv:
    """``envs.make`` with the unknown-name error turned into a user error."""
    try:
        return envs.make(name)
    except ValueError as err:
        raise UserError(str(err)) from None


@dataclass(frozen=True)
class Trainer:
    """Static description of a run: config, environment and algorithm. Hashable (jit-static)."""

    config: Config

    @cached_property
    def env(self) -> envs.Environment | envs.HostEnv:
        return make_env(self.config.env)

    @property
    def on_host(self) -> bool:
        """The env is a gymnasium env stepped on the host (Box2D): collection and evaluation run
        in :mod:`espl_jax.host`; ``collect``, ``iteration``, ``chunk`` and ``evaluate`` here are
        for JAX envs only."""
        return envs.is_host(self.env)

    @cached_property
    def sac(self) -> SAC:
        return SAC(self.config, self.env.obs_dim, self.env.action_dim)

    @property
    def buffer_capacity(self) -> int:
        cfg = self.config
        wanted = min(cfg.buffer_size, cfg.total_env_steps)
        return replay.capacity_for(wanted, cfg.steps_per_iteration)

    # State ---------------------------------------------------------------------------------

    def init(self, key: jax.Array) -> TrainState:
        """A fresh TrainState for one seed. ``key`` is a raw uint32[2] key (checkpointable).

        For a host env there is no env state in JAX: ``env_state`` is None and ``obs`` zeros
        until the host collector resets its envs (see :mod:`espl_jax.host`).
        """
        key, k_learner, k_reset = jax.random.split(key, 3)
        if self.on_host:
            obs, env_state = jnp.zeros(self.env.obs_dim), None
        else:
            obs, env_state = self.env.reset(k_reset, self.env.default_params)
        zero_i = jnp.zeros((), jnp.int32)
        return TrainState(
            **self.sac.init_learner(k_learner),
            buffer=replay.init(self.buffer_capacity, self.env.obs_dim, self.env.action_dim),
            env_state=env_state,
            obs=obs,
            episode_return=jnp.zeros(()),
            exploration_noise=jnp.zeros(self.env.action_dim),
            key=key,
            iteration=zero_i,
            env_steps=zero_i,
            episodes=zero_i,
        )

    def init_seeds(self) -> TrainState:
        """States for ``config.seeds`` seeds stacked on a leading axis."""
        keys = jax.random.split(jax.random.PRNGKey(self.config.seed), self.config.seeds)
        return jax.jit(jax.vmap(self.init))(keys)

    # Collection -----------------------------------------------------------------------------

    def explore(
        self, actor_params: dict, mask: list | None, obs: jax.Array, eps: jax.Array, key: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """One exploration step for one observation: the action and the new noise ε.

        The action is tanh(μ + σ ε). With ``exploration_correlation`` ρ > 0, ε is an AR(1)
        process, ε_t = ρ ε_{t−1} + √(1−ρ²) ξ_t: still N(0, 1) at every step, so the policy's
        distribution per step is unchanged, but successive pushes agree for ~1/(1−ρ) steps
        (temporally correlated exploration; white noise, ρ = 0, is plain SAC). Both collectors
        (``collect`` in JAX, :mod:`espl_jax.host` for host envs) act through this function.
        """
        rho = self.config.exploration_correlation
        eps = rho * eps + math.sqrt(1.0 - rho**2) * jax.random.normal(key, eps.shape)
        return self.sac.actor.act_with_noise(actor_params, mask, obs, eps), eps

    def record_collection(
        self,
        state: TrainState,
        *,
        env_state: Any,
        obs: jax.Array,
        episode_return: jax.Array,
        exploration_noise: jax.Array,
        done: jax.Array,
        finished_returns: jax.Array,
    ) -> tuple[TrainState, Metrics]:
        """The state and metrics after K collection steps (shared by both collectors).

        ``done`` (K,) marks the steps that ended an episode, ``finished_returns`` (K,) holds the
        return of the episode ended at that step (0 elsewhere).
        """
        finished = jnp.sum(done)
        state = state.replace(
            env_state=env_state,
            obs=obs,
            episode_return=episode_return,
            exploration_noise=exploration_noise,
            env_steps=state.env_steps + self.config.steps_per_iteration,
            episodes=state.episodes + finished,
        )
        metrics = {
            "episodes_finished": finished,
            "train_return": jnp.sum(finished_returns) / jnp.maximum(finished, 1),
        }
        return state, metrics

    def collect(
        self, state: TrainState, mask: list | None, key: jax.Array
    ) -> tuple[TrainState, replay.Transition, Metrics]:
        """K env steps with one fixed mask (Algorithm 1, lines 5–7); resets finished episodes.

        Actions come from :meth:`explore`. Only ``terminated`` is stored; at a time-limit end the
        stored next_obs is the true next observation, not the reset one.
        """
        env, params = self.env, self.env.default_params

        def step(carry, k):
            env_state, obs, ep_return, eps = carry
            k_act, k_env, k_reset = jax.random.split(k, 3)
            action, eps = self.explore(state.actor, mask, obs, eps, k_act)
            next_obs, next_state, reward, terminated, truncated, _ = env.step(
                k_env, env_state, action, params
            )
            done = terminated | truncated
            reset_obs, reset_state = env.reset(k_reset, params)
            env_state = jax.tree.map(lambda r, n: jnp.where(done, r, n), reset_state, next_state)
            ep_return = ep_return + reward
            out = (
                replay.Transition(obs, action, reward, next_obs, terminated),
                done,
                jnp.where(done, ep_return, 0.0),
            )
            carry = (
                env_state,
                jnp.where(done, reset_obs, next_obs),
                jnp.where(done, 0.0, ep_return),
                eps,
            )
            return carry, out

        keys = jax.random.split(key, self.config.steps_per_iteration)
        carry = (state.env_state, state.obs, state.episode_return, state.exploration_noise)
        (env_state, obs, ep_return, eps), (transitions, done, finished_returns) = jax.lax.scan(
            step, carry, keys
        )
        state, metrics = self.record_collection(
            state,
            env_state=env_state,
            obs=obs,
            episode_return=ep_return,
            exploration_noise=eps,
            done=done,
            finished_returns=finished_returns,
        )
        return state, transitions, metrics

    # One iteration and a chunk of them --------------------------------------------------------

    def schedules(self, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(τ, l_min) at iteration t (Algorithm 1, lines 3 and 8)."""
        cfg = self.config
        tau = selector.temperature(t, cfg.schedule_iterations, cfg.target_temperature)
        l_min = selector.l_min_schedule(t, cfg.schedule_iterations, cfg.target_l0_ratio)
        return tau, l_min

    def start_iteration(
        self, key: jax.Array, actor_params: dict
    ) -> tuple[jax.Array, list | None, jax.Array, jax.Array]:
        """The iteration's randomness: (next state key, Bernoulli mask, collect key, update key).

        The mask is Algorithm 1, line 4; one mask serves the whole collection of the iteration.
        """
        key, k_mask, k_collect, k_update = jax.random.split(key, 4)
        return key, self.sac.actor.collect_mask(k_mask, actor_params), k_collect, k_update

    def learn(
        self,
        state: TrainState,
        transitions: replay.Transition,
        collect_metrics: Metrics,
        key: jax.Array,
    ) -> tuple[TrainState, Metrics]:
        """The rest of an iteration after collection: store the K transitions, take
        ``updates_per_iteration`` SAC steps in one scan (Algorithm 1, lines 8–17), count it."""
        tau, l_min = self.schedules(state.iteration)
        state = state.replace(buffer=replay.insert(state.buffer, transitions))

        def update(s, k):
            return self.sac.update(s, k, tau, l_min)

        keys = jax.random.split(key, self.config.updates_per_iteration)
        state, u_metrics = jax.lax.scan(update, state, keys)
        state = state.replace(iteration=state.iteration + 1)
        metrics = {
            **collect_metrics,
            **jax.tree.map(jnp.mean, u_metrics),
            "tau": tau,
            "l_min": l_min,
            "l0_ratio": self.l0_ratio(state),
            "env_steps": state.env_steps,
            "episodes": state.episodes,
            "iteration": state.iteration,
        }
        return state, metrics

    def iteration(self, state: TrainState) -> tuple[TrainState, Metrics]:
        """One iteration of Algorithm 1 in JAX (collection in the JAX env, then ``learn``)."""
        key, mask, k_collect, k_update = self.start_iteration(state.key, state.actor)
        state, transitions, c_metrics = self.collect(state, mask, k_collect)
        return self.learn(state.replace(key=key), transitions, c_metrics, k_update)

    def l0_ratio(self, state: TrainState) -> jax.Array:
        """E||m||_0 / N: the fraction of paths the selector keeps in expectation (1 without one)."""
        probs = state.actor["probs"]
        if not probs:
            return jnp.ones(())
        return selector.expected_l0(probs) / selector.count(probs)

    def chunk(self, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
        """``length`` iterations in one scan, for one seed."""
        return jax.lax.scan(lambda s, _: self.iteration(s), state, None, length=length)

    def compiled_chunk(self, length: int):
        """jit(vmap(chunk)) over the leading seed axis; the state buffers are donated."""
        return jax.jit(jax.vmap(lambda s: self.chunk(s, length)), donate_argnums=0)

    # Deterministic evaluation in JAX ---------------------------------------------------------

    def evaluate(self, actor_params: dict, key: jax.Array, episodes: int) -> jax.Array:
        """Returns of ``episodes`` deterministic episodes (eval mask: the exported formula)."""
        env, actor, params = self.env, self.sac.actor, self.env.default_params
        mask = actor.eval_mask(actor_params)
        k_reset, k_run = jax.random.split(key)
        obs, env_state = jax.vmap(env.reset, (0, None))(jax.random.split(k_reset, episodes), params)

        def step(carry, k):
            obs, env_state, total, done = carry
            action = jax.vmap(actor.deterministic, (None, None, 0))(actor_params, mask, obs)
            keys = jax.random.split(k, episodes)
            obs, env_state, reward, terminated, truncated, _ = jax.vmap(env.step, (0, 0, 0, None))(
                keys, env_state, action, params
            )
            total = total + jnp.where(done, 0.0, reward)
            return (obs, env_state, total, done | terminated | truncated), None

        init = (obs, env_state, jnp.zeros(episodes), jnp.zeros(episodes, bool))
        (_, _, total, _), _ = jax.lax.scan(step, init, jax.random.split(k_run, env.horizon))
        return total

    def compiled_evaluate(self, episodes: int):
        """jit(vmap(evaluate)) over seeds: (actor params [S, ...], keys [S, 2]) -> [S, E].

        JAX envs only; ``host.HostEvaluator`` is the counterpart for host envs.
        """
        return jax.jit(jax.vmap(lambda p, k: self.evaluate(p, k, episodes)))
