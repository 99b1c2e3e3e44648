"""MuJoCo environments stepped with MJX (``mujoco.mjx``), jit- and vmap-able.

Each env reproduces a gymnasium 1.4.0 MuJoCo ``v5`` class (model, ``frame_skip``, observation,
reward, termination and reset noise; sources in ``gymnasium/envs/mujoco/``), except
``inverted_pendulum_swingup``, which rebuilds PyBullet's ``InvertedPendulumSwingupBulletEnv`` task
on gymnasium's cart-pole model:

* ``inverted_double_pendulum``: ``InvertedDoublePendulum-v5``
  (``inverted_double_pendulum_v5.py``, ``assets/inverted_double_pendulum.xml``);
* ``hopper``: ``Hopper-v5`` (``hopper_v5.py``, ``assets/hopper.xml``);
* ``walker2d``: ``Walker2d-v5`` (``walker2d_v5.py``, ``assets/walker2d_v5.xml``);
* ``halfcheetah``: ``HalfCheetah-v5`` (``half_cheetah_v5.py``, ``assets/half_cheetah.xml``);
* ``inverted_pendulum_swingup``: PyBullet's ``InvertedPendulumSwingupBulletEnv-v0``
  (``pybullet_envs/gym_pendulum_envs.py``, ``robot_pendula.py``) on
  ``assets/inverted_pendulum.xml``, modified at load time (see ``InvertedPendulumSwingup``);
* ``HalfCheetahVel``: HalfCheetah-v5 with the target-velocity reward of the meta-RL family
  ``cheetah_vel_ood`` (``envs/tasks.py``); not in ``MJX_ENVS`` (no single-task benchmark).

The XML files are read at runtime from the installed gymnasium package (not copied into this
repo). The four gymnasium models load into MJX unchanged; only the swing-up model is modified.

Physics parameters (``MjxParams``: ``body_mass``, ``body_inertia``, ``dof_damping``,
``geom_friction``, in the model's own shapes) are written into the ``mjx.Model`` with
``Model.replace`` inside ``reset``/``step``, so a vmapped batch of params is a batch of different
physics. As when editing ``MjModel.body_mass`` etc. on the host without ``mj_setConst`` (which is
what ``rand_param_envs``' ``set_task``, behind PEARL's ``*-rand-params`` tasks, does), the
constants MuJoCo derives at compile time from the reference masses (``body_invweight0``,
``dof_invweight0``, which only scale the constraint regularizer) keep their default values.
The double pendulum and the swing-up have no contacts, so ``geom_friction`` has no effect there.

Precision: MJX runs in float32 (JAX's default) while gymnasium runs MuJoCo in float64;
``tests/test_envs_mjx.py`` states the agreement achieved. Actions are clipped to [-1, 1] before
scaling (the interface contract), so the control cost uses the clipped action; gymnasium uses the
raw action (MuJoCo clamps the control itself), so both agree for every in-bounds action.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
import warnings
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

# mujoco-mjx prints "Failed to import warp" on import when the optional GPU backend (NVIDIA Warp)
# is absent, as it is on every CPU install; MJX's JAX backend, the one used here, needs no Warp.
with contextlib.redirect_stdout(None):
    from mujoco import mjx

from espl_jax.envs.base import Environment, PRNGKey, StepOutput, time_limit


def gymnasium_xml_path(filename: str) -> str:
    """Path of a MuJoCo model shipped with the installed gymnasium package.

    Args:
        filename: file name inside ``gymnasium/envs/mujoco/assets/``, e.g. ``"hopper.xml"``.

    Returns:
        The absolute path as a string.

    The package is located without importing it (importing ``gymnasium.envs.mujoco`` needs
    gymnasium's optional rendering dependencies).
    """
    spec = importlib.util.find_spec("gymnasium")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("gymnasium is not installed; it ships the MuJoCo models")
    root = next(iter(spec.submodule_search_locations))
    path = os.path.join(root, "envs", "mujoco", "assets", filename)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"gymnasium ships no MuJoCo model {filename!r} (looked at {path})")
    return path


@contextlib.contextmanager
def mujoco_warnings_to_python() -> Iterator[None]:
    """Re-emits MuJoCo's warnings (e.g. the compiler's) as Python warnings while active.

    MuJoCo's default handler appends them to ``MUJOCO_LOG.TXT`` in the working directory
    (``half_cheetah.xml`` triggers one: ``settotalmass`` is deprecated in MuJoCo 3.x).
    """
    messages: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(messages.append)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)
        for message in messages:
            warnings.warn(f"MuJoCo: {message}", stacklevel=3)


@struct.dataclass
class MjxParams:
    """Physics parameters written into the ``mjx.Model`` at every ``reset``/``step``.

    Shapes follow the model (``nbody`` includes the world body 0, ``nv`` is the number of dofs,
    ``ngeom`` the number of geoms, in MuJoCo's own order).

    Attributes:
        body_mass: float32 (nbody,), body masses.
        body_inertia: float32 (nbody, 3), diagonal inertias in the body's inertial frame.
        dof_damping: float32 (nv,), joint damping.
        geom_friction: float32 (ngeom, 3), sliding/torsional/rolling friction.
    """

    body_mass: jax.Array
    body_inertia: jax.Array
    dof_damping: jax.Array
    geom_friction: jax.Array


@struct.dataclass
class MjxState:
    """State of an MJX env: the full ``mjx.Data`` and the step counter.

    Attributes:
        data: ``mjx.Data`` after the last step (or after reset).
        t: int32 (), number of env steps taken since reset.
    """

    data: mjx.Data
    t: jax.Array


class MjxEnv(Environment):
    """Common machinery of the MJX envs: model loading, params, reset noise, frame-skipped step.

    Subclasses set the class attributes ``env_name``, ``xml_file``, ``frame_skip`` and implement
    ``_obs`` and ``_reward``; they may override ``_load_model`` (to modify the model) and
    ``_init_qpos_qvel`` (reset distribution).

    Attributes:
        model: the host ``mujoco.MjModel`` (float64), e.g. for CPU reference rollouts.
        dt: seconds per env step, ``model.opt.timestep * frame_skip``.
    """

    env_name: str
    xml_file: str
    frame_skip: int
    forward_on_reset: bool = False  # run mjx.forward at reset (only if obs needs derived fields)

    def __init__(self, horizon: int = 1000):
        """Builds the env (loads the model and puts it on the default device; no compilation).

        Args:
            horizon: time limit (1000 for the single-task benchmarks, 200 for meta-RL).
        """
        self.model = self._load_model()
        self.name = self.env_name
        self.horizon = int(horizon)
        self.dt = float(self.model.opt.timestep) * self.frame_skip
        self.init_qpos = np.array(self.model.qpos0, np.float64)
        self.init_qvel = np.zeros(self.model.nv, np.float64)
        self.action_dim = int(self.model.nu)
        self.action_low, self.action_high = self._action_bounds()
        self.obs_dim = int(self._obs(mujoco.MjData(self.model), np).shape[-1])

    @functools.cached_property
    def _mx(self) -> mjx.Model:
        """The MJX model, put on the device on first use (the native backend never needs it).
        Concrete even when first asked for inside a jit trace: a cached tracer would leak."""
        with jax.ensure_compile_time_eval():
            return mjx.put_model(self.model)

    @functools.cached_property
    def _data0(self) -> mjx.Data:
        with jax.ensure_compile_time_eval():
            return mjx.make_data(self._mx)

    # ----------------------------------------------------------------------------------------
    # hooks
    # ----------------------------------------------------------------------------------------

    def _load_model(self) -> mujoco.MjModel:
        """Loads ``xml_file`` from gymnasium's assets, unmodified."""
        with mujoco_warnings_to_python():
            return mujoco.MjModel.from_xml_path(gymnasium_xml_path(self.xml_file))

    def _action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The actuators' ``ctrlrange`` (gymnasium's ``action_space`` bounds)."""
        ctrlrange = np.array(self.model.actuator_ctrlrange, np.float64)
        return ctrlrange[:, 0].copy(), ctrlrange[:, 1].copy()

    def _init_qpos_qvel(self, key: PRNGKey) -> tuple[jax.Array, jax.Array]:
        """Samples the initial ``(qpos (nq,), qvel (nv,))``; overridden per env."""
        raise NotImplementedError

    def _obs(self, data, xp=jnp) -> jax.Array:
        """The observation (..., obs_dim) of ``data`` in its own dtype.

        Task hooks (``_obs``, ``_reward``, ``_is_healthy``, ``_bullet_terms``) are written once
        for both backends: ``xp`` is ``jax.numpy`` (MJX, one env under vmap) or ``numpy`` (the
        native backend, ``envs/native.py``, float64 arrays with a leading batch axis), so they
        index from the end (``[..., i]``) and read only ``qpos``, ``qvel``, ``qfrc_constraint``
        and ``site_xpos`` of ``data``.
        """
        raise NotImplementedError

    def _before_substep(
        self, model: mjx.Model, data: mjx.Data, params: MjxParams
    ) -> tuple[mjx.Model, mjx.Data]:
        """``(model, data)`` for the next ``mjx.step``, for what MuJoCo itself does not model.

        The gymnasium envs need nothing; the swing-up adds Bullet's link damping and joint-limit
        rule (``InvertedPendulumSwingup``).
        """
        del params
        return model, data

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: MjxParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        """``(reward (...), terminated (...), info)`` of the transition ``data_before -> data``
        (``xp`` and batching: see ``_obs``)."""
        raise NotImplementedError

    # ----------------------------------------------------------------------------------------
    # API
    # ----------------------------------------------------------------------------------------

    @property
    def default_params(self) -> MjxParams:
        """The model's own masses, inertias, damping and friction, as float32 arrays."""
        m = self.model
        return MjxParams(
            body_mass=jnp.asarray(m.body_mass, jnp.float32),
            body_inertia=jnp.asarray(m.body_inertia, jnp.float32),
            dof_damping=jnp.asarray(m.dof_damping, jnp.float32),
            geom_friction=jnp.asarray(m.geom_friction, jnp.float32),
        )

    def mjx_model(self, params: MjxParams) -> mjx.Model:
        """The ``mjx.Model`` with ``params`` written in (batched if ``params`` is, under vmap).

        Args:
            params: physics parameters.

        Returns:
            The ``mjx.Model``.
        """
        return self._mx.replace(
            body_mass=jnp.asarray(params.body_mass, self._mx.body_mass.dtype),
            body_inertia=jnp.asarray(params.body_inertia, self._mx.body_inertia.dtype),
            dof_damping=jnp.asarray(params.dof_damping, self._mx.dof_damping.dtype),
            geom_friction=jnp.asarray(params.geom_friction, self._mx.geom_friction.dtype),
        )

    def data_from_qpos_qvel(
        self, qpos: jax.Array, qvel: jax.Array, params: MjxParams | None = None
    ) -> mjx.Data:
        """A fresh ``mjx.Data`` at ``(qpos, qvel)``, zero control and warm start.

        Derived quantities (positions of bodies, contact forces, ...) are computed with
        ``mjx.forward`` only if the env's observation needs them (``forward_on_reset``);
        ``mjx.step`` recomputes them from ``qpos``/``qvel`` anyway.

        Args:
            qpos: float (nq,), joint positions.
            qvel: float (nv,), joint velocities.
            params: physics parameters for the forward pass (default params if None).

        Returns:
            The ``mjx.Data``.
        """
        dtype = self._data0.qpos.dtype
        data = self._data0.replace(qpos=jnp.asarray(qpos, dtype), qvel=jnp.asarray(qvel, dtype))
        if self.forward_on_reset:
            params = self.default_params if params is None else params
            data = mjx.forward(self.mjx_model(params), data)
        return data

    def reset(self, key: PRNGKey, params: MjxParams) -> tuple[jax.Array, MjxState]:
        """Samples an initial state as the gymnasium class's ``reset_model`` does.

        Args:
            key: PRNG key.
            params: physics parameters.

        Returns:
            ``(obs, state)``: obs float32 (obs_dim,), state with ``t == 0``.
        """
        qpos, qvel = self._init_qpos_qvel(key)
        data = self.data_from_qpos_qvel(qpos, qvel, params)
        state = MjxState(data=data, t=jnp.zeros((), jnp.int32))
        return self._obs(data).astype(jnp.float32), state

    def step(
        self, key: PRNGKey, state: MjxState, action: jax.Array, params: MjxParams
    ) -> StepOutput:
        """Applies the scaled action as ``ctrl`` and runs ``frame_skip`` ``mjx.step`` calls.

        This is gymnasium's ``MujocoEnv.do_simulation`` (``mj_step(model, data, nstep=frame_skip)``;
        its trailing ``mj_rnePostConstraint`` only fills ``cacc``/``cfrc_*``, unused here).

        Args:
            key: PRNG key (unused; the dynamics are deterministic).
            state: current state.
            action: float32 (action_dim,), normalized to [-1, 1].
            params: physics parameters.

        Returns:
            ``(obs (obs_dim,), state, reward (), terminated (), truncated (), info)``; ``info``
            holds the reward terms of the gymnasium class (float32 scalars).
        """
        del key
        model = self.mjx_model(params)
        ctrl = self.scale_action(action).astype(state.data.ctrl.dtype)
        data0 = state.data.replace(ctrl=ctrl)

        def substep(_, d):
            return mjx.step(*self._before_substep(model, d, params))

        data = jax.lax.fori_loop(0, self.frame_skip, substep, data0)
        reward, terminated, info = self._reward(state.data, data, ctrl, params)
        t = state.t + 1
        truncated = time_limit(t, self.horizon, terminated)
        info = {k: jnp.asarray(v, jnp.float32) for k, v in info.items()}
        return (
            self._obs(data).astype(jnp.float32),
            MjxState(data=data, t=t),
            jnp.asarray(reward, jnp.float32),
            jnp.asarray(terminated, jnp.bool_),
            truncated,
            info,
        )


