"""Functional JAX environments (gymnax-style) and host-side reference environments.

Usage::

    from espl_jax import envs
    env = envs.make("pendulum")
    obs, state = env.reset(key, env.default_params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

Meta-RL task families (``envs/tasks.py``): an env plus seeded train/test task sets, each a batch
of the env's params with a leading task axis::

    family = envs.make_family("hopper_params")
    train, test = family.tasks(seed=0)

To add an environment, add ``name -> factory`` to ``_REGISTRY`` below (or call ``register``). A
factory is any callable returning an ``Environment``; keep heavy imports (MJX, Box2D) inside the
factory so ``from espl_jax import envs`` stays cheap (``envs.box2d`` imports gymnasium only when
an env is built)::

    def _hopper(**kwargs):
        from espl_jax.envs.hopper import Hopper

        return Hopper(**kwargs)
"""

from __future__ import annotations

from collections.abc import Callable

from espl_jax.envs import box2d, tasks
from espl_jax.envs.base import Environment, time_limit
from espl_jax.envs.box2d import HostEnv
from espl_jax.envs.classic import CartPole, MountainCar, Pendulum
from espl_jax.envs.physics import PHYSICS, with_physics
from espl_jax.envs.tasks import TaskFamily

# A registry entry builds a functional env: in JAX, or stepped on the host behind the same
# interface (MuJoCo's C engine, envs/native.py; gymnasium's Box2D envs, envs/box2d.py).
EnvFactory = Callable[..., Environment]


def _mjx_factory(name: str) -> EnvFactory:
    """A factory that imports ``envs.mjx`` (and with it MuJoCo/MJX) only when called."""

    def factory(physics: str = "mjx", **kwargs) -> Environment:
        from espl_jax.envs.mjx import MJX_ENVS

        return with_physics(MJX_ENVS[name](**kwargs), physics)

    factory.__name__ = f"make_{name}"
    return factory


_REGISTRY: dict[str, EnvFactory] = {
    "cartpole": CartPole,
    "mountaincar": MountainCar,
    "pendulum": Pendulum,
    # MJX envs (envs/mjx.py): gymnasium v5 MuJoCo tasks and PyBullet's swing-up
    "halfcheetah": _mjx_factory("halfcheetah"),
    "hopper": _mjx_factory("hopper"),
    "inverted_double_pendulum": _mjx_factory("inverted_double_pendulum"),
    "inverted_pendulum_swingup": _mjx_factory("inverted_pendulum_swingup"),
    "walker2d": _mjx_factory("walker2d"),
    # gymnasium Box2D envs, stepped on the host through callbacks (envs/box2d.py)
    "bipedalwalker": box2d.bipedalwalker,
    "lunarlander": box2d.lunarlander,
}

KNOWN_ENVS: tuple[str, ...] = tuple(sorted(_REGISTRY))
# The envs and families simulated by MuJoCo: their factories take ``physics=`` (``PHYSICS``).
MUJOCO: frozenset[str] = frozenset(
    {name for name, f in _REGISTRY.items() if f.__name__.startswith("make_")}
    | set(tasks.MUJOCO_FAMILIES)
)
KNOWN_FAMILIES: tuple[str, ...] = tuple(sorted(tasks.FAMILIES))


def register(name: str, factory: EnvFactory) -> None:
    """Adds an environment to the registry (and to ``KNOWN_ENVS``).

    Args:
        name: registry name; must not be registered yet.
        factory: callable ``factory(**kwargs) -> Environment``.
    """
    global KNOWN_ENVS
    if name in _REGISTRY or name in tasks.FAMILIES:
        raise ValueError(f"environment {name!r} is already registered (as an env or a family)")
    _REGISTRY[name] = factory
    KNOWN_ENVS = tuple(sorted(_REGISTRY))


def make(name: str, **kwargs) -> Environment:
    """Builds a registered environment.

    Args:
        name: registry name, one of ``KNOWN_ENVS``.
        **kwargs: forwarded to the env's factory (e.g. ``horizon=200``).

    Returns:
        The environment instance (for the gymnasium Box2D envs a ``HostEnv``).

    Raises:
        ValueError: ``name`` is not registered; the message lists the known env names and the
            task families (a family name is refused too: build it with ``make_family``).
    """
    if name in tasks.FAMILIES:
        raise ValueError(
            f"{name!r} is a meta-RL task family, not an environment; use envs.make_family({name!r})"
        )
    if name not in _REGISTRY:
        raise ValueError(
            f"unknown environment {name!r}; known: {', '.join(sorted(_REGISTRY))}; "
            f"meta-RL task families: {', '.join(KNOWN_FAMILIES)}"
        )
    return _REGISTRY[name](**kwargs)


def is_family(name: str) -> bool:
    """Whether ``name`` is a registered meta-RL task family (``make_family``)."""
    return name in tasks.FAMILIES


def make_family(name: str, **kwargs) -> TaskFamily:
    """Builds a meta-RL task family (``envs/tasks.py``; paper App. B.2).

    Args:
        name: one of ``KNOWN_FAMILIES``.
        **kwargs: forwarded to the family's factory (``physics=`` for the ``MUJOCO`` ones).

    Returns:
        The ``TaskFamily``: its env (built with the family's horizon), task counts, and the
        seeded ``tasks(seed) -> (train, test)`` params batches.

    Raises:
        ValueError: ``name`` is not a family; the message lists the known families.
    """
    if name not in tasks.FAMILIES:
        raise ValueError(
            f"unknown task family {name!r}; known: {', '.join(KNOWN_FAMILIES)}"
            + (f" ({name!r} is a single-task environment: envs.make)" if name in _REGISTRY else "")
        )
    return tasks.FAMILIES[name](**kwargs)


__all__ = [
    "KNOWN_ENVS",
    "KNOWN_FAMILIES",
    "MUJOCO",
    "PHYSICS",
    "CartPole",
    "Environment",
    "HostEnv",
    "MountainCar",
    "Pendulum",
    "TaskFamily",
    "is_family",
    "make",
    "make_family",
    "register",
    "time_limit",
    "with_physics",
]
