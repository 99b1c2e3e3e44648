"""Collection, evaluation and PEARL's protocol, for one task at a time (the trainer vmaps over
seeds and tasks): the one rollout path of every env, written against ``envs.Environment``. The
JAX envs step inside the program; the host-stepped ones (MuJoCo's C engine, gymnasium's Box2D)
through one host callback per env step for the whole vmapped batch.

- ``collect``: K env steps of the exploring policy with auto-reset (Algorithm 1 lines 5–7,
  Algorithm 2 lines 6–10). ESPL draws its Bernoulli mask once per iteration and continues its
  episodes across iterations; the meta-RL phases reset first and draw a new z (and CSP a new
  mask) at the start of every trajectory, as PEARL's sampler does (``draw``).
- ``evaluate``: deterministic episodes of one fixed task policy; ``evaluate_learned``, of a
  single-task run's exported formula.
- ``adapt_and_evaluate``: PEARL's test-task protocol for one run on one task (docs/design.md
  "One trainer"): start from the prior, collect whole trajectories until ``eval_steps``,
  the context accumulating online from the run itself; after ``exploration_trajectories``
  trajectories z is a sample of the posterior of every transition so far, re-drawn after each
  trajectory; actions are deterministic (CSP: the formula of p > 0.5); the return of the last
  trajectory is reported. ``runs_on_tasks`` repeats it on a batch of tasks.

Only ``terminated`` is stored in transitions; at an episode end (time limit or not) the stored
next_obs is the true final observation, not the reset one (``Environment.step_autoreset``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from espl_jax import pearl
from espl_jax.policies import Actor, TaskPolicy, no_latent
from espl_jax.replay import Transition

Draw = Callable[[jax.Array], tuple[Any, Any]]  # episode index -> (z-dependent part, mask)


@struct.dataclass
class Rollout:
    """The exploring agent in one env: env state, current observation, return of the episode in
    progress and the AR(1) exploration noise ε of the last step (action_dim,)."""

    env_state: Any
    obs: jax.Array
    episode_return: jax.Array
    exploration_noise: jax.Array


def where(pred: jax.Array, a: Any, b: Any) -> Any:
    """Pytree ``a if pred else b`` (pred a scalar)."""
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def reset(env, task_params, key: jax.Array, action_dim: int) -> Rollout:
    obs, env_state = env.reset(key, task_params)
    return Rollout(env_state, obs, jnp.zeros(()), jnp.zeros(action_dim))


def explore(
    actor: Actor,
    rho: float,
    policy: TaskPolicy,
    mask: Any,
    obs: jax.Array,
    eps: jax.Array,
    key: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """One exploration step for one observation: the action and the new noise ε.

    The action is tanh(μ + σ ε). With ``exploration_correlation`` ρ > 0, ε is an AR(1) process,
    ε_t = ρ ε_{t−1} + √(1−ρ²) ξ_t: still N(0, 1) at every step, so the policy's distribution per
    step is unchanged, but successive pushes agree for ~1/(1−ρ) steps (temporally correlated
    exploration; ρ = 0 is plain SAC).
    """
    eps = rho * eps + math.sqrt(1.0 - rho**2) * jax.random.normal(key, eps.shape)
    return actor.act_with_noise(policy, mask, obs, eps), eps


def collect(
    env,
    actor: Actor,
    rho: float,
    rollout: Rollout,
    task_params: Any,
    actor_params: Any,
    part: Any,
    mask: Any,
    key: jax.Array,
    steps: int,
    draw: Draw | None = None,
) -> tuple[Rollout, Transition, jax.Array, jax.Array]:
    """``steps`` env steps on one task; resets finished episodes.

    Args:
        rollout: where the agent is (a fresh ``reset`` to start a phase from scratch).
        actor_params: the learned params.
        part, mask: the z-dependent part of the task policy (``Actor.generate``) and the mask
            to act with, until ``draw`` replaces them.
        draw: if given, ``draw(i) -> (part, mask)`` gives the policy of the i-th episode of this
            call, at its first step (a new z per trajectory); else the policy is fixed.

    Returns:
        (rollout, transitions [K], done [K], finished_returns [K]): done marks the steps that
        ended an episode, finished_returns holds that episode's return there (0 elsewhere).
    """

    def step(carry, k):
        r, part, mask, fresh, episode = carry
        k_act, k_env, k_reset = jax.random.split(k, 3)
        if draw is not None:
            part, mask = where(fresh, draw(episode), (part, mask))
        policy = actor.policy(actor_params, part)
        action, eps = explore(actor, rho, policy, mask, r.obs, r.exploration_noise, k_act)
        s = env.step_autoreset(k_env, k_reset, r.env_state, action, task_params)
        done = s.reset  # every ended episode is reset
        ep_return = r.episode_return + s.reward
        out = (
            Transition(r.obs, action, s.reward, s.obs, s.terminated),
            done,
            jnp.where(done, ep_return, 0.0),
        )
        r = Rollout(s.next_state, s.next_obs, jnp.where(done, 0.0, ep_return), eps)
        return (r, part, mask, done, episode + done.astype(jnp.int32)), out

    keys = jax.random.split(key, steps)
    init = (rollout, part, mask, jnp.asarray(True), jnp.zeros((), jnp.int32))
    (rollout, *_), (transitions, done, finished) = jax.lax.scan(step, init, keys)
    return rollout, transitions, done, finished


def evaluate(
    env, actor: Actor, policy: TaskPolicy, mask: Any, task_params: Any, key: jax.Array, episodes
) -> jax.Array:
    """Returns [episodes] of deterministic episodes of a fixed task policy (and mask): a scan of
    ``horizon`` steps, rewards counted until each episode's end (later steps are ignored)."""
    k_reset, k_run = jax.random.split(key)
    obs, env_state = jax.vmap(env.reset, (0, None))(
        jax.random.split(k_reset, episodes), task_params
    )

    def step(carry, k):
        obs, env_state, total, done = carry
        action = jax.vmap(actor.deterministic, (None, None, 0))(policy, mask, obs)
        keys = jax.random.split(k, episodes)
        obs, env_state, reward, terminated, truncated, _ = jax.vmap(env.step, (0, 0, 0, None))(
            keys, env_state, action, task_params
        )
        total = total + jnp.where(done, 0.0, reward)
        return (obs, env_state, total, done | terminated | truncated), None

    init = (obs, env_state, jnp.zeros(episodes), jnp.zeros(episodes, bool))
    (_, _, total, _), _ = jax.lax.scan(step, init, jax.random.split(k_run, env.horizon))
    return total