def _uniform(key: PRNGKey, shape: tuple[int, ...], scale: float) -> jax.Array:
    return jax.random.uniform(key, shape, jnp.float32, minval=-scale, maxval=scale)


# --------------------------------------------------------------------------------------------
# Locomotion: hopper, walker2d, halfcheetah
# --------------------------------------------------------------------------------------------


class _Locomotion(MjxEnv):
    """Shared parts of Hopper/Walker2d/HalfCheetah-v5: forward reward, control cost, reset noise.

    ``x_velocity = (qpos_after[0] - qpos_before[0]) / dt``; ``reward = forward_reward_weight *
    x_velocity + healthy_reward * is_healthy - ctrl_cost_weight * ||ctrl||^2``; obs
    ``[qpos[1:], qvel]`` (qvel clipped to [-10, 10] by Hopper and Walker2d, not by HalfCheetah).
    """

    forward_reward_weight: float = 1.0
    ctrl_cost_weight: float = 1e-3
    healthy_reward: float = 1.0
    reset_noise_scale: float = 5e-3
    gaussian_qvel_noise: bool = False  # HalfCheetah draws qvel noise from N(0, scale^2)
    clip_qvel_obs: bool = True

    def _init_qpos_qvel(self, key: PRNGKey) -> tuple[jax.Array, jax.Array]:
        k1, k2 = jax.random.split(key)
        s = self.reset_noise_scale
        qpos = jnp.asarray(self.init_qpos, jnp.float32) + _uniform(k1, (self.model.nq,), s)
        if self.gaussian_qvel_noise:
            noise = s * jax.random.normal(k2, (self.model.nv,), jnp.float32)
        else:
            noise = _uniform(k2, (self.model.nv,), s)
        return qpos, jnp.asarray(self.init_qvel, jnp.float32) + noise

    def _obs(self, data, xp=jnp) -> jax.Array:
        qvel = xp.clip(data.qvel, -10.0, 10.0) if self.clip_qvel_obs else data.qvel
        return xp.concatenate([data.qpos[..., 1:], qvel], axis=-1)

    def _is_healthy(self, data, xp=jnp) -> jax.Array:
        """bool (...), gymnasium's ``is_healthy`` (always true for envs that never terminate)."""
        return xp.ones(data.qpos.shape[:-1], xp.bool_)

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: MjxParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        del params
        x_velocity = (data.qpos[..., 0] - data_before.qpos[..., 0]) / self.dt
        forward_reward = self.forward_reward_weight * x_velocity
        ctrl_cost = self.ctrl_cost_weight * xp.sum(xp.square(ctrl), axis=-1)
        healthy = self._is_healthy(data, xp)
        healthy_reward = self.healthy_reward * healthy
        reward = forward_reward + healthy_reward - ctrl_cost
        info = {
            "x_position": data.qpos[..., 0],
            "x_velocity": x_velocity,
            "reward_forward": forward_reward,
            "reward_ctrl": -ctrl_cost,
            "reward_survive": healthy_reward,
        }
        return reward, xp.logical_not(healthy), info


