"""Box2D environments (gymnasium's LunarLanderContinuous and BipedalWalker) behind the functional
``Environment`` interface, stepped by gymnasium on the host.

* ``lunarlander``: ``gymnasium.make("LunarLander-v3", continuous=True)`` (gymnasium 1.x's id of
  LunarLanderContinuous; 8 observations, 2 actions in [-1, 1], 1000-step limit). Params:
  ``LunarLanderParams`` (the world's gravity; the task of ``lunarlander_params``).
* ``bipedalwalker``: ``gymnasium.make("BipedalWalker-v3")`` (24 observations, 4 actions in [-1, 1],
  1600-step limit). No params.

Collection, evaluation and PEARL's protocol step them as any env (``espl_jax/rollout.py``): only
the physics leaves XLA. ``reset``, ``step`` and ``step_autoreset`` are each one
``jax.pure_callback`` with ``vmap_method="broadcast_all"``, so a vmapped batch (seeds × tasks ×
episodes) reaches the host as one call per env step, which loops over the lanes' gymnasium envs.
Each call passes one packed float32 row per lane and returns one (every array a callback passes
costs tens of microseconds, ``envs/native.py``).

A Box2D world cannot be written into arrays, but an episode is a pure function of its gymnasium
reset seed, its params and the actions taken since (Box2D and the env's own random draws are
deterministic). So the JAX state (``Box2DState``) holds exactly that: the seed (drawn from the
reset key), the step count ``t``, the actions so far, and the current observation and status. The
host keeps the live gymnasium envs in a cache keyed by (seed, params) (``Episodes``); a step whose
cached env is not at that state (a restored checkpoint, or a call XLA repeated) rebuilds it by
replaying the actions from the reset. The callbacks are therefore pure, as ``pure_callback``
requires (XLA may merge, drop or repeat them), checkpoints hold the simulator state, and a resumed
run continues exactly as an uninterrupted one. The cache is only a memo: evicting an env costs a
replay, never a result.

Episode rules, as gymnasium's: ``terminated`` is the env's own end, ``truncated`` its time limit
(``max_episode_steps`` = ``horizon``; not flagged when terminated at the same step); ``obs`` of an
ending step is the true final observation. After an episode's end ``step`` leaves the env as it is
(reward 0, the same observation and flags): the rollouts ignore those steps (evaluation masks
them, the protocol marks the lane inactive), and the host skips them.

gymnasium (and Box2D) is imported only when an env is built, so ``from espl_jax import envs``
stays cheap.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from espl_jax.envs.base import (
    Environment,
    PRNGKey,
    StepOutput,
    Stepped,
    action_center_half_range,
    to_env_units,
)

RUNNING, TERMINATED, TRUNCATED = 0, 1, 2  # Box2DState.status
# Live episodes the host keeps (LRU beyond it): a run's collection lanes plus its largest
# evaluation batch fit many times over; an evicted one is replayed if it is stepped again.
MAX_LIVE = 1024
MAX_FREE = 256  # built gymnasium envs kept for reuse (gymnasium.make costs ~1 ms)
_INTS = 7  # packed row: seed (hi, lo), t, status, reset seed (hi, lo), may_reset


@struct.dataclass
class LunarLanderParams:
    """The physics of ``lunarlander`` (and a task of ``lunarlander_params``).

    Attributes:
        gravity: float32 (), Box2D world gravity in m/s^2 (negative; gymnasium's default -10).
    """

    gravity: jax.Array


@struct.dataclass
class NoParams:
    """An env without params (``bipedalwalker``)."""


@struct.dataclass
class Box2DState:
    """One Box2D episode, as what determines it (module docstring).

    Attributes:
        seed: int32 (), the gymnasium seed of the episode's reset (drawn from the reset key).
        t: int32 (), env steps since the reset.
        status: int32 (), ``RUNNING``, ``TERMINATED`` or ``TRUNCATED``.
        obs: float32 (obs_dim,), the current observation.
        actions: float32 (horizon, action_dim), the normalized actions taken; ``[:t]`` are set.
    """

    seed: jax.Array
    t: jax.Array
    status: jax.Array
    obs: jax.Array
    actions: jax.Array


class HostEnv(Environment):
    """A gymnasium Box2D env as a functional ``Environment`` (module docstring).

    Attributes:
        name: registry name, e.g. ``"lunarlander"``.
        env_id: the gymnasium id; ``kwargs`` are passed to ``gymnasium.make``.
        obs_dim, action_dim: from the gymnasium spaces.
        horizon: time limit (``max_episode_steps``); truncation happens there.
        action_low, action_high: numpy float arrays (action_dim,), the bounds in env units.

    Actions from the policy are normalized to [-1, 1]; ``to_env_action`` maps them to the env's
    units on the host (as ``Environment.scale_action``). Params are a ``flax.struct`` dataclass of
    scalar float32 fields, each a ``gymnasium.make`` keyword (``gym_kwargs``).
    """

    simulator = "gymnasium"

    def __init__(
        self,
        name: str,
        env_id: str,
        params: Any = None,
        horizon: int | None = None,
        **kwargs: Any,
    ):
        """Builds the description by making the env once and reading its spaces.

        Args:
            name: registry name.
            env_id: gymnasium id.
            params: the default params (a dataclass of ``gymnasium.make`` keywords), or None.
            horizon: time limit; None keeps the registered ``max_episode_steps``.
            **kwargs: forwarded to ``gymnasium.make`` (e.g. ``continuous=True``).
        """
        import gymnasium

        self.name = name
        self.env_id = env_id
        self.kwargs = kwargs
        self._default_params = NoParams() if params is None else params
        self._param_names = tuple(self._default_params.__dataclass_fields__)
        registered = gymnasium.spec(env_id).max_episode_steps
        self.horizon = int(registered if horizon is None else horizon)
        env = self.make_env()
        try:
            obs_space, action_space = env.observation_space, env.action_space
            self.obs_dim = int(np.prod(obs_space.shape))
            self.action_dim = int(np.prod(action_space.shape))
            self.action_low = np.asarray(action_space.low, np.float64).reshape(-1)
            self.action_high = np.asarray(action_space.high, np.float64).reshape(-1)
        finally:
            env.close()
        self.episodes = Episodes(self)

    @property
    def default_params(self) -> Any:
        return self._default_params

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, id={self.env_id!r})"

    # gymnasium ----------------------------------------------------------------------------

    def make_env(self, **kwargs: Any):
        """One gymnasium env with this description's time limit; actions in the env's units.

        ``kwargs`` (e.g. ``render_mode``, ``gravity``) are forwarded to ``gymnasium.make``.
        """
        import gymnasium

        return gymnasium.make(
            self.env_id, max_episode_steps=self.horizon, **{**self.kwargs, **kwargs}
        )

    def gym_kwargs(self, row: np.ndarray) -> dict[str, float]:
        """The ``gymnasium.make`` keywords of one params row (``flat_params``)."""
        return {k: float(v) for k, v in zip(self._param_names, row, strict=True)}

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        """Normalized actions (..., action_dim) in [-1, 1] to float32 actions in env units.

        Non-finite entries (a diverged actor) become 0 so Box2D is never fed NaN; the trainer
        still stops on the non-finite losses.
        """
        center, half_range = action_center_half_range(self.action_low, self.action_high)
        action = np.asarray(action, np.float64)
        if not np.isfinite(action).all():
            action = np.nan_to_num(action)
        return to_env_units(action, center, half_range).astype(np.float32)

    # JAX side ------------------------------------------------------------------------------

    def flat_params(self, params: Any) -> jax.Array:
        """The params' fields as one float32 row (P,), in field order."""
        fields = [jnp.asarray(getattr(params, k), jnp.float32) for k in self._param_names]
        return jnp.stack(fields) if fields else jnp.zeros((0,), jnp.float32)

    @staticmethod
    def _seed(key: PRNGKey) -> jax.Array:
        """The gymnasium seed of an episode reset with ``key`` (31 bits)."""
        return jax.random.randint(key, (), 0, 2**31 - 1)

    @staticmethod
    def _seed_words(seed: jax.Array) -> list[jax.Array]:
        # two 16-bit halves: exact as float32 in the packed row
        return [seed >> 16, seed & 0xFFFF]

    def reset(self, key: PRNGKey, params: Any) -> tuple[jax.Array, Box2DState]:
        """A gymnasium reset with a seed drawn from ``key`` (one host call for a batch)."""
        seed = self._seed(key)
        row = jnp.concatenate(
            [jnp.stack(self._seed_words(seed)).astype(jnp.float32), self.flat_params(params)]
        )
        obs = jax.pure_callback(
            self.episodes.host_reset,
            jax.ShapeDtypeStruct((self.obs_dim,), jnp.float32),
            row,
            vmap_method="broadcast_all",
        )
        zero = jnp.zeros((), jnp.int32)
        actions = jnp.zeros((self.horizon, self.action_dim), jnp.float32)
        return obs, Box2DState(seed, zero, zero + RUNNING, obs, actions)

    def step(self, key: PRNGKey, state: Box2DState, action: jax.Array, params: Any) -> StepOutput:
        """One gymnasium step (none after the episode's end; module docstring)."""
        s = self._host_step(state, action, params, state.seed, jnp.asarray(False))
        return s.obs, s.next_state, s.reward, s.terminated, s.truncated, {}

    def step_autoreset(
        self,
        key: PRNGKey,
        reset_key: PRNGKey,
        state: Box2DState,
        action: jax.Array,
        params: Any,
        may_reset: jax.Array | None = None,
    ) -> Stepped:
        """``step`` and, in the same host call, a reset (seed drawn from ``reset_key``) of the
        lanes whose episode ended, where ``may_reset``."""
        del key
        may = jnp.asarray(True) if may_reset is None else may_reset
        return self._host_step(state, action, params, self._seed(reset_key), may)

    def _host_step(self, state: Box2DState, action, params, reset_seed, may_reset) -> Stepped:
        obs_dim = self.obs_dim
        action = jnp.asarray(action, jnp.float32)
        ints = [
            *self._seed_words(state.seed), state.t, state.status,
            *self._seed_words(reset_seed), may_reset.astype(jnp.int32),
        ]  # fmt: skip
        row = jnp.concatenate(
            [
                jnp.stack(ints).astype(jnp.float32),
                self.flat_params(params),
                action,
                state.actions.ravel(),
            ]
        )
        out = jax.pure_callback(
            self.episodes.host_step,
            jax.ShapeDtypeStruct((2 * obs_dim + 2,), jnp.float32),
            row,
            vmap_method="broadcast_all",
        )
        running = state.status == RUNNING
        obs = jnp.where(running, out[:obs_dim], state.obs)
        reward = jnp.where(running, out[obs_dim], 0.0)
        status = out[obs_dim + 1].astype(jnp.int32)
        terminated, truncated = status == TERMINATED, status == TRUNCATED
        index = jnp.minimum(state.t, self.horizon - 1)
        actions = state.actions.at[index].set(jnp.where(running, action, state.actions[index]))
        t = state.t + running.astype(jnp.int32)
        reset = (status != RUNNING) & may_reset
        reset_obs = out[obs_dim + 2 :]
        next_state = Box2DState(
            seed=jnp.where(reset, reset_seed, state.seed),
            t=jnp.where(reset, 0, t),
            status=jnp.where(reset, RUNNING, status),
            obs=jnp.where(reset, reset_obs, obs),
            actions=actions,
        )
        return Stepped(obs, reward, terminated, truncated, reset, next_state.obs, next_state)


class _Episode:
    """A live gymnasium env (unwrapped: the time limit is ``host_step``'s), ``t`` steps into the
    episode of (seed, params), after ``actions[:t]`` (normalized, (horizon, action_dim))."""

    __slots__ = ("actions", "gym", "t")

    def __init__(self, gym, horizon: int, action_dim: int):
        self.gym = gym
        self.t = 0
        self.actions = np.zeros(horizon * action_dim, np.float32).reshape(horizon, action_dim)


class Episodes:
    """The host side of a ``HostEnv``: its live episodes keyed by (seed, params row), and the
    callbacks (module docstring). Thread-safe (XLA may call back from several threads)."""

    def __init__(self, env: HostEnv):
        self.env = env
        self.live: OrderedDict[tuple[int, bytes], _Episode] = OrderedDict()
        self.free: dict[bytes, list] = {}  # params row -> built gymnasium envs
        self.replays = 0  # episodes rebuilt by replaying their actions (a restored state)
        self.calls = 0  # host calls of step / step_autoreset (one per env step of a batch)
        self._lock = threading.Lock()

    # the callbacks -------------------------------------------------------------------------

    def host_reset(self, rows: np.ndarray) -> np.ndarray:
        """Rows [..., 2 + P] of (seed hi, seed lo, params) -> first observations [..., obs]."""
        rows = np.asarray(rows, np.float32)
        flat = rows.reshape(-1, rows.shape[-1])
        out = np.empty((len(flat), self.env.obs_dim), np.float32)
        with self._lock:
            for i, row in enumerate(flat):
                seed = (int(row[0]) << 16) | int(row[1])
                out[i] = self._reset(seed, row[2:].tobytes(), None)
        return out.reshape(*rows.shape[:-1], self.env.obs_dim)

    def host_step(self, rows: np.ndarray) -> np.ndarray:
        """Packed rows [..., W] (``HostEnv._host_step``) -> [..., obs, reward, status, reset
        obs] (the reset obs zero where no reset happened)."""
        env = self.env
        rows = np.asarray(rows, np.float32)
        flat = rows.reshape(-1, rows.shape[-1])
        a0 = _INTS + len(env._param_names)
        h0 = a0 + env.action_dim
        obs_dim, horizon = env.obs_dim, env.horizon
        ints = flat[:, :_INTS].astype(np.int64)  # exact: the packed ints are < 2**24
        seeds = ((ints[:, 0] << 16) | ints[:, 1]).tolist()
        reset_seeds = ((ints[:, 4] << 16) | ints[:, 5]).tolist()
        ts, statuses, may_reset = ints[:, 2].tolist(), ints[:, 3].tolist(), ints[:, 6].tolist()
        env_actions = env.to_env_action(flat[:, a0:h0])
        out = np.zeros((len(flat), 2 * obs_dim + 2), np.float32)
        with self._lock:
            self.calls += 1
            for i, row in enumerate(flat):
                t, status = ts[i], statuses[i]
                key = (seeds[i], row[_INTS:a0].tobytes())
                if status == RUNNING:
                    episode = self._at(key, t, row[h0:])
                    obs, reward, terminated, _, _ = episode.gym.step(env_actions[i])
                    episode.actions[t] = row[a0:h0]
                    episode.t = t = t + 1
                    # gymnasium's TimeLimit: truncated at the horizon, unless terminated
                    status = TERMINATED if terminated else TRUNCATED if t >= horizon else RUNNING
                    out[i, :obs_dim], out[i, obs_dim] = obs, reward
                out[i, obs_dim + 1] = status
                if status != RUNNING:
                    if may_reset[i]:  # the env moves on to the new episode
                        out[i, obs_dim + 2 :] = self._reset(reset_seeds[i], key[1], key)
                    else:
                        self._release(key)
        return out.reshape(*rows.shape[:-1], -1)

    # the cache -----------------------------------------------------------------------------

    def _reset(self, seed: int, params: bytes, reuse: tuple[int, bytes] | None) -> np.ndarray:
        """A fresh episode of (seed, params), in the env of the episode ``reuse`` if live."""
        episode = self.live.pop(reuse, None) if reuse is not None else None
        key = (seed, params)
        if key in self.live:  # the same episode again: restart it
            if episode is not None:
                self._free(params, episode.gym)
            episode = self.live.pop(key)
        if episode is None:
            episode = _Episode(self._build(params), self.env.horizon, self.env.action_dim)
        obs, _ = episode.gym.reset(seed=seed)
        episode.t = 0
        self.live[key] = episode
        while len(self.live) > MAX_LIVE:
            old_key, old = self.live.popitem(last=False)
            self._free(old_key[1], old.gym)
        return obs

    def _at(self, key: tuple[int, bytes], t: int, history: np.ndarray) -> _Episode:
        """The live episode ``key`` = (seed, params) after the first ``t`` actions of
        ``history`` (flat); replayed from its reset if not live."""
        a = self.env.action_dim
        episode = self.live.get(key)
        if (
            episode is not None
            and episode.t == t
            and episode.actions[:t].tobytes() == history[: t * a].tobytes()
        ):
            self.live.move_to_end(key)
            return episode
        self.replays += 1
        self._reset(key[0], key[1], None)
        episode = self.live[key]
        actions = history[: t * a].reshape(t, a)
        for j, action in enumerate(self.env.to_env_action(actions)):
            terminated = episode.gym.step(action)[2]
            if terminated or j + 1 >= self.env.horizon:
                raise RuntimeError(
                    f"{self.env.name}: replaying episode seed {key[0]} ended at step {j + 1} of "
                    f"{t}; the state does not come from this env"
                )
        episode.actions[:t] = actions
        episode.t = t
        return episode

    def _release(self, key: tuple[int, bytes]) -> None:
        """An ended episode: its env is kept for reuse."""
        episode = self.live.pop(key, None)
        if episode is not None:
            self._free(key[1], episode.gym)

    def _free(self, params: bytes, gym_env) -> None:
        pool = self.free.setdefault(params, [])
        if sum(len(p) for p in self.free.values()) < MAX_FREE:
            pool.append(gym_env)
        else:
            gym_env.close()

    def _build(self, params: bytes):
        """An unwrapped gymnasium env of these params (reused if one is free)."""
        pool = self.free.get(params)
        if pool:
            return pool.pop()
        row = np.frombuffer(params, np.float32)
        return self.env.make_env(**self.env.gym_kwargs(row)).unwrapped

    def close(self) -> None:
        """Closes every env (they are rebuilt, by replay, when stepped again)."""
        with self._lock:
            for episode in self.live.values():
                episode.gym.close()
            for pool in self.free.values():
                for gym_env in pool:
                    gym_env.close()
            self.live.clear()
            self.free.clear()


def lunarlander(**kwargs: Any) -> HostEnv:
    gravity = LunarLanderParams(gravity=np.asarray(-10.0, np.float32))
    return HostEnv("lunarlander", "LunarLander-v3", gravity, continuous=True, **kwargs)


def bipedalwalker(**kwargs: Any) -> HostEnv:
    return HostEnv("bipedalwalker", "BipedalWalker-v3", **kwargs)
