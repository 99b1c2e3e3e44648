"""Host-side reference environments (gymnasium), used to evaluate exported policies.

``reference_env(name)`` returns the implementation each JAX env in ``envs/`` reproduces. Its
``step`` takes actions in the env's OWN units (``[env.action_low, env.action_high]``), not the
normalized [-1, 1] of the JAX envs:

* ``pendulum``: ``gymnasium.make("Pendulum-v1")`` (torque in [-2, 2], 200-step limit).
* ``mountaincar``: ``gymnasium.make("MountainCarContinuous-v0")`` (force in [-1, 1], 999 steps).
* ``cartpole``: ``ContinuousCartPole``, DSO's ``CustomCartPoleContinuous-v0`` in numpy float64
  (action in [-1, 1], force ``30 * action``), wrapped in a 1000-step ``TimeLimit``.
* ``lunarlander``, ``bipedalwalker``: the gymnasium Box2D envs themselves (``envs/box2d.py``;
  the trainer steps the same envs on the host).
* ``inverted_double_pendulum``, ``hopper``, ``walker2d``, ``halfcheetah``: gymnasium's MuJoCo
  ``v5`` classes, which the MJX envs reproduce. ``inverted_pendulum_swingup`` has none.

Nothing here is jit-able; this module runs on the host only.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

from espl_jax.envs import box2d


class ContinuousCartPole(gymnasium.Env):
    """DSO's continuous CartPole (``dso/task/control/envs/continuous_cartpole.py``), numpy float64.

    Ported from DSO's gym class to the gymnasium API (``reset(seed=...)`` and the 5-tuple
    ``step``). The action is clipped to [-1, 1] (DSO asserts it instead); the reward is 1.0 on
    every step including the terminal one (DSO returns 0.0 only for steps past termination, which
    gymnasium's contract forbids anyway).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        gravity: float = 9.8,
        masscart: float = 1.0,
        masspole: float = 0.1,
        length: float = 0.5,
        force_mag: float = 30.0,
        tau: float = 0.02,
        render_mode: str | None = None,
    ):
        """Builds the env.

        Args:
            gravity: gravitational acceleration.
            masscart: cart mass.
            masspole: pole mass.
            length: half the pole's length.
            force_mag: force at ``action = 1``.
            tau: Euler step in seconds.
            render_mode: accepted for API uniformity; rendering is not implemented.
        """
        self.render_mode = render_mode
        self.gravity = gravity
        self.masscart = masscart
        self.masspole = masspole
        self.total_mass = masspole + masscart
        self.length = length
        self.polemass_length = masspole * length
        self.force_mag = force_mag
        self.tau = tau
        self.theta_threshold_radians = 12 * 2 * math.pi / 360
        self.x_threshold = 2.4
        high = np.array(
            [
                self.x_threshold * 2,
                np.finfo(np.float32).max,
                self.theta_threshold_radians * 2,
                np.finfo(np.float32).max,
            ]
        )
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(1,), dtype=np.float64)
        self.observation_space = spaces.Box(-high, high, dtype=np.float64)
        self.state: np.ndarray | None = None

    def step(self, action):
        """One explicit-Euler step of DSO's ``stepPhysics``.

        Args:
            action: array-like (1,), force fraction in [-1, 1] (clipped).

        Returns:
            ``(obs (4,) float64, reward, terminated, truncated=False, {})``.
        """
        assert self.state is not None, "call reset() first"
        force = self.force_mag * float(
            np.clip(np.asarray(action, np.float64).reshape(-1)[0], -1, 1)
        )
        x, x_dot, theta, theta_dot = (float(v) for v in self.state)
        costheta = math.cos(theta)
        sintheta = math.sin(theta)
        temp = (force + self.polemass_length * theta_dot * theta_dot * sintheta) / self.total_mass
        thetaacc = (self.gravity * sintheta - costheta * temp) / (
            self.length * (4.0 / 3.0 - self.masspole * costheta * costheta / self.total_mass)
        )
        xacc = temp - self.polemass_length * thetaacc * costheta / self.total_mass
        x = x + self.tau * x_dot
        x_dot = x_dot + self.tau * xacc
        theta = theta + self.tau * theta_dot
        theta_dot = theta_dot + self.tau * thetaacc
        self.state = np.array([x, x_dot, theta, theta_dot])
        terminated = bool(
            x < -self.x_threshold
            or x > self.x_threshold
            or theta < -self.theta_threshold_radians
            or theta > self.theta_threshold_radians
        )
        return np.array(self.state), 1.0, terminated, False, {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Samples the state from ``U(-0.05, 0.05)^4``.

        Args:
            seed: optional seed for ``self.np_random``.
            options: unused.

        Returns:
            ``(obs (4,) float64, {})``.
        """
        super().reset(seed=seed)
        self.state = self.np_random.uniform(low=-0.05, high=0.05, size=(4,))
        return np.array(self.state), {}


def _cartpole(**kwargs) -> gymnasium.Env:
    return TimeLimit(ContinuousCartPole(**kwargs), max_episode_steps=1000)


def _cartpole_fl(**kwargs) -> gymnasium.Env:
    """cartpole_fl_ood's task: the same CartPole with the task's force_mag and (half-)length,
    horizon 200 (paper App. B.2)."""
    return TimeLimit(ContinuousCartPole(**kwargs), max_episode_steps=200)


_REFERENCES: dict[str, Callable[..., gymnasium.Env]] = {
    "cartpole": _cartpole,
    "cartpole_fl_ood": _cartpole_fl,
    "mountaincar": lambda **kwargs: gymnasium.make("MountainCarContinuous-v0", **kwargs),
    "pendulum": lambda **kwargs: gymnasium.make("Pendulum-v1", **kwargs),
    "lunarlander": lambda **kwargs: box2d.lunarlander().make_env(**kwargs),
    # lunarlander_params' tasks: the same env with the task's gravity (envs/tasks.py)
    "lunarlander_params": lambda **kwargs: box2d.lunarlander().make_env(**kwargs),
    "bipedalwalker": lambda **kwargs: box2d.bipedalwalker().make_env(**kwargs),
    # MJX envs reproduce these gymnasium v5 classes (envs/mjx.py). The swing-up task has no
    # gymnasium counterpart (PyBullet's is not installable here), so it has no reference.
    "inverted_double_pendulum": lambda **kw: gymnasium.make("InvertedDoublePendulum-v5", **kw),
    "hopper": lambda **kwargs: gymnasium.make("Hopper-v5", **kwargs),
    "walker2d": lambda **kwargs: gymnasium.make("Walker2d-v5", **kwargs),
    "halfcheetah": lambda **kwargs: gymnasium.make("HalfCheetah-v5", **kwargs),
}


REFERENCE_ENVS: tuple[str, ...] = tuple(sorted(_REFERENCES))


def reference_env(name: str, **kwargs) -> gymnasium.Env:
    """Builds the host-side reference implementation of a JAX env.

    Args:
        name: env name, as in ``envs.make``.
        **kwargs: forwarded to the constructor (e.g. ``render_mode``, cartpole's ``force_mag``).

    Returns:
        A gymnasium env (with its time limit) whose ``step`` takes actions in env units.

    Raises:
        ValueError: ``name`` has no reference; the message lists the known names.
    """
    if name not in _REFERENCES:
        raise ValueError(
            f"no reference environment for {name!r}; known: {', '.join(sorted(_REFERENCES))}"
        )
    return _REFERENCES[name](**kwargs)
