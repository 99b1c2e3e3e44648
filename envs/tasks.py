"""Meta-RL task families (paper App. B.2 "Meta-RL"; docs/design.md "Meta-RL task families"),
gymnax-style.

A task family is an env plus two seeded task sets. A task is the env's own params pytree (the
``params`` argument of ``reset``/``step``), so a task set is that pytree with a leading task axis
and a batch of tasks is rolled out with ``jax.vmap`` over params::

    family = envs.make_family("hopper_params")
    train, test = family.tasks(seed=0)           # MjxParams, leaves [40, ...] / [10, ...]
    step = jax.jit(jax.vmap(family.env.step))    # over (keys, states, actions, params)
    json.dumps(family.describe(train))           # one dict per task, saved with the run

The draw: ``key_train, key_test = jax.random.split(jax.random.PRNGKey(seed))``; each split is
then sampled from its own key (``TaskFamily.sample``), so the two sets are independent, and the
same seed always gives identical arrays (for a given JAX version: ``jax.random``'s bits may
change between releases, which is why ``describe`` output is saved with a run).

Families (the registry ``FAMILIES``; ``envs.make_family(name)``):

* ``cartpole_fl_ood``: DSO's continuous CartPole, force magnitude and pole half-length (OOD test).
* ``invdoublepend_params``, ``hopper_params``, ``walker2d_params``: the MJX envs with
  rand_param_envs' per-element multipliers on masses, inertias, damping and friction.
* ``cheetah_vel_ood``: HalfCheetah with a target velocity (OOD test).
* ``lunarlander_params``: gymnasium's LunarLanderContinuous with random gravity (Box2D).

MJX and gymnasium are imported only when a family is built, so ``from espl_jax import envs``
stays cheap.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax.envs import box2d
from espl_jax.envs.base import Environment, PRNGKey
from espl_jax.envs.box2d import LunarLanderParams
from espl_jax.envs.classic import CartPole, CartPoleParams
from espl_jax.envs.physics import with_physics

Params = Any
Split = Literal["train", "test"]
Interval = tuple[float, float]


# --------------------------------------------------------------------------------------------
# sampling helpers
# --------------------------------------------------------------------------------------------


def unit_to_union(u: jax.Array, intervals: Sequence[Interval]) -> jax.Array:
    """Maps ``u ~ U[0, 1)`` onto the union of disjoint intervals, uniformly (density 1 / length).

    ``u`` scaled to the union's total length is laid along the intervals end to end, so each
    interval is hit in proportion to its length (e.g. ``[5, 7.5] u [12.5, 15]``: each half the
    time).

    Args:
        u: float array of uniforms in [0, 1), any shape.
        intervals: ``((low, high), ...)``, sorted and non-overlapping.

    Returns:
        float32, ``u``'s shape, every element inside one of the intervals.
    """
    lows = np.array([a for a, _ in intervals], np.float64)
    highs = np.array([b for _, b in intervals], np.float64)
    if np.any(highs <= lows) or np.any(lows[1:] < highs[:-1]):
        raise ValueError(f"intervals must be sorted, non-empty and disjoint, got {intervals}")
    widths = highs - lows
    starts = np.concatenate([[0.0], np.cumsum(widths)[:-1]])  # offset of each interval along u
    length = jnp.asarray(u, jnp.float32) * jnp.float32(widths.sum())
    idx = jnp.searchsorted(jnp.asarray(starts[1:], jnp.float32), length, side="right")
    x = jnp.asarray(lows, jnp.float32)[idx] + (length - jnp.asarray(starts, jnp.float32)[idx])
    # float32 rounding of low + offset could step over an interval's end; clip it back
    return jnp.clip(x, jnp.asarray(lows, jnp.float32)[idx], jnp.asarray(highs, jnp.float32)[idx])


def uniform_union(key: PRNGKey, shape: tuple[int, ...], intervals: Sequence[Interval]) -> jax.Array:
    """float32 ``shape`` drawn uniformly over a union of disjoint intervals (``unit_to_union``)."""
    return unit_to_union(jax.random.uniform(key, shape, jnp.float32), intervals)


def broadcast_tasks(params: Params, n: int) -> Params:
    """``n`` copies of a params pytree: every leaf as float32 ``[n, *leaf.shape]``."""
    return jax.tree.map(
        lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.float32), (n, *np.shape(x))), params
    )


def num_tasks(params: Params) -> int:
    """Size of the leading task axis of a task batch."""
    return int(np.shape(jax.tree.leaves(params)[0])[0])


def _to_python(x: np.ndarray) -> float | list:
    """A float32 array as JSON-ready python floats (exact: float64 holds every float32)."""
    return np.asarray(x, np.float64).tolist()


# --------------------------------------------------------------------------------------------
# the family interface
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TaskFamily:
    """A meta-RL task distribution: an env and its seeded train/test task sets.

    Subclasses implement ``sample`` and ``_describe_one``.

    Attributes:
        name: registry name, e.g. ``"hopper_params"``.
        env: the underlying ``Environment``, built with the family's horizon (for gymnasium's
            Box2D tasks a ``HostEnv``, envs/box2d.py).
        n_train: number of meta-training tasks.
        n_test: number of meta-test tasks.
        use_next_obs_in_context: whether the context encoder sees s' (PEARL's
            ``use_next_obs_in_context``: on where the dynamics differ across tasks, off where
            only the reward does, as in the authors' cheetah config).
    """

    name: str
    env: Environment
    n_train: int
    n_test: int
    use_next_obs_in_context: bool = True

    def split_keys(self, seed: int) -> tuple[PRNGKey, PRNGKey]:
        """``(key_train, key_test)``: the two halves of ``jax.random.split(PRNGKey(seed))``."""
        key_train, key_test = jax.random.split(jax.random.PRNGKey(seed))
        return key_train, key_test

    def tasks(self, seed: int) -> tuple[Params, Params]:
        """The train and test task sets of ``seed`` (a pure function of ``seed``).

        Args:
            seed: integer seed.

        Returns:
            ``(train, test)``: the env's params pytree with leaves ``[n_train, ...]`` and
            ``[n_test, ...]``; task ``i`` is ``jax.tree.map(lambda x: x[i], train)``.
        """
        key_train, key_test = self.split_keys(seed)
        return (
            self._jit_sample(key_train, self.n_train, "train"),
            self._jit_sample(key_test, self.n_test, "test"),
        )

    @functools.cached_property
    def _jit_sample(self) -> Callable[[PRNGKey, int, Split], Params]:
        # one compiled program per split instead of a dozen eagerly dispatched (and compiled) ops
        return jax.jit(self.sample, static_argnums=(1, 2))

    def sample(self, key: PRNGKey, n: int, split: Split) -> Params:
        """``n`` tasks of one split drawn from ``key``: params leaves ``[n, ...]``."""
        raise NotImplementedError

    def describe(self, params: Params) -> list[dict]:
        """One JSON-serialisable dict per task of a batch: the family's task params.

        Args:
            params: a task batch (leaves ``[n, ...]``), e.g. one of ``tasks(seed)``.

        Returns:
            ``n`` dicts of python floats / nested lists, in the env's own units.
        """
        host = jax.tree.map(np.asarray, params)
        return [
            self._describe_one(jax.tree.map(lambda x, i=i: x[i], host))
            for i in range(num_tasks(host))
        ]

    def _describe_one(self, params: Params) -> dict:
        """The dict of one task (numpy leaves, no task axis)."""
        raise NotImplementedError


# --------------------------------------------------------------------------------------------
# cartpole_fl_ood
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CartPoleForceLengthOOD(TaskFamily):
    """``cartpole_fl_ood``: CartPole with random force magnitude and pole half-length, OOD test.

    Paper App. B.2 ("Cartpole-fl-ood"; the same continuous CartPole as the single-task one, i.e.
    DSO's, ``envs.classic.CartPole``), horizon 200; the authors' CSP
    ``rlkit/envs/cartpole_wrappper_ood.py`` (``sample_ood_tasks(40, 10)``). Per task, each
    coordinate independently: train ``force_mag ~ U[7.5, 12.5]``, ``length ~ U[0.3, 0.7]``;
    test ``force_mag ~ U([5, 7.5] u [12.5, 15])``, ``length ~ U([0.2, 0.3] u [0.7, 0.8])``
    (uniform over each union, ``uniform_union``). ``length`` is the pole's HALF-length, as in
    DSO's code (default 0.5); all other ``CartPoleParams`` keep their defaults.

    Draw: ``u = jax.random.uniform(key_split, (n, 2))``; ``force_mag`` from ``u[:, 0]``,
    ``length`` from ``u[:, 1]``, each through ``unit_to_union``.

    Params: ``CartPoleParams``, every field float32 ``[n]``.
    """

    force_mag_train: tuple[Interval, ...] = ((7.5, 12.5),)
    length_train: tuple[Interval, ...] = ((0.3, 0.7),)
    force_mag_test: tuple[Interval, ...] = ((5.0, 7.5), (12.5, 15.0))
    length_test: tuple[Interval, ...] = ((0.2, 0.3), (0.7, 0.8))

    def sample(self, key: PRNGKey, n: int, split: Split) -> CartPoleParams:
        force_intervals = self.force_mag_train if split == "train" else self.force_mag_test
        length_intervals = self.length_train if split == "train" else self.length_test
        u = jax.random.uniform(key, (n, 2), jnp.float32)
        return broadcast_tasks(self.env.default_params, n).replace(
            force_mag=unit_to_union(u[:, 0], force_intervals),
            length=unit_to_union(u[:, 1], length_intervals),
        )

    def _describe_one(self, params: CartPoleParams) -> dict:
        return {"force_mag": _to_python(params.force_mag), "length": _to_python(params.length)}


# --------------------------------------------------------------------------------------------
# invdoublepend_params, hopper_params, walker2d_params
# --------------------------------------------------------------------------------------------

# rand_param_envs' RandomEnv.sample_tasks: multiplier base per randomized model field
RAND_PARAM_BASES: tuple[tuple[str, float], ...] = (
    ("body_mass", 1.5),
    ("body_inertia", 1.5),
    ("dof_damping", 1.3),
    ("geom_friction", 1.5),
)


@dataclass(frozen=True)
class MjxPhysicsFamily(TaskFamily):
    """``*_params``: an MJX env whose masses, inertias, damping and friction are randomized.

    Paper App. B.2 ("Walker2d-params", "Hopper-params", "InvDoublePend-params": "the dynamics
    parameters of the environment are randomly initialized"; horizon 200; 40 train / 10 test),
    built on rand_param_envs (github dennisl88/rand_param_envs, ``rand_param_envs/base.py``,
    ``RandomEnv.sample_tasks`` with ``log_scale_limit`` 3, as in its ``hopper_rand_params.py``):
    every array element gets its own multiplier on the model's default value,

        body_mass, body_inertia, geom_friction  x 1.5 ** U(-3, 3),
        dof_damping                             x 1.3 ** U(-3, 3).

    Elements whose default is 0 (the world body's mass and inertia, the free root joints'
    damping) stay 0. Train and test come from the same distribution (the authors sample 50 tasks
    with the unseeded global numpy RNG and split them 40/10; here both sets are seeded). The
    defaults are gymnasium v5's models (``envs.mjx``), not the gym-0.x XMLs of rand_param_envs.

    Draw: one array of exponents ``jax.random.uniform(key_split, (n, size), minval=-3,
    maxval=3)``, ``size`` the total element count of the four fields, cut per task into the
    fields in the order of ``RAND_PARAM_BASES`` (each reshaped to the field's shape). One draw,
    not one per field: XLA's CPU compile of each threefry call costs about a second here.

    Params: ``envs.mjx.MjxParams`` with leaves float32 ``[n, nbody]``, ``[n, nbody, 3]``,
    ``[n, nv]``, ``[n, ngeom, 3]``.
    """

    log_scale_limit: float = 3.0
    bases: tuple[tuple[str, float], ...] = RAND_PARAM_BASES

    def multipliers(self, key: PRNGKey, n: int) -> dict[str, jax.Array]:
        """The per-element multipliers of ``n`` tasks.

        Args:
            key: the split's key.
            n: number of tasks.

        Returns:
            ``{field: float32 [n, *default.field.shape]}`` for the fields of ``bases``, field
            ``f`` in ``[base_f ** -3, base_f ** 3]``.
        """
        default = self.env.default_params
        shapes = [np.shape(getattr(default, field)) for field, _ in self.bases]
        sizes = [int(np.prod(shape)) for shape in shapes]
        lim = self.log_scale_limit
        exponents = jax.random.uniform(key, (n, sum(sizes)), jnp.float32, -lim, lim)
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        fields = {}
        for (field, base), shape, lo, hi in zip(
            self.bases, shapes, offsets[:-1], offsets[1:], strict=True
        ):
            exponent = exponents[:, lo:hi].reshape(n, *shape)
            fields[field] = jnp.power(jnp.float32(base), exponent)
        return fields

    def sample(self, key: PRNGKey, n: int, split: Split) -> Params:
        del split  # train and test share the distribution
        default = self.env.default_params
        scaled = {f: getattr(default, f) * m for f, m in self.multipliers(key, n).items()}
        # fields outside ``bases`` (if the env's params have more) keep their defaults
        return broadcast_tasks(default, n).replace(**scaled)

    def _describe_one(self, params: Params) -> dict:
        return {field: _to_python(getattr(params, field)) for field, _ in self.bases}


# --------------------------------------------------------------------------------------------
# cheetah_vel_ood
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CheetahVelOOD(TaskFamily):
    """``cheetah_vel_ood``: HalfCheetah tracking a target velocity, OOD test velocities.

    Paper App. B.2 ("Cheetah-vel-ood": train ``v* ~ U[0, 2.5]``, test ``v* ~ U[2.5, 3.0]``,
    horizon 200, 50 train / 15 test); the authors' CSP ``rlkit/envs/half_cheetah_vel_ood.py``
    (reward ``-|v - v*| - 0.05 ||a||^2``, never terminates; see ``envs.mjx.HalfCheetahVel``;
    they draw with ``np.random.seed(1337)``, here from the family's seed). Physics at defaults.

    Draw: ``v* = jax.random.uniform(key_split, (n,), minval, maxval)``.

    Params: ``envs.mjx.CheetahVelParams``: the default physics broadcast to ``[n, ...]`` and
    ``target_velocity`` float32 ``[n]``.
    """

    train_velocity: Interval = (0.0, 2.5)
    test_velocity: Interval = (2.5, 3.0)

    def sample(self, key: PRNGKey, n: int, split: Split) -> Params:
        low, high = self.train_velocity if split == "train" else self.test_velocity
        velocity = jax.random.uniform(key, (n,), jnp.float32, low, high)
        return broadcast_tasks(self.env.default_params, n).replace(target_velocity=velocity)

    def _describe_one(self, params: Params) -> dict:
        return {"target_velocity": _to_python(params.target_velocity)}


# --------------------------------------------------------------------------------------------
# lunarlander_params
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LunarLanderGravity(TaskFamily):
    """``lunarlander_params``: gymnasium's LunarLanderContinuous with a random gravity per task.

    Paper App. B.2 ("LunarLander-params": "we randomly initialize the gravity", horizon 1000,
    40 train / 10 test); the authors' CSP ``rlkit/envs/lunarlander_wapper.py`` wraps a
    ``rand_param_envs.lunar_lander_rand_params`` module that neither the authors' repository nor
    dennisl88/rand_param_envs contains, so the range is ours: ``gravity ~ U(-11, -5)`` for train
    and test alike. Why: gymnasium asserts ``-12 < gravity < 0``; -11 keeps a margin from that
    bound while being 10% stronger than the default -10, and -5 halves it, so tasks differ from
    the default in both directions and the lander stays controllable (at -11 the main engine at
    full throttle still accelerates it upwards: from reset, vertical velocity -0.50 -> +0.03 in
    40 steps, vs -0.49 -> +0.13 at -10).

    The env is gymnasium's, stepped on the host (``envs/box2d.py``): a task's params are the
    ``gymnasium.make`` keywords of its env; ``host_kwargs(params, i)`` gives those of task ``i``,
    for ``family.env.make_env(**kwargs)`` (the reference env of its policy.py).

    Draw: ``gravity = jax.random.uniform(key_split, (n,), minval=-11, maxval=-5)``.

    Params: ``LunarLanderParams`` with ``gravity`` float32 ``[n]``.
    """

    gravity_range: Interval = (-11.0, -5.0)

    def sample(self, key: PRNGKey, n: int, split: Split) -> LunarLanderParams:
        del split  # train and test share the distribution
        low, high = self.gravity_range
        return LunarLanderParams(gravity=jax.random.uniform(key, (n,), jnp.float32, low, high))

    def host_kwargs(self, params: LunarLanderParams, i: int) -> dict:
        """The ``gymnasium.make`` kwargs of task ``i`` of a batch, e.g. ``{"gravity": -7.3}``."""
        return {"gravity": float(np.asarray(params.gravity)[i])}

    def _describe_one(self, params: LunarLanderParams) -> dict:
        return {"gravity": _to_python(params.gravity)}


# --------------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------------

META_HORIZON = 200  # paper App. B.2, every family but lunarlander_params (1000)


def _cartpole_fl_ood() -> TaskFamily:
    return CartPoleForceLengthOOD("cartpole_fl_ood", CartPole(horizon=META_HORIZON), 40, 10)


def _mjx_family(name: str, env_name: str) -> Callable[..., TaskFamily]:
    def factory(physics: str = "mjx") -> TaskFamily:
        from espl_jax.envs.mjx import MJX_ENVS

        env = with_physics(MJX_ENVS[env_name](horizon=META_HORIZON), physics)
        return MjxPhysicsFamily(name, env, 40, 10)

    factory.__name__ = f"_{name}"
    return factory


def _cheetah_vel_ood(physics: str = "mjx") -> TaskFamily:
    from espl_jax.envs.mjx import HalfCheetahVel

    return CheetahVelOOD(
        "cheetah_vel_ood",
        with_physics(HalfCheetahVel(horizon=META_HORIZON), physics),
        50,
        15,
        use_next_obs_in_context=False,
    )


def _lunarlander_params() -> TaskFamily:
    return LunarLanderGravity("lunarlander_params", box2d.lunarlander(horizon=1000), 40, 10)


FAMILIES: dict[str, Callable[..., TaskFamily]] = {
    "cartpole_fl_ood": _cartpole_fl_ood,
    "cheetah_vel_ood": _cheetah_vel_ood,
    "hopper_params": _mjx_family("hopper_params", "hopper"),
    "invdoublepend_params": _mjx_family("invdoublepend_params", "inverted_double_pendulum"),
    "lunarlander_params": _lunarlander_params,
    "walker2d_params": _mjx_family("walker2d_params", "walker2d"),
}

# The families simulated by MuJoCo (their factories take ``physics=``, envs.PHYSICS).
MUJOCO_FAMILIES = ("cheetah_vel_ood", "hopper_params", "invdoublepend_params", "walker2d_params")

__all__ = [
    "FAMILIES",
    "MUJOCO_FAMILIES",
    "RAND_PARAM_BASES",
    "CartPoleForceLengthOOD",
    "CheetahVelOOD",
    "LunarLanderGravity",
    "LunarLanderParams",
    "MjxPhysicsFamily",
    "TaskFamily",
    "broadcast_tasks",
    "num_tasks",
    "uniform_union",
    "unit_to_union",
]