class Hopper(_Locomotion):
    """gymnasium 1.4.0 ``Hopper-v5`` (``gymnasium/envs/mujoco/hopper_v5.py``, ``hopper.xml``).

    frame_skip 4 (dt 0.008 s, RK4 at 2 ms); 3 torques in [-1, 1] (gear 200); obs (11,)
    ``[qpos[1:6], clip(qvel, -10, 10)]``; reward ``x_velocity + 1 * healthy - 1e-3 ||a||^2``;
    terminates when unhealthy, i.e. unless ``0.7 < z``, ``-0.2 < torso angle < 0.2`` and every
    element of ``[qpos[2:], qvel]`` (unclipped) lies in ``(-100, 100)``. Reset
    ``qpos0 + U(+-5e-3)``, ``qvel ~ U(+-5e-3)``.
    """

    env_name = "hopper"
    xml_file = "hopper.xml"
    frame_skip = 4

    def _is_healthy(self, data, xp=jnp) -> jax.Array:
        z, angle = data.qpos[..., 1], data.qpos[..., 2]
        state = xp.concatenate([data.qpos[..., 2:], data.qvel], axis=-1)
        healthy_state = xp.all((state > -100.0) & (state < 100.0), axis=-1)
        return healthy_state & (z > 0.7) & (angle > -0.2) & (angle < 0.2)


