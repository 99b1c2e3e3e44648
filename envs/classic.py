"""Classic-control environments in pure JAX: ``cartpole``, ``pendulum``, ``mountaincar``.

Each is a step-by-step port of a reference implementation, checked against it in
``tests/test_envs_classic.py``:

* ``cartpole``: DSO's continuous CartPole (``CustomCartPoleContinuous-v0``,
  ``dso/task/control/envs/continuous_cartpole.py``, itself Ian Danforth's gist
  https://gist.github.com/iandanforth/e3ffb67cf3623153e968f2afdfb01dc8), horizon 1000.
* ``pendulum``: gymnasium 1.4.0 ``Pendulum-v1`` (``gymnasium/envs/classic_control/pendulum.py``).
* ``mountaincar``: gymnasium 1.4.0 ``MountainCarContinuous-v0``
  (``gymnasium/envs/classic_control/continuous_mountain_car.py``).

The references compute in float64 (cartpole, pendulum) or mostly float32 (mountaincar); these ports
run in JAX's default float32.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from espl_jax.envs.base import Environment, PRNGKey, StepOutput, time_limit

# --------------------------------------------------------------------------------------------
# CartPole (DSO continuous)
# --------------------------------------------------------------------------------------------


@struct.dataclass
class CartPoleParams:
    """Physics of DSO's continuous CartPole; every field may be randomized (e.g. by meta-RL).

    ``total_mass`` and ``polemass_length`` are derived in ``step`` so they stay consistent when
    ``masscart``, ``masspole`` or ``length`` change.
    """

    gravity: float = 9.8
    masscart: float = 1.0
    masspole: float = 0.1
    length: float = 0.5  # half the pole's length
    force_mag: float = 30.0
    tau: float = 0.02
    x_threshold: float = 2.4
    theta_threshold_radians: float = 12 * 2 * math.pi / 360


@struct.dataclass
class CartPoleState:
    """CartPole state: cart position/velocity, pole angle/angular velocity, step counter."""

    x: jax.Array
    x_dot: jax.Array
    theta: jax.Array
    theta_dot: jax.Array
    t: jax.Array


class CartPole(Environment):
    """DSO's continuous CartPole (``CustomCartPoleContinuous-v0``, Ian Danforth's gist).

    Force ``force_mag * a`` with ``a`` in [-1, 1]; explicit Euler where positions advance with the
    old velocities; terminates when ``|x| > 2.4`` or ``|theta| > 12 deg``; reward +1 every step,
    including the terminal one; reset ``U(-0.05, 0.05)^4``. Obs ``[x, x_dot, theta, theta_dot]``.
    The action bounds are the normalized [-1, 1] (the force scaling happens inside ``step``).
    """

    def __init__(self, horizon: int = 1000):
        """Builds the env.

        Args:
            horizon: time limit (1000 for the single-task benchmark, 200 for meta-RL).
        """
        self.name = "cartpole"
        self.obs_dim = 4
        self.action_dim = 1
        self.horizon = int(horizon)
        self.action_low = np.array([-1.0])
        self.action_high = np.array([1.0])

    @property
    def default_params(self) -> CartPoleParams:
        """DSO's constants (g 9.8, masses 1.0/0.1, half-length 0.5, force_mag 30, tau 0.02)."""
        return CartPoleParams()

    def reset(self, key: PRNGKey, params: CartPoleParams) -> tuple[jax.Array, CartPoleState]:
        """Samples ``[x, x_dot, theta, theta_dot] ~ U(-0.05, 0.05)^4``.

        Args:
            key: PRNG key.
            params: env parameters (unused).

        Returns:
            ``(obs, state)``: obs float32 (4,).
        """
        del params
        s = jax.random.uniform(key, (4,), jnp.float32, minval=-0.05, maxval=0.05)
        state = CartPoleState(
            x=s[0], x_dot=s[1], theta=s[2], theta_dot=s[3], t=jnp.zeros((), jnp.int32)
        )
        return self._obs(state), state

    def step(
        self, key: PRNGKey, state: CartPoleState, action: jax.Array, params: CartPoleParams
    ) -> StepOutput:
        """One explicit-Euler step of DSO's ``stepPhysics`` (see ``Environment.step``).

        Args:
            key: PRNG key (unused).
            state: current state.
            action: float32 (1,), normalized force in [-1, 1].
            params: env parameters.

        Returns:
            ``(obs (4,), state, reward (), terminated (), truncated (), {})``.
        """
        del key
        force = params.force_mag * self.scale_action(action)[0]
        total_mass = params.masspole + params.masscart
        polemass_length = params.masspole * params.length
        costheta = jnp.cos(state.theta)
        sintheta = jnp.sin(state.theta)
        temp = (force + polemass_length * state.theta_dot * state.theta_dot * sintheta) / total_mass
        thetaacc = (params.gravity * sintheta - costheta * temp) / (
            params.length * (4.0 / 3.0 - params.masspole * costheta * costheta / total_mass)
        )
        xacc = temp - polemass_length * thetaacc * costheta / total_mass
        t = state.t + 1
        state = CartPoleState(
            x=state.x + params.tau * state.x_dot,
            x_dot=state.x_dot + params.tau * xacc,
            theta=state.theta + params.tau * state.theta_dot,
            theta_dot=state.theta_dot + params.tau * thetaacc,
            t=t,
        )
        terminated = (
            (state.x < -params.x_threshold)
            | (state.x > params.x_threshold)
            | (state.theta < -params.theta_threshold_radians)
            | (state.theta > params.theta_threshold_radians)
        )
        reward = jnp.ones((), jnp.float32)
        truncated = time_limit(t, self.horizon, terminated)
        return self._obs(state), state, reward, terminated, truncated, {}

    @staticmethod
    def _obs(state: CartPoleState) -> jax.Array:
        return jnp.stack([state.x, state.x_dot, state.theta, state.theta_dot]).astype(jnp.float32)


