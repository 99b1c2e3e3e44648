"""Training and evaluation on host-stepped gymnasium envs (the Box2D tasks), same algorithm.

Only the env steps leave JAX. One iteration, for all seeds at once:

1. ``Trainer.start_iteration`` (jitted, vmapped over seeds): the next key, the Bernoulli
   collection mask of each seed (Algorithm 1, line 4) and the per-step noise keys.
2. K = ``steps_per_iteration`` steps of a gymnasium ``SyncVectorEnv`` with one env per seed: the
   batched observation goes through ``rollout.explore`` (jitted, vmapped; the same AR(1) noise and
   tanh-Gaussian action as the JAX collector), the action is mapped to env units and stepped.
   ``terminated`` is stored, not ``truncated``; at an episode end the stored next_obs is the true
   final observation (same-step autoreset puts it in ``info["final_obs"]``).
3. ``Trainer.record_collection`` + ``Trainer.learn`` (jitted, vmapped, state donated): append the
   K transitions to each seed's replay buffer and take ``updates_per_iteration`` SAC steps in one
   ``lax.scan``, exactly as in the JAX trainer.

Checkpoints hold the same TrainState as for JAX envs (the rollout's ``env_state`` is None; its
``obs`` and ``episode_return`` are those of the host envs at the end of the last iteration). The
Box2D simulator state itself is not checkpointed: a resumed run starts from freshly reset envs,
seeded from the restored state's keys, and drops the partial episodes in progress at the checkpoint.
So a resumed run is reproducible but not bitwise equal to an uninterrupted one (it is for JAX
envs).

Evaluation (``HostEvaluator``) runs the deterministic eval-mask policy (the exported formula) in
gymnasium, all seeds × episodes stepped together; the episode seeds come from the given keys, so
different keys give different episodes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import replay, rollout
from espl_jax.keys import HOST_RESET, salted
from espl_jax.learner import Trainer
from espl_jax.rollout import Rollout
from espl_jax.sac import Metrics, TrainState


def env_seeds(keys: jax.Array) -> list[int]:
    """One gymnasium seed per key (keys [S, 2]), drawn from the key: deterministic."""
    draw = jax.vmap(lambda k: jax.random.randint(k, (), 0, 2**31 - 1))
    return [int(s) for s in np.asarray(draw(jnp.asarray(keys)))]


def reset_seeds(state_keys: jax.Array) -> list[int]:
    """The env seeds a (re)started collector resets its envs with, from the states' keys."""
    return env_seeds(salted(state_keys, HOST_RESET))