class Walker2d(_Locomotion):
    """gymnasium 1.4.0 ``Walker2d-v5`` (``gymnasium/envs/mujoco/walker2d_v5.py``,
    ``walker2d_v5.xml``).

    frame_skip 4 (dt 0.008 s, RK4 at 2 ms); 6 torques in [-1, 1] (gear 100); obs (17,)
    ``[qpos[1:9], clip(qvel, -10, 10)]``; reward ``x_velocity + 1 * healthy - 1e-3 ||a||^2``;
    terminates when unhealthy, i.e. unless ``0.8 < z < 2.0`` and ``-1 < torso angle < 1``. Reset
    ``qpos0 + U(+-5e-3)``, ``qvel ~ U(+-5e-3)``.
    """

    env_name = "walker2d"
    xml_file = "walker2d_v5.xml"
    frame_skip = 4

    def _is_healthy(self, data, xp=jnp) -> jax.Array:
        z, angle = data.qpos[..., 1], data.qpos[..., 2]
        return (z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0)


class HalfCheetah(_Locomotion):
    """gymnasium 1.4.0 ``HalfCheetah-v5`` (``gymnasium/envs/mujoco/half_cheetah_v5.py``,
    ``half_cheetah.xml``).

    frame_skip 5 (dt 0.05 s, Euler at 10 ms); 6 torques in [-1, 1]; obs (17,) ``[qpos[1:9], qvel]``
    (not clipped); reward ``x_velocity - 0.1 ||a||^2``; never terminates. Reset
    ``qpos0 + U(+-0.1)``, ``qvel ~ 0.1 N(0, 1)``.
    """

    env_name = "halfcheetah"
    xml_file = "half_cheetah.xml"
    frame_skip = 5
    ctrl_cost_weight = 0.1
    healthy_reward = 0.0
    reset_noise_scale = 0.1
    gaussian_qvel_noise = True
    clip_qvel_obs = False

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: MjxParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        reward, terminated, info = super()._reward(data_before, data, ctrl, params, xp)
        del info["reward_survive"]  # HalfCheetah-v5 has no survival term
        return reward, terminated, info


