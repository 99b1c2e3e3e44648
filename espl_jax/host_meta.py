"""Meta-RL on host-stepped gymnasium task families (lunarlander_params): the same algorithm.

The counterpart of the JAX meta-RL collection (``Trainer.collect_meta``, ``Trainer.warmup``)
and of PEARL's protocol (``Trainer.adapt``) for a family whose env is a gymnasium (Box2D) env.
Only the env steps leave JAX; what runs where:

- jitted, vmapped over seeds: the choice of the visited tasks, the trajectories' latents and
  policies (``Trainer.draws``, from the prior or the posterior of the fresh encoder buffer),
  the exploring actions of all lanes, the buffer inserts and ``Trainer.learn``;
- on the host: one gymnasium env per (seed, visited task), built with the task's params
  (``TaskFamily.host_kwargs``), stepped in lock-step; an episode end resets that env and moves
  its lane to the phase's next trajectory policy.

Envs are rebuilt for every phase (PEARL's rollouts start from a reset), seeded from the keys, so
collection is reproducible for a given state. The protocol runs all seeds × test tasks × runs as
lanes; the posterior of a run's own context is accumulated online (``pearl.Posterior``) from the
encoder's per-transition factors, one jitted call per step for all lanes.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import pearl, replay, rollout
from espl_jax.host import env_seeds, host_chunk
from espl_jax.keys import HOST_WARMUP, salted
from espl_jax.learner import Trainer
from espl_jax.replay import Transition
from espl_jax.rollout import Adapted
from espl_jax.sac import Metrics, TrainState
from espl_jax.seeds import take


class HostMetaCollector:
    """``chunk(state, length)`` like ``Trainer.compiled_chunk(length)(state)``, and ``warmup``."""

    def __init__(self, trainer: Trainer):
        self.trainer = trainer
        self.env, self.family, self.cfg = trainer.env, trainer.family, trainer.config
        self.slots = trainer.rollout_slots
        actor, cfg = trainer.actor, trainer.config
        n = trainer.DRAWS_PER_PHASE

        def choose(key):
            key, k_tasks, k_prior, k_posterior, k_update = jax.random.split(key, 5)
            tasks = jax.random.choice(
                k_tasks, trainer.num_train_tasks, (self.slots,), replace=False
            )
            return key, tasks, k_prior, k_posterior, k_update

        def draws(state, tasks, key, posterior):
            k_context, k_draw = jax.random.split(key)
            mu, var = trainer.phase_latents(state, tasks, k_context, posterior)
            keys = jax.random.split(k_draw, tasks.shape[0])
            return jax.vmap(trainer.draws, (None, 0, 0, 0))(state.actor, mu, var, keys)

        def act(actor_params, parts, masks, episode, obs, eps, key):
            """One seed's lanes [R]: the exploring action of each lane's current trajectory."""

            def lane(part_d, mask_d, e, o, ep, k):
                part, mask = take((part_d, mask_d), e % n)
                policy = actor.policy(actor_params, part)
                return rollout.explore(actor, cfg.exploration_correlation, policy, mask, o, ep, k)

            keys = jax.random.split(key, obs.shape[0])
            return jax.vmap(lane)(parts, masks, episode, obs, eps, keys)

        def store(state, tasks, transitions, to_encoder, clear):
            encoder_buffer = state.encoder_buffer
            if clear:
                encoder_buffer = replay.clear(encoder_buffer, tasks)
            buffer = replay.insert(state.buffer, tasks, transitions)
            if to_encoder:
                encoder_buffer = replay.insert(encoder_buffer, tasks, transitions)
            return state.replace(buffer=buffer, encoder_buffer=encoder_buffer)

        def learn(state, done, finished, key):
            state, c_metrics = trainer.record_collection(
                state,
                rollout_state=state.rollout,
                done=done,
                finished_returns=finished,
                steps=trainer.steps_per_iteration,
            )
            return trainer.learn(state, c_metrics, key)

        def count_warmup(state, done):
            steps = trainer.num_train_tasks * cfg.initial_steps
            return state.replace(
                env_steps=state.env_steps + steps, episodes=state.episodes + jnp.sum(done)
            )

        self._choose = jax.jit(jax.vmap(choose))
        self._draws = jax.jit(jax.vmap(draws, (0, 0, 0, None)), static_argnums=3)
        self._act = jax.jit(jax.vmap(act))
        self._store = jax.jit(
            jax.vmap(store, (0, 0, 0, None, None)), static_argnums=(3, 4), donate_argnums=0
        )
        self._learn = jax.jit(jax.vmap(learn), donate_argnums=0)
        self._count_warmup = jax.jit(jax.vmap(count_warmup))

    def close(self) -> None:
        """Nothing stays open between phases (the envs are rebuilt for each)."""

    def phase(self, state: TrainState, tasks: np.ndarray, key: jax.Array, steps: int, posterior):
        """``steps`` steps on each seed's ``tasks`` [S, R]: (transitions [S, R, K, ...], done,
        finished returns)."""
        env, family = self.env, self.family
        seeds, lanes = tasks.shape
        k_draw, k_steps, k_seed = (np.asarray(k) for k in _split3(key))
        parts, masks = self._draws(state, jnp.asarray(tasks), jnp.asarray(k_draw), posterior)
        train_params = self.trainer.tasks[0]
        first = env_seeds(jnp.asarray(k_seed))
        gym_envs = [
            [
                env.make_env(**family.host_kwargs(train_params, int(tasks[s, r])))
                for r in range(lanes)
            ]
            for s in range(seeds)
        ]
        shape = (seeds, lanes, steps)
        obs_log = np.zeros((*shape, env.obs_dim), np.float32)
        actions = np.zeros((*shape, env.action_dim), np.float32)
        rewards = np.zeros(shape, np.float32)
        next_obs = np.zeros((*shape, env.obs_dim), np.float32)
        terminated = np.zeros(shape, bool)
        done = np.zeros(shape, bool)
        finished = np.zeros(shape, np.float32)
        try:
            obs = np.stack(
                [[gym_envs[s][r].reset(seed=first[s] + r)[0] for r in range(lanes)]
                 for s in range(seeds)]
            ).astype(np.float32)  # fmt: skip
            eps = jnp.zeros((seeds, lanes, env.action_dim))
            episode = np.zeros((seeds, lanes), np.int32)
            ep_return = np.zeros((seeds, lanes))
            step_keys = jax.vmap(lambda k: jax.random.split(k, steps))(jnp.asarray(k_steps))
            for t in range(steps):
                action, eps = self._act(
                    state.actor, parts, masks, jnp.asarray(episode), obs, eps, step_keys[:, t]
                )
                action = np.asarray(action)
                env_action = env.to_env_action(action)
                for s in range(seeds):
                    for r in range(lanes):
                        o, reward, term, trunc, _ = gym_envs[s][r].step(env_action[s, r])
                        obs_log[s, r, t], actions[s, r, t] = obs[s, r], action[s, r]
                        rewards[s, r, t], next_obs[s, r, t] = reward, o
                        terminated[s, r, t] = term
                        ep_return[s, r] += reward
                        if term or trunc:
                            done[s, r, t] = True
                            finished[s, r, t] = ep_return[s, r]
                            ep_return[s, r] = 0.0
                            episode[s, r] += 1
                            o, _ = gym_envs[s][r].reset()
                        obs[s, r] = o
        finally:
            for row in gym_envs:
                for gym_env in row:
                    gym_env.close()
        transitions = Transition(obs_log, actions, rewards, next_obs, terminated)
        return transitions, done, finished

    def warmup(self, state: TrainState) -> TrainState:
        """PEARL's initial collection on every training task (prior z), into both buffers."""
        cfg, t = self.cfg, self.trainer.num_train_tasks
        if not cfg.initial_steps:
            return state
        keys = salted(state.key, HOST_WARMUP)
        tasks = np.tile(np.arange(t), (cfg.seeds, 1))
        transitions, done, _ = self.phase(state, tasks, keys, cfg.initial_steps, False)
        state = self._store(state, jnp.asarray(tasks), transitions, True, False)
        return self._count_warmup(state, jnp.asarray(done))

    def iteration(self, state: TrainState) -> tuple[TrainState, Metrics]:
        cfg = self.cfg
        key, tasks, k_prior, k_posterior, k_update = self._choose(state.key)
        state = state.replace(key=key)
        tasks_np = np.asarray(tasks)
        prior, done_p, fin_p = self.phase(state, tasks_np, k_prior, cfg.prior_steps, False)
        state = self._store(state, tasks, prior, True, True)
        dones, finished = [done_p.reshape(cfg.seeds, -1)], [fin_p.reshape(cfg.seeds, -1)]
        if cfg.posterior_steps:
            post, done_q, fin_q = self.phase(
                state, tasks_np, k_posterior, cfg.posterior_steps, True
            )
            state = self._store(state, tasks, post, False, False)
            dones.append(done_q.reshape(cfg.seeds, -1))
            finished.append(fin_q.reshape(cfg.seeds, -1))
        return self._learn(state, np.concatenate(dones, 1), np.concatenate(finished, 1), k_update)

    def chunk(self, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
        return host_chunk(self.iteration, state, length)


def _split3(keys: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    out = jax.vmap(lambda k: jax.random.split(k, 3))(jnp.asarray(keys))
    return out[:, 0], out[:, 1], out[:, 2]


class HostAdapter:
    """PEARL's protocol on host envs: ``(state [S], keys [S, 2]) -> Adapted [S, N, runs]`` on
    the given task params [N] (the host counterpart of ``Trainer.adapt``)."""

    def __init__(self, trainer: Trainer, task_params):
        self.trainer, self.task_params = trainer, task_params
        self.env, self.family, cfg = trainer.env, trainer.family, trainer.config
        actor, encoder = trainer.actor, trainer.encoder
        self.n = jax.tree.leaves(task_params)[0].shape[0]

        def generate(actor_params, z):  # one seed, lanes [M]
            def lane(z_i):
                part = actor.generate(actor_params, z_i)
                return part, actor.eval_mask(actor.policy(actor_params, part))

            return jax.vmap(lane)(z)

        def act(actor_params, parts, masks, obs):
            def lane(part, mask, o):
                return actor.deterministic(actor.policy(actor_params, part), mask, o)

            return jax.vmap(lane)(parts, masks, obs)

        def accumulate(encoder_params, posterior, transitions, weight):  # one seed, lanes [M]
            """Multiply each active lane's new transition into its ``pearl.Posterior``."""
            mu, var = jax.vmap(partial(encoder.factors, encoder_params))(transitions)
            return jax.vmap(pearl.Posterior.add)(posterior, mu, var, weight)

        self._generate = jax.jit(jax.vmap(generate))
        self._act = jax.jit(jax.vmap(act))
        self._accumulate = jax.jit(jax.vmap(accumulate))
        self._gaussian = jax.jit(jax.vmap(jax.vmap(pearl.Posterior.gaussian)))
        self.runs, self.eval_steps = cfg.eval_runs, cfg.eval_steps
        self.exploration = cfg.eval_exploration_trajectories

    def __call__(self, state: TrainState, keys: jax.Array) -> Adapted:
        env, family, runs = self.env, self.family, self.runs
        seeds = int(np.shape(keys)[0])
        lanes = self.n * runs  # lane = task * runs + run
        latent = self.trainer.latent_dim
        rng = np.random.default_rng(env_seeds(keys))
        first = env_seeds(keys)
        gym_envs = [
            [
                env.make_env(**family.host_kwargs(self.task_params, lane // runs))
                for lane in range(lanes)
            ]
            for _ in range(seeds)
        ]
        z = rng.standard_normal((seeds, lanes, latent)).astype(np.float32)
        parts, masks = self._generate(state.actor, jnp.asarray(z))
        posterior = pearl.Posterior(
            jnp.zeros((seeds, lanes, latent)), jnp.zeros((seeds, lanes, latent))
        )
        ep_return = np.zeros((seeds, lanes))
        steps = np.zeros((seeds, lanes), np.int64)
        trajectories = np.zeros((seeds, lanes), np.int64)
        final = np.zeros((seeds, lanes))
        first_return = np.zeros((seeds, lanes))
        active = np.ones((seeds, lanes), bool)
        try:
            obs = np.stack(
                [[gym_envs[s][m].reset(seed=first[s] + m)[0] for m in range(lanes)]
                 for s in range(seeds)]
            ).astype(np.float32)  # fmt: skip
            while active.any():
                action = np.asarray(self._act(state.actor, parts, masks, obs))
                env_action = env.to_env_action(action)
                next_obs = obs.copy()
                reward = np.zeros((seeds, lanes), np.float32)
                terminated = np.zeros((seeds, lanes), bool)
                ended = np.zeros((seeds, lanes), bool)
                for s, m in zip(*np.nonzero(active), strict=True):
                    o, r, term, trunc, _ = gym_envs[s][m].step(env_action[s, m])
                    next_obs[s, m], reward[s, m], terminated[s, m] = o, r, term
                    ended[s, m] = term or trunc
                posterior = self._accumulate(
                    state.encoder,
                    posterior,
                    Transition(obs, action, reward, next_obs, terminated),
                    active.astype(np.float32),
                )
                ep_return += np.where(active, reward, 0.0)
                steps += active
                trajectories += ended
                first_return = np.where(ended & (trajectories == 1), ep_return, first_return)
                final = np.where(ended, ep_return, final)
                again = ended & (steps < self.eval_steps)
                active &= ~(ended & ~again)
                obs = next_obs
                if again.any():
                    noise = rng.standard_normal((seeds, lanes, latent))
                    post_mu, post_var = (np.asarray(x) for x in self._gaussian(posterior))
                    sample = post_mu + np.sqrt(post_var) * noise
                    use = (trajectories >= self.exploration)[..., None]
                    new_z = np.where(use, sample, noise).astype(np.float32)
                    z = np.where(again[..., None], new_z, z)
                    parts, masks = self._generate(state.actor, jnp.asarray(z))
                    ep_return = np.where(again, 0.0, ep_return)
                    for s, m in zip(*np.nonzero(again), strict=True):
                        obs[s, m] = gym_envs[s][m].reset()[0]
        finally:
            for row in gym_envs:
                for gym_env in row:
                    gym_env.close()
        shape = (seeds, self.n, runs)
        return Adapted(
            final_return=final.reshape(shape),
            first_return=first_return.reshape(shape),
            trajectories=trajectories.reshape(shape),
            z=z.reshape((*shape, latent)),
        )