# --------------------------------------------------------------------------------------------
# Pendulum (gymnasium Pendulum-v1)
# --------------------------------------------------------------------------------------------


@struct.dataclass
class PendulumParams:
    """Physics of gymnasium's ``Pendulum-v1``.

    The torque bound (``max_torque`` 2.0) is the static action bound, not a param: actions are
    normalized, so the clip to [-max_torque, max_torque] is the clip to [-1, 1] before scaling.
    """

    max_speed: float = 8.0
    dt: float = 0.05
    g: float = 10.0
    m: float = 1.0
    l: float = 1.0


@struct.dataclass
class PendulumState:
    """Pendulum state: angle (unwrapped, as in gymnasium), angular velocity, step counter."""

    theta: jax.Array
    theta_dot: jax.Array
    t: jax.Array


def angle_normalize(x: jax.Array) -> jax.Array:
    """Wraps an angle to [-pi, pi), as gymnasium's ``pendulum.angle_normalize``."""
    return ((x + jnp.pi) % (2 * jnp.pi)) - jnp.pi


class Pendulum(Environment):
    """gymnasium 1.4.0 ``Pendulum-v1`` (``classic_control/pendulum.py``).

    Torque in [-2, 2]; reward ``-(angle_normalize(th)^2 + 0.1 thdot^2 + 0.001 u^2)`` from the state
    before the step; semi-implicit Euler with the new velocity clipped to ``max_speed``; reset
    ``th ~ U(-pi, pi)``, ``thdot ~ U(-1, 1)``; obs ``[cos th, sin th, thdot]``; never terminates;
    horizon 200.
    """

    def __init__(self, horizon: int = 200):
        """Builds the env.

        Args:
            horizon: time limit (gymnasium's ``max_episode_steps`` is 200).
        """
        self.name = "pendulum"
        self.obs_dim = 3
        self.action_dim = 1
        self.horizon = int(horizon)
        self.action_low = np.array([-2.0])
        self.action_high = np.array([2.0])

    @property
    def default_params(self) -> PendulumParams:
        """gymnasium's constants (max_speed 8, dt 0.05, g 10, m 1, l 1)."""
        return PendulumParams()

    def reset(self, key: PRNGKey, params: PendulumParams) -> tuple[jax.Array, PendulumState]:
        """Samples ``th ~ U(-pi, pi)``, ``thdot ~ U(-1, 1)``.

        Args:
            key: PRNG key.
            params: env parameters (unused).

        Returns:
            ``(obs, state)``: obs float32 (3,).
        """
        del params
        high = jnp.array([jnp.pi, 1.0], jnp.float32)
        s = jax.random.uniform(key, (2,), jnp.float32, minval=-high, maxval=high)
        state = PendulumState(theta=s[0], theta_dot=s[1], t=jnp.zeros((), jnp.int32))
        return self._obs(state), state

    def step(
        self, key: PRNGKey, state: PendulumState, action: jax.Array, params: PendulumParams
    ) -> StepOutput:
        """One step of ``PendulumEnv.step`` (see ``Environment.step``).

        Args:
            key: PRNG key (unused).
            state: current state.
            action: float32 (1,), normalized torque in [-1, 1].
            params: env parameters.

        Returns:
            ``(obs (3,), state, reward (), terminated (), truncated (), {})``.
        """
        del key
        u = self.scale_action(action)[0]
        th, thdot = state.theta, state.theta_dot
        g, m, l, dt = params.g, params.m, params.l, params.dt
        costs = angle_normalize(th) ** 2 + 0.1 * thdot**2 + 0.001 * (u**2)
        newthdot = thdot + (3 * g / (2 * l) * jnp.sin(th) + 3.0 / (m * l**2) * u) * dt
        newthdot = jnp.clip(newthdot, -params.max_speed, params.max_speed)
        newth = th + newthdot * dt
        t = state.t + 1
        state = PendulumState(theta=newth, theta_dot=newthdot, t=t)
        terminated = jnp.zeros((), jnp.bool_)
        truncated = time_limit(t, self.horizon, terminated)
        reward = (-costs).astype(jnp.float32)
        return self._obs(state), state, reward, terminated, truncated, {}

    @staticmethod
    def _obs(state: PendulumState) -> jax.Array:
        return jnp.stack([jnp.cos(state.theta), jnp.sin(state.theta), state.theta_dot]).astype(
            jnp.float32
        )