@struct.dataclass
class CheetahVelParams(MjxParams):
    """``MjxParams`` plus the task of ``cheetah_vel_ood``: the target forward velocity.

    Attributes:
        target_velocity: float32 (), the target velocity ``v*`` of the root, in m/s.
    """

    target_velocity: jax.Array


class HalfCheetahVel(HalfCheetah):
    """HalfCheetah with a target velocity: the env of the meta-RL family ``cheetah_vel_ood``.

    The authors' CSP ``rlkit/envs/half_cheetah_vel_ood.py`` (guojm14/ESPL, after MAML's
    ``half_cheetah_env_rand.py``): reward ``-|v - v*| - 0.5 * 1e-1 * ||a||^2`` with ``v =
    (qpos_after[0] - qpos_before[0]) / dt`` (dt 0.05 s) and ``a`` the action in env units
    (``ctrlrange`` +-1, so equal to the normalized action); never terminates. Model, frame skip,
    reset noise and observation are ``HalfCheetah``'s (gymnasium v5, obs (17,)); PEARL's
    ``half_cheetah.py``, under the authors' class, also appends the torso's COM (obs (20,)).

    ``v*`` is ``params.target_velocity`` (``CheetahVelParams``), so a vmapped batch of params is
    a batch of tasks; the default 0.0 is the authors' fallback (``get('velocity', 0.0)``).
    """

    env_name = "halfcheetah_vel"
    ctrl_cost_weight = 0.05
    default_target_velocity = 0.0

    @property
    def default_params(self) -> CheetahVelParams:
        """The model's own physics and ``target_velocity`` 0.0."""
        physics = super().default_params
        return CheetahVelParams(
            **vars(physics),
            target_velocity=jnp.asarray(self.default_target_velocity, jnp.float32),
        )

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: CheetahVelParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        x_velocity = (data.qpos[..., 0] - data_before.qpos[..., 0]) / self.dt
        forward_reward = -xp.abs(x_velocity - params.target_velocity)
        ctrl_cost = self.ctrl_cost_weight * xp.sum(xp.square(ctrl), axis=-1)
        info = {
            "x_position": data.qpos[..., 0],
            "x_velocity": x_velocity,
            "reward_forward": forward_reward,
            "reward_ctrl": -ctrl_cost,
        }
        return forward_reward - ctrl_cost, xp.zeros(x_velocity.shape, xp.bool_), info