def evaluate_learned(
    env, actor: Actor, actor_params: Any, task_params: Any, key: jax.Array, episodes: int
) -> jax.Array:
    """Single task: returns [episodes] of deterministic episodes of the learned params'
    eval-mask policy (the exported formula)."""
    policy = actor.at(actor_params, no_latent())
    return evaluate(env, actor, policy, actor.eval_mask(policy), task_params, key, episodes)


@struct.dataclass
class Adapted:
    """What one run of the protocol ends with."""

    final_return: jax.Array  # return of the last complete trajectory
    first_return: jax.Array  # return of the first trajectory (z from the prior)
    trajectories: jax.Array  # number of trajectories collected
    z: jax.Array  # (L,) the latent of the last trajectory: its formula is the adapted policy


def adapt_and_evaluate(
    env,
    actor: Actor,
    encoder: pearl.Encoder,
    actor_params: Any,
    encoder_params: Any,
    task_params: Any,
    key: jax.Array,
    eval_steps: int,
    exploration_trajectories: int,
) -> Adapted:
    """PEARL's protocol for one run on one task (module docstring); fixed-size scan of
    ``eval_steps + horizon`` steps, idle once the budget is used and the trajectory is over."""
    latent = encoder.latent_dim

    def task_policy(z):
        part = actor.generate(actor_params, z)
        return part, actor.eval_mask(actor.policy(actor_params, part))

    k_z, k_reset, k_run = jax.random.split(key, 3)
    z = jax.random.normal(k_z, (latent,))
    obs, env_state = env.reset(k_reset, task_params)
    part, mask = task_policy(z)
    zero = jnp.zeros(())
    init = dict(
        env_state=env_state, obs=obs, ep_return=zero, steps=jnp.zeros((), jnp.int32),
        trajectories=jnp.zeros((), jnp.int32), posterior=pearl.Posterior.empty(latent), z=z,
        part=part, mask=mask, final=zero, first=zero, active=jnp.asarray(True),
    )  # fmt: skip

    def step(c, k):
        k_env, k_reset, k_z = jax.random.split(k, 3)
        active = c["active"]
        policy = actor.policy(actor_params, c["part"])
        action = actor.deterministic(policy, c["mask"], c["obs"])
        # A trajectory that ends within the budget is followed by another (``again``).
        s = env.step_autoreset(
            k_env, k_reset, c["env_state"], action, task_params,
            may_reset=active & (c["steps"] + 1 < eval_steps),
        )  # fmt: skip
        reward, next_obs = s.reward, s.obs
        mu, var = encoder.factors(
            encoder_params, Transition(c["obs"], action, reward, next_obs, s.terminated)
        )
        posterior = c["posterior"].add(mu, var, jnp.where(active, 1.0, 0.0))
        ep_return = c["ep_return"] + jnp.where(active, reward, 0.0)
        steps = c["steps"] + active.astype(jnp.int32)
        ended = active & (s.terminated | s.truncated)
        trajectories = c["trajectories"] + ended.astype(jnp.int32)
        again = s.reset  # = ended & (steps < eval_steps)
        # The next trajectory's z: the posterior once enough trajectories exist, else the prior.
        post_mu, post_var = posterior.gaussian()
        use_posterior = trajectories >= exploration_trajectories
        noise = jax.random.normal(k_z, (latent,))
        new_z = jnp.where(use_posterior, post_mu + jnp.sqrt(post_var) * noise, noise)
        new_part, new_mask = task_policy(new_z)
        c = dict(
            env_state=s.next_state,
            obs=s.next_obs,
            ep_return=jnp.where(again, 0.0, ep_return),
            steps=steps,
            trajectories=trajectories,
            posterior=posterior,
            z=jnp.where(again, new_z, c["z"]),
            part=where(again, new_part, c["part"]),
            mask=where(again, new_mask, c["mask"]),
            final=jnp.where(ended, ep_return, c["final"]),
            first=jnp.where(ended & (trajectories == 1), ep_return, c["first"]),
            active=active & ~(ended & ~again),
        )
        return c, None

    keys = jax.random.split(k_run, eval_steps + env.horizon)
    c, _ = jax.lax.scan(step, init, keys)
    return Adapted(c["final"], c["first"], c["trajectories"], c["z"])


def runs_on_tasks(
    run: Callable[[Any, jax.Array], Any], task_params: Any, key: jax.Array, runs: int
):
    """``run(task params, key)`` — one run of the protocol (``adapt_and_evaluate``) — ``runs``
    times on each task of ``task_params`` [N], each with its own key: leaves [N, runs]."""
    n = jax.tree.leaves(task_params)[0].shape[0]
    keys = jax.random.split(key, n * runs).reshape(n, runs, -1)
    return jax.vmap(jax.vmap(run, (None, 0)), (0, 0))(task_params, keys)