def host_chunk(iteration, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
    """``length`` host-stepped iterations; metrics stacked to [S, length] like a compiled
    chunk's (``Trainer.compiled_chunk``)."""
    rows = []
    for _ in range(length):
        state, metrics = iteration(state)
        rows.append(jax.device_get(metrics))
    return state, jax.tree.map(lambda *xs: np.stack(xs, axis=1), *rows)


class HostCollector:
    """Steps one gymnasium env per seed on the host; policy and updates stay jitted.

    ``chunk(state, length)`` has the signature of ``Trainer.compiled_chunk(length)(state)``: it
    returns the new state (the input state's buffers are donated) and metrics shaped
    [seeds, length]. The envs are built and reset on the first call (see the module docstring
    for what that means for resuming).
    """

    def __init__(self, trainer: Trainer):
        if not trainer.on_host:
            raise ValueError(f"{trainer.config.env} is a JAX env; use Trainer.compiled_chunk")
        self.trainer = trainer
        self.env = trainer.env
        self.seeds = trainer.config.seeds
        self.steps = trainer.config.steps_per_iteration
        self.vector_env = None
        self.obs: np.ndarray | None = None  # [S, obs_dim] current observation of each env
        self.episode_return: np.ndarray | None = None  # [S] return of the episode in progress

        def begin(key, actor_params, iteration):
            actor_params = trainer.freeze_mask(actor_params, iteration)
            key, mask, k_collect, k_update = trainer.start_iteration(key, actor_params)
            return key, actor_params, mask, jax.random.split(k_collect, self.steps), k_update

        def learn(state, transitions, done, finished_returns, obs, episode_return, eps, key):
            state, c_metrics = trainer.record_collection(
                state,
                rollout_state=Rollout(None, obs[None], episode_return[None], eps[None]),
                done=done,
                finished_returns=finished_returns,
                steps=self.steps,
            )
            one_task = jax.tree.map(lambda x: x[None], transitions)
            buffer = replay.insert(state.buffer, jnp.zeros(1, jnp.int32), one_task)
            return trainer.learn(state.replace(buffer=buffer), c_metrics, key)

        def explore(actor_params, mask, obs, eps, key):
            policy = trainer.actor.at(actor_params, jnp.zeros((0,)))
            rho = trainer.config.exploration_correlation
            return rollout.explore(trainer.actor, rho, policy, mask, obs, eps, key)

        self._begin = jax.jit(jax.vmap(begin))
        self._explore = jax.jit(jax.vmap(explore))
        self._learn = jax.jit(jax.vmap(learn), donate_argnums=0)

    def reset(self, state: TrainState) -> None:
        """(Re)builds the vector env and resets it, env seeds drawn from the state's keys."""
        self.close()
        self.vector_env = self.env.make_vector_env(self.seeds)
        obs, _ = self.vector_env.reset(seed=reset_seeds(state.key))
        self.obs = np.asarray(obs, np.float32)
        self.episode_return = np.zeros(self.seeds)

    def close(self) -> None:
        if self.vector_env is not None:
            self.vector_env.close()
            self.vector_env = None

    def collect(
        self, state: TrainState, mask: list | None, step_keys: jax.Array
    ) -> tuple[replay.Transition, np.ndarray, np.ndarray, jax.Array]:
        """K steps of every seed's env with the seed's fixed mask (Algorithm 1, lines 5–7).

        Args:
            state: the seeds' states (only ``actor`` and the rollout's noise are read).
            mask: the seeds' collection masks (leading seed axis).
            step_keys: [S, K, 2] one noise key per seed and step.

        Returns:
            ``(transitions [S, K, ...], done [S, K], finished_returns [S, K], eps [S, A])``,
            numpy except the final noise ε. ``self.obs`` and ``self.episode_return`` advance.
        """
        if self.vector_env is None:
            self.reset(state)
        s, k, env = self.seeds, self.steps, self.env
        obs = np.empty((s, k, env.obs_dim), np.float32)
        actions = np.empty((s, k, env.action_dim), np.float32)
        rewards = np.empty((s, k), np.float32)
        next_obs = np.empty((s, k, env.obs_dim), np.float32)
        terminated = np.empty((s, k), bool)
        done = np.empty((s, k), bool)
        finished_returns = np.zeros((s, k), np.float32)
        step_keys = np.asarray(step_keys)
        eps = state.rollout.exploration_noise[:, 0]
        for t in range(k):
            action, eps = self._explore(state.actor, mask, self.obs, eps, step_keys[:, t])
            action = np.asarray(action)
            new_obs, reward, term, trunc, info = self.vector_env.step(env.to_env_action(action))
            ended = term | trunc
            true_next = np.array(new_obs, np.float32)
            for i in np.flatnonzero(ended):
                true_next[i] = info["final_obs"][i]
            obs[:, t], actions[:, t], rewards[:, t] = self.obs, action, reward
            next_obs[:, t], terminated[:, t], done[:, t] = true_next, term, ended
            self.episode_return += reward
            finished_returns[:, t] = np.where(ended, self.episode_return, 0.0)
            self.episode_return[ended] = 0.0
            self.obs = np.asarray(new_obs, np.float32)
        transitions = replay.Transition(obs, actions, rewards, next_obs, terminated)
        return transitions, done, finished_returns, eps

    def iteration(self, state: TrainState) -> tuple[TrainState, Metrics]:
        """One iteration for all seeds (Algorithm 1, lines 3–18); metrics shaped [S]."""
        key, actor, mask, step_keys, k_update = self._begin(state.key, state.actor, state.iteration)
        state = state.replace(key=key, actor=actor)
        transitions, done, finished_returns, eps = self.collect(state, mask, step_keys)
        return self._learn(
            state,
            transitions,
            done,
            finished_returns,
            self.obs,
            self.episode_return.astype(np.float32),
            eps,
            k_update,
        )

    def chunk(self, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
        return host_chunk(self.iteration, state, length)


class HostEvaluator:
    """Deterministic returns in gymnasium: (actor params [S, ...], keys [S, 2]) -> [S, E].

    The host counterpart of ``Trainer.compiled_evaluate(episodes)``: the eval-mask policy (the
    exported formula), seed s plays episodes with env seeds ``env_seeds(keys)[s] + 0 … E−1``.
    All S × E episodes are stepped together with one batched policy call per step.
    """

    def __init__(self, trainer: Trainer, episodes: int):
        self.env = trainer.env
        self.episodes = episodes
        actor = trainer.actor

        def act(params, obs):  # one seed: obs [E, obs_dim]
            policy = actor.at(params, jnp.zeros((0,)))
            mask = actor.eval_mask(policy)
            return jax.vmap(actor.deterministic, (None, None, 0))(policy, mask, obs)

        self._act = jax.jit(jax.vmap(act))

    def __call__(self, actor_params: dict, keys: jax.Array) -> np.ndarray:
        seeds, episodes, env = int(np.shape(keys)[0]), self.episodes, self.env
        first = env_seeds(keys)
        gym_envs = [[env.make_env() for _ in range(episodes)] for _ in range(seeds)]
        try:
            obs = np.zeros((seeds, episodes, env.obs_dim), np.float32)
            for s, row in enumerate(gym_envs):
                for e, gym_env in enumerate(row):
                    obs[s, e] = gym_env.reset(seed=first[s] + e)[0]
            totals = np.zeros((seeds, episodes))
            done = np.zeros((seeds, episodes), bool)
            while not done.all():
                actions = env.to_env_action(np.asarray(self._act(actor_params, obs)))
                for s, e in zip(*np.nonzero(~done), strict=True):
                    o, reward, terminated, truncated, _ = gym_envs[s][e].step(actions[s, e])
                    obs[s, e] = o
                    totals[s, e] += float(reward)
                    done[s, e] = terminated or truncated
        finally:
            for row in gym_envs:
                for gym_env in row:
                    gym_env.close()
        return totals