# --------------------------------------------------------------------------------------------
# Pendula
# --------------------------------------------------------------------------------------------


class InvertedDoublePendulum(MjxEnv):
    """gymnasium 1.4.0 ``InvertedDoublePendulum-v5`` (``inverted_double_pendulum_v5.py``,
    ``inverted_double_pendulum.xml``).

    frame_skip 5 (dt 0.05 s, RK4 at 10 ms); 1 force in [-1, 1] (gear 500); obs (9,) ``[x,
    sin(hinge angles) (2), cos(hinge angles) (2), clip(qvel, -10, 10) (3),
    clip(qfrc_constraint[0], -10, 10)]``. With ``(x_tip, y_tip)`` the tip site's x/z position:
    terminates when ``y_tip <= 1``; reward ``10 * (not terminated) - 0.01 x_tip^2 - (y_tip - 2)^2
    - 1e-3 v1^2 - 5e-3 v2^2`` (``v1, v2`` the hinge velocities). As in gymnasium, the site
    position and constraint force are those MuJoCo left in ``data`` after the last substep (from
    its final forward pass, not re-evaluated at the new ``qpos``); MJX's RK4 leaves the same.
    Reset ``qpos0 + U(+-0.1)``, ``qvel ~ 0.1 N(0, 1)``; ``mjx.forward`` runs at reset for the
    constraint force in the first observation (gymnasium's ``set_state`` runs ``mj_forward``).
    """

    env_name = "inverted_double_pendulum"
    xml_file = "inverted_double_pendulum.xml"
    frame_skip = 5
    forward_on_reset = True
    healthy_reward = 10.0
    reset_noise_scale = 0.1

    def _init_qpos_qvel(self, key: PRNGKey) -> tuple[jax.Array, jax.Array]:
        k1, k2 = jax.random.split(key)
        s = self.reset_noise_scale
        qpos = jnp.asarray(self.init_qpos, jnp.float32) + _uniform(k1, (self.model.nq,), s)
        qvel = jnp.asarray(self.init_qvel, jnp.float32) + s * jax.random.normal(
            k2, (self.model.nv,), jnp.float32
        )
        return qpos, qvel

    def _obs(self, data, xp=jnp) -> jax.Array:
        return xp.concatenate(
            [
                data.qpos[..., :1],
                xp.sin(data.qpos[..., 1:]),
                xp.cos(data.qpos[..., 1:]),
                xp.clip(data.qvel, -10.0, 10.0),
                xp.clip(data.qfrc_constraint, -10.0, 10.0)[..., :1],
            ],
            axis=-1,
        )

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: MjxParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        del data_before, ctrl, params
        x, y = data.site_xpos[..., 0, 0], data.site_xpos[..., 0, 2]
        terminated = y <= 1.0
        v1, v2 = data.qvel[..., 1], data.qvel[..., 2]
        dist_penalty = 0.01 * x**2 + (y - 2.0) ** 2
        vel_penalty = 1e-3 * v1**2 + 5e-3 * v2**2
        alive_bonus = self.healthy_reward * xp.logical_not(terminated)
        reward = alive_bonus - dist_penalty - vel_penalty
        info = {
            "reward_survive": alive_bonus,
            "distance_penalty": -dist_penalty,
            "velocity_penalty": -vel_penalty,
        }
        return reward, terminated, info


