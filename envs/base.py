"""The functional environment interface shared by every JAX environment (gymnax-style).

An environment is a stateless object holding only static metadata (sizes, horizon, action bounds).
Everything that changes lives in two pytrees passed explicitly: ``params`` (physics/task parameters,
a ``flax.struct.dataclass`` with float leaves, so a meta-RL task batch is a vmapped batch of params)
and ``state`` (physics state plus the step counter ``t``)::

    env = envs.make("pendulum")
    params = env.default_params
    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

``action`` is normalized to [-1, 1] per dimension; ``step`` clips it and scales it linearly to the
env's own bounds ``[action_low, action_high]``. ``terminated`` is a true end (no bootstrap),
``truncated`` is the time limit (``t >= horizon`` and not terminated). ``step`` never auto-resets;
``step_autoreset`` is a step followed, where the episode ended, by a reset (what collection and
PEARL's protocol step with, ``espl_jax/rollout.py``). What ``step`` does after an episode's end is
the env's own: the JAX envs go on simulating, the Box2D envs (``envs/box2d.py``) stay put; the
rollouts ignore those steps either way.
"""

from __future__ import annotations

import abc
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

PRNGKey = jax.Array
EnvParams = Any
EnvState = Any
StepOutput = tuple[jax.Array, Any, jax.Array, jax.Array, jax.Array, dict[str, jax.Array]]


class Stepped(NamedTuple):
    """One step with auto-reset (``Environment.step_autoreset``).

    Attributes:
        obs: float32 (obs_dim,), the observation the step ended in: at an episode end the true
            final one, never the reset one.
        reward: float32 ().
        terminated: bool (), a true end.
        truncated: bool (), the time limit.
        reset: bool (), a new episode began after this step.
        next_obs: where the agent goes on: ``obs``, or the new episode's first observation.
        next_state: the state to step next (the new episode's where ``reset``).
    """

    obs: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    reset: jax.Array
    next_obs: jax.Array
    next_state: Any


class Environment(abc.ABC):
    """Base class of the functional JAX environments.

    Subclasses set the static attributes in ``__init__`` and implement ``default_params``,
    ``reset`` and ``step`` as pure functions of their arguments (jit- and vmap-able, including
    vmap over ``params``).

    Attributes:
        name: registry name, e.g. ``"pendulum"``.
        obs_dim: size of the observation vector.
        action_dim: size of the action vector.
        horizon: time limit; ``truncated`` becomes true at ``t == horizon``.
        action_low: numpy float array (action_dim,), lower action bound in the env's own units.
        action_high: numpy float array (action_dim,), upper action bound in the env's own units.
        simulator: what simulates it, as a run's eval.json reports (``evaluated_in``): ``"jax"``,
            or ``"gymnasium"`` for the Box2D envs.
    """

    simulator: str = "jax"
    name: str
    obs_dim: int
    action_dim: int
    horizon: int
    action_low: np.ndarray
    action_high: np.ndarray

    @property
    @abc.abstractmethod
    def default_params(self) -> EnvParams:
        """The reference physics/task parameters (a ``flax.struct.dataclass``)."""

    @abc.abstractmethod
    def reset(self, key: PRNGKey, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """Samples an initial state.

        Args:
            key: PRNG key.
            params: env parameters (``default_params`` or a variant of it).

        Returns:
            ``(obs, state)``: obs float32 (obs_dim,) and the initial state with ``t == 0``.
        """

    @abc.abstractmethod
    def step(
        self, key: PRNGKey, state: EnvState, action: jax.Array, params: EnvParams
    ) -> StepOutput:
        """Advances the env by one step (no auto-reset).

        Args:
            key: PRNG key (unused by deterministic envs).
            state: current state.
            action: float32 (action_dim,), normalized to [-1, 1]; clipped to that range.
            params: env parameters.

        Returns:
            ``(obs, state, reward, terminated, truncated, info)``: obs float32 (obs_dim,), the next
            state, reward float32 (), terminated and truncated bool (), info a dict.
        """

    def step_autoreset(
        self,
        key: PRNGKey,
        reset_key: PRNGKey,
        state: EnvState,
        action: jax.Array,
        params: EnvParams,
        may_reset: jax.Array | None = None,
    ) -> Stepped:
        """``step``, then ``reset`` (with ``reset_key``) where the episode ended and
        ``may_reset`` (None: wherever it ended).

        This default evaluates ``reset`` at every step and selects it with ``jnp.where``, which
        is what a JAX env costs least with. Host-stepped envs override it with one host call
        that resets only the lanes that ended (``envs/box2d.py``).
        """
        obs, next_state, reward, terminated, truncated, _ = self.step(key, state, action, params)
        reset_obs, reset_state = self.reset(reset_key, params)
        reset = terminated | truncated
        if may_reset is not None:
            reset = reset & may_reset
        return Stepped(
            obs, reward, terminated, truncated, reset,
            jnp.where(reset, reset_obs, obs),
            jax.tree.map(lambda x, y: jnp.where(reset, x, y), reset_state, next_state),
        )  # fmt: skip

    def scale_action(self, action: jax.Array) -> jax.Array:
        """Clips a normalized action to [-1, 1] and maps it linearly onto the env's bounds
        (``to_env_units`` in float32).

        Args:
            action: float (action_dim,), normalized action.

        Returns:
            float32 (action_dim,), the action in the env's own units.
        """
        center, half_range = action_center_half_range(self.action_low, self.action_high)
        return to_env_units(
            jnp.asarray(action, jnp.float32),
            jnp.asarray(center, jnp.float32),
            jnp.asarray(half_range, jnp.float32),
            jnp.clip,
        )

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, horizon={self.horizon})"


def action_center_half_range(low: Any, high: Any) -> tuple[np.ndarray, np.ndarray]:
    """float64 ``((high + low) / 2, (high − low) / 2)`` of action bounds, for ``to_env_units``."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return (high + low) / 2.0, (high - low) / 2.0


def to_env_units(action, center, half_range, clip=np.clip):
    """The action scaling: normalized ``action`` in [-1, 1] (clipped) to the env's own units,
    ``center + a · half_range`` (``action_center_half_range``).

    The one formula of every place an action is scaled: the JAX envs (``scale_action``, float32),
    the Box2D envs (``to_env_action``, float64 then float32) and the exported ``policy.py``, which
    carries this function's source verbatim (``espl_jax.expression.to_python``), so the reference
    env receives what the training env stepped with. It equals ``low + (a + 1) / 2 · (high − low)``
    but is exact for symmetric bounds (every registered env's): no rounding through ``a + 1``, and
    a = ±1 gives the bounds themselves.
    """
    return center + clip(action, -1.0, 1.0) * half_range


def time_limit(t: jax.Array, horizon: int, terminated: jax.Array) -> jax.Array:
    """Truncation flag: the time limit is reached and the episode did not truly end.

    Args:
        t: int32 (), step counter after the step.
        horizon: the env's time limit.
        terminated: bool (), true-end flag of the same step.

    Returns:
        bool (), ``(t >= horizon) & ~terminated``.
    """
    return jnp.logical_and(t >= horizon, jnp.logical_not(terminated))