# --------------------------------------------------------------------------------------------
# MountainCar (gymnasium MountainCarContinuous-v0)
# --------------------------------------------------------------------------------------------


@struct.dataclass
class MountainCarParams:
    """Physics/task constants of gymnasium's ``MountainCarContinuous-v0``.

    ``gravity`` is the coefficient of ``cos(3 * position)`` in the velocity update.
    """

    min_position: float = -1.2
    max_position: float = 0.6
    max_speed: float = 0.07
    goal_position: float = 0.45
    goal_velocity: float = 0.0
    power: float = 0.0015
    gravity: float = 0.0025


@struct.dataclass
class MountainCarState:
    """MountainCar state: position, velocity, step counter."""

    position: jax.Array
    velocity: jax.Array
    t: jax.Array


class MountainCar(Environment):
    """gymnasium 1.4.0 ``MountainCarContinuous-v0`` (``continuous_mountain_car.py``).

    Force in [-1, 1]; velocity and position clipped, velocity zeroed at the left wall; terminates at
    ``position >= 0.45 and velocity >= 0``; reward ``100 * terminated - 0.1 * force^2``; reset
    ``position ~ U(-0.6, -0.4)``, velocity 0; obs ``[position, velocity]``; horizon 999.

    gymnasium penalizes the *unclipped* ``action[0] ** 2``; here the action is clipped to [-1, 1]
    first (the interface contract), so both agree for every in-bounds action.
    """

    def __init__(self, horizon: int = 999):
        """Builds the env.

        Args:
            horizon: time limit (gymnasium's ``max_episode_steps`` is 999).
        """
        self.name = "mountaincar"
        self.obs_dim = 2
        self.action_dim = 1
        self.horizon = int(horizon)
        self.action_low = np.array([-1.0])
        self.action_high = np.array([1.0])

    @property
    def default_params(self) -> MountainCarParams:
        """gymnasium's constants (power 0.0015, max_speed 0.07, goal 0.45, ...)."""
        return MountainCarParams()

    def reset(self, key: PRNGKey, params: MountainCarParams) -> tuple[jax.Array, MountainCarState]:
        """Samples ``position ~ U(-0.6, -0.4)`` with zero velocity.

        Args:
            key: PRNG key.
            params: env parameters (unused).

        Returns:
            ``(obs, state)``: obs float32 (2,).
        """
        del params
        position = jax.random.uniform(key, (), jnp.float32, minval=-0.6, maxval=-0.4)
        state = MountainCarState(
            position=position, velocity=jnp.zeros((), jnp.float32), t=jnp.zeros((), jnp.int32)
        )
        return self._obs(state), state

    def step(
        self, key: PRNGKey, state: MountainCarState, action: jax.Array, params: MountainCarParams
    ) -> StepOutput:
        """One step of ``Continuous_MountainCarEnv.step`` (see ``Environment.step``).

        Args:
            key: PRNG key (unused).
            state: current state.
            action: float32 (1,), normalized force in [-1, 1].
            params: env parameters.

        Returns:
            ``(obs (2,), state, reward (), terminated (), truncated (), {})``.
        """
        del key
        force = self.scale_action(action)[0]
        velocity = (
            state.velocity + force * params.power - params.gravity * jnp.cos(3 * state.position)
        )
        velocity = jnp.clip(velocity, -params.max_speed, params.max_speed)
        position = jnp.clip(state.position + velocity, params.min_position, params.max_position)
        velocity = jnp.where((position == params.min_position) & (velocity < 0), 0.0, velocity)
        terminated = (position >= params.goal_position) & (velocity >= params.goal_velocity)
        reward = jnp.where(terminated, 100.0, 0.0) - force**2 * 0.1
        t = state.t + 1
        state = MountainCarState(position=position, velocity=velocity, t=t)
        truncated = time_limit(t, self.horizon, terminated)
        return self._obs(state), state, reward.astype(jnp.float32), terminated, truncated, {}

    @staticmethod
    def _obs(state: MountainCarState) -> jax.Array:
        return jnp.stack([state.position, state.velocity]).astype(jnp.float32)