class InvertedPendulumSwingup(MjxEnv):
    """PyBullet's ``InvertedPendulumSwingupBulletEnv-v0``, rebuilt in MJX to Bullet's physics.

    Task, as PyBullet's ``gym_pendulum_envs.py``/``robot_pendula.py``: the pole starts hanging
    down, angle ``3.1415 + U(-0.1, 0.1)`` with zero velocity and the cart at rest at 0; force
    ``100 * a`` on the cart; reward ``cos(theta)`` every step (after the step); never terminates;
    horizon 1000; obs (5,) ``[x, x_dot, cos(theta), sin(theta), theta_dot]``; control period
    0.0165 s (PyBullet's ``timestep=0.0165, frame_skip=1``, one Bullet step per env step).

    Model: PyBullet loads ``pybullet_data/mjcf/inverted_pendulum.xml``, which is gymnasium's
    ``assets/inverted_pendulum.xml`` with the hinge unlimited. Bullet's MJCF importer does not
    read everything MuJoCo would, so the MuJoCo model is changed at load time to what PyBullet
    3.2.7 actually simulates (read back with ``getJointInfo``/``getDynamicsInfo``/
    ``getPhysicsEngineParameters`` and matched step by step, see ``tests/test_envs_mjx.py``):

    * the hinge is unlimited (gymnasium limits it to +-90 deg);
    * joint damping 0 on slider and hinge: the importer ignores the XML's ``damping="1"``. With
      it, neither the paper's formula nor a hand-written energy pump swung the pole up (a hinge
      damping of 1 N m s dissipates about as much power as +-100 N on the cart can pump in);
    * gravity 9.8 (PyBullet's scene), timestep 0.0165 s, semi-implicit Euler (Bullet's
      integrator) instead of RK4;
    * the pole's inertia about its COM is Bullet's (0.2664, 0.2665, 0.0267) kg m^2; the masses
      (cart 10.47 kg, pole 5.02 kg, from the capsules at density 1000) already agree;
    * Bullet's default link damping (``btMultiBody`` ``m_linearDamping = m_angularDamping = 0.04``):
      every link feels ``-m v (k + k|v|)`` at its COM and ``-I w (k + k|w|)``, applied here as
      ``xfrc_applied`` before each step (``_before_substep``); it slows the cart by ~5% at 3 m/s;
    * the slider's +-1 m limit acts as Bullet's joint-limit constraint (``btMultiBodyJointLimit
      Constraint`` under PyBullet's split impulse): within one step it sets the cart's velocity
      into the limit to ``erp * depth / dt`` outwards (erp 0.2) if the cart is less than 0.04 m
      beyond the limit, and to 0 (no push back) if deeper. In MuJoCo terms the limit is a
      constraint of impedance 0.9999 with reference acceleration ``-v / dt - k * r``, ``k =
      erp / dt^2`` or 0 by the depth at the start of the step (``jnt_solref`` set per step).

    Actions in [-1, 1] are the ``ctrl`` (gear 100 -> +-100 N; the model's own ``ctrlrange`` of +-3,
    i.e. +-300 N, is gymnasium's InvertedPendulum's).
    """

    env_name = "inverted_pendulum_swingup"
    xml_file = "inverted_pendulum.xml"
    frame_skip = 1
    timestep = 0.0165
    gravity = 9.8
    max_force = 100.0
    init_angle = 3.1415  # PyBullet's value, not pi
    init_noise = 0.1
    # Bullet's link-frame inertia of the pole (principal axes x, y (the hinge), z (the pole))
    pole_inertia = (0.26639019844481543, 0.26653950154827094, 0.026650811429848154)
    link_damping = 0.04  # btMultiBody's default linear and angular damping
    limit_erp = 0.2  # btContactSolverInfo's default m_erp
    split_depth = 0.04  # PyBullet's splitImpulsePenetrationThreshold (-0.04), as a depth

    def _load_model(self) -> mujoco.MjModel:
        with mujoco_warnings_to_python():
            spec = mujoco.MjSpec.from_file(gymnasium_xml_path(self.xml_file))
            spec.joint("hinge").limited = mujoco.mjtLimited.mjLIMITED_FALSE
            for joint in ("hinge", "slider"):
                spec.joint(joint).damping = np.zeros(3)  # (MuJoCo 3.17: a 3-vector)
            spec.option.timestep = self.timestep
            spec.option.gravity = [0.0, 0.0, -self.gravity]
            spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
            model = spec.compile()
        pole = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "pole")
        slider = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "slider")
        # the pole's inertial frame is its geometric one turned about the hinge axis (y) only,
        # so the diagonal keeps Bullet's axis order
        model.body_inertia[pole] = self.pole_inertia
        model.jnt_solref[slider] = self._limit_solref(0.0)
        model.jnt_solimp[slider] = [0.9999, 0.9999, 0.001, 0.5, 2.0]
        return model

    def _limit_solref(self, depth, xp=jnp):
        """The slider limit's ``solref`` (direct ``(-k, -b)``) when the cart is ``depth`` m beyond
        it (<= 0 inside): ``b = 1/dt`` stops it; ``k = erp/dt^2`` pushes back if shallower than
        ``split_depth``. (k is never exactly 0: MuJoCo reads ``solref[0] == 0`` as unset.)
        """
        dt = self.timestep
        k = xp.where(depth < self.split_depth, self.limit_erp / dt**2, 1e-9)
        return xp.stack([-k, xp.full_like(k, -1.0 / dt)])

    def _action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        gear = float(self.model.actuator_gear[0, 0])
        bound = self.max_force / gear
        return np.array([-bound]), np.array([bound])

    def _init_qpos_qvel(self, key: PRNGKey) -> tuple[jax.Array, jax.Array]:
        u = _uniform(key, (), self.init_noise)
        qpos = jnp.stack([jnp.zeros((), jnp.float32), self.init_angle + u])
        return qpos, jnp.zeros((self.model.nv,), jnp.float32)

    def _bullet_terms(self, qpos, qvel, body_mass, body_inertia, xp=jnp):
        """What Bullet adds before each step: ``(cart force (3,), pole force (3,), pole y torque,
        slider solref (2,))`` for one env (``xp``: see ``_obs``).

        Link damping (force at the COM, torque; world frame). Bodies: 1 the cart (slides along
        x), 2 the pole (turns by theta about y around the cart's origin). The pole's COM sits at
        ``R_y(theta) @ body_ipos`` from the pivot, so its velocity is ``(x_dot + theta_dot * r_z,
        0, -theta_dot * r_x)``; the hinge axis is a principal axis, so its angular damping is a
        y torque with inertia ``body_inertia[pole, 1]``. The limit rule: ``_limit_solref``.
        """
        k = self.link_damping
        x_dot, theta, theta_dot = qvel[0], qpos[1], qvel[1]
        px, _, pz = self.model.body_ipos[2]
        c, s = xp.cos(theta), xp.sin(theta)
        r_x, r_z = c * px + s * pz, -s * px + c * pz
        zero = xp.zeros_like(x_dot)
        v_cart = xp.stack([x_dot, zero, zero])
        v_pole = xp.stack([x_dot + theta_dot * r_z, zero, -theta_dot * r_x])

        def drag(mass, v):
            return -mass * v * (k + k * xp.sqrt(xp.sum(v * v)))

        torque = -body_inertia[2, 1] * theta_dot * (k + k * xp.abs(theta_dot))
        depth = xp.abs(qpos[0]) - self.model.jnt_range[0, 1]
        solref = self._limit_solref(depth, xp)
        return drag(body_mass[1], v_cart), drag(body_mass[2], v_pole), torque, solref

    def _before_substep(
        self, model: mjx.Model, data: mjx.Data, params: MjxParams
    ) -> tuple[mjx.Model, mjx.Data]:
        """Bullet's link damping as ``xfrc_applied`` and its limit rule as the slider's
        ``jnt_solref`` for this step (``_bullet_terms``)."""
        f_cart, f_pole, torque, solref = self._bullet_terms(
            data.qpos, data.qvel, params.body_mass, params.body_inertia
        )
        xfrc = jnp.zeros_like(data.xfrc_applied)
        xfrc = xfrc.at[1, :3].set(f_cart).at[2, :3].set(f_pole).at[2, 4].set(torque)
        solref = solref.astype(model.jnt_solref.dtype)
        data = data.replace(xfrc_applied=xfrc.astype(data.xfrc_applied.dtype))
        return model.replace(jnt_solref=model.jnt_solref.at[0].set(solref)), data

    def _native_before_substep(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """``_before_substep`` for MuJoCo's C engine, in place (``envs/native.py``)."""
        f_cart, f_pole, torque, solref = self._bullet_terms(
            data.qpos, data.qvel, model.body_mass, model.body_inertia, np
        )
        data.xfrc_applied[:] = 0.0
        data.xfrc_applied[1, :3] = f_cart
        data.xfrc_applied[2, :3] = f_pole
        data.xfrc_applied[2, 4] = torque
        model.jnt_solref[0] = solref

    def _obs(self, data, xp=jnp) -> jax.Array:
        x, theta = data.qpos[..., 0], data.qpos[..., 1]
        x_dot, theta_dot = data.qvel[..., 0], data.qvel[..., 1]
        return xp.stack([x, x_dot, xp.cos(theta), xp.sin(theta), theta_dot], axis=-1)

    def _reward(
        self, data_before, data, ctrl: jax.Array, params: MjxParams, xp=jnp
    ) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        del data_before, ctrl, params
        theta = data.qpos[..., 1]
        return xp.cos(theta), xp.zeros(theta.shape, xp.bool_), {}


MJX_ENVS: dict[str, type[MjxEnv]] = {
    cls.env_name: cls
    for cls in (InvertedDoublePendulum, InvertedPendulumSwingup, Hopper, Walker2d, HalfCheetah)
}

__all__ = [
    "MJX_ENVS",
    "CheetahVelParams",
    "HalfCheetah",
    "HalfCheetahVel",
    "Hopper",
    "InvertedDoublePendulum",
    "InvertedPendulumSwingup",
    "MjxEnv",
    "MjxParams",
    "MjxState",
    "Walker2d",
    "gymnasium_xml_path",
]
