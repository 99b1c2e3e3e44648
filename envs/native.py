"""MuJoCo tasks stepped by MuJoCo's C engine on the host: the fast physics on a CPU.

``NativeEnv(task)`` is a functional ``Environment`` over the same task definition as the MJX env
(``envs/mjx.py``: model, frame skip, reset distribution, observation, reward, termination,
params), so collection, evaluation and PEARL's protocol (``espl_jax/rollout.py``) run unchanged
inside the jitted scan. Only the physics leaves XLA: ``step`` is one ``jax.pure_callback`` with
``vmap_method="broadcast_all"``, so a vmapped batch (seeds × tasks × episodes) reaches the host
as one call per env step, which loops ``mj_step(model, data, nstep=frame_skip)`` over the lanes.
(On 2 cores that loop matched ``mujoco.rollout``'s thread pool and ``mjbatch`` at batch 1-40:
``benchmarks/env_throughput.py --backends``; it needs no extra dependency.)

The callback is pure: the whole simulator state lives in the JAX state, so checkpoints hold it
and a resumed run continues bit for bit. MuJoCo computes in float64 and JAX holds float32 (x64
off), so ``NativeState`` keeps each float64 as its two 32-bit words (``uint32 (..., 2)``):
``qpos``, ``qvel``, ``act``, ``qacc_warmstart`` and ``time``, everything ``mj_step`` reads of
these models' data. One env step from a state equals gymnasium's continuous stepping bit for bit
(``tests/test_envs_native.py``).

Params are the MJX env's (``MjxParams``, float32). A task's params become a cached ``MjModel``
copy with the fields written in; an element equal to the float32 rounding of the model's own
value keeps the model's float64 value, so the default params give gymnasium's model exactly and
a family's task (default × multiplier, in float32) gives what MJX simulates, in float64.
"""

from __future__ import annotations

import copy
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from espl_jax.envs.base import Environment, PRNGKey, StepOutput, time_limit
from espl_jax.envs.mjx import MjxEnv, MjxParams

# The MjxParams fields that are model fields (a family's params may carry task terms too, such
# as cheetah's target velocity, which only the reward reads).
MODEL_FIELDS = tuple(MjxParams.__dataclass_fields__)
HOOK_FIELDS = ("qpos", "qvel", "qfrc_constraint", "site_xpos")  # what obs and reward may read
# ``NativeState.physics`` is MuJoCo's state vector of this signature, [time, qpos, qvel, act,
# qacc_warmstart] (``mj_getState``; no history: these models have no delays); a step loads it
# with the ctrl appended in one ``mj_setState``.
STATE_SPEC = (
    mujoco.mjtState.mjSTATE_TIME
    | mujoco.mjtState.mjSTATE_QPOS
    | mujoco.mjtState.mjSTATE_QVEL
    | mujoco.mjtState.mjSTATE_ACT
    | mujoco.mjtState.mjSTATE_WARMSTART
)
STEP_SPEC = STATE_SPEC | mujoco.mjtState.mjSTATE_CTRL
MAX_CACHED_MODELS = 512
MAX_THREADS = 4  # a run has at most a few hundred distinct tasks
# A second worker (the calling thread steps one chunk, the pool the other) from 16 lanes on. On
# an idle 2-vCPU machine it pays from 8 (env steps/s, one vs two workers, hopper: 10.7k vs 10.4k
# at 5 lanes, 12.2k vs 15.8k at 8, 14.6k vs 19.3k at 16), but beside other busy processes (two
# training runs on the 2 vCPUs, as a seed sweep runs) the handoff waits for the scheduler: median
# 4.4k vs 2.9k at 8 lanes, 4.4k vs 5.3k at 16, 3.8k vs 7.1k at 40.
LANES_PER_WORKER = 8


@struct.dataclass
class NativeState:
    """The simulator state of one env.

    Attributes:
        physics: uint32 (n, 2), the float64 vector ``[time, qpos, qvel, act, qacc_warmstart]``
            as two 32-bit words per value (``qacc_warmstart`` is the solver's first guess for
            the next step: without it a restored state would not continue bit for bit).
        t: int32 (), env steps since reset.
    """

    physics: jax.Array
    t: jax.Array


def float64_words(x: jax.Array) -> jax.Array:
    """The float64 value of float32 ``x`` as uint32 words (..., 2), little-endian (as numpy's
    ``x.astype(np.float64).view(np.uint32)``), computed in JAX without x64.

    Every float32 is exactly a float64; subnormals are normalized (float64 has the exponent
    range), zero keeps its sign, inf and NaN stay inf and NaN.
    """
    b = jax.lax.bitcast_convert_type(jnp.asarray(x, jnp.float32), jnp.uint32)
    sign = b >> 31
    exp = (b >> 23) & 0xFF
    mant = b & 0x7FFFFF
    # a subnormal's leading 1 moves to bit 23 (shift s); its exponent is then -126 - s
    shift = jax.lax.clz(mant) - 8
    sub_mant = (mant << shift.astype(jnp.uint32)) & 0x7FFFFF
    exp64 = jnp.where(
        exp == 0xFF,
        jnp.uint32(0x7FF),
        jnp.where(exp == 0, jnp.where(mant == 0, 0, 897 - shift), exp + 896),
    ).astype(jnp.uint32)
    mant = jnp.where((exp == 0) & (mant != 0), sub_mant, mant)
    hi = (sign << 31) | (exp64 << 20) | (mant >> 3)
    lo = (mant & 7) << 29
    return jnp.stack([lo, hi], axis=-1)


def to_words(x: np.ndarray) -> np.ndarray:
    """float64 (...,) -> uint32 (..., 2) (numpy, the host side of ``float64_words``)."""
    x = np.ascontiguousarray(x, np.float64)
    return x.view(np.uint32).reshape(*x.shape, 2)


def from_words(w: np.ndarray) -> np.ndarray:
    """uint32 (..., 2) -> float64 (...,)."""
    return np.ascontiguousarray(w, np.uint32).view(np.float64)[..., 0]


class _FieldsRead(SimpleNamespace):
    """A hook view that records the fields the task's hooks read (``NativeEnv.__init__``)."""

    def __getattribute__(self, name: str):
        if not name.startswith("_"):
            object.__getattribute__(self, "_read").add(name)
        return object.__getattribute__(self, name)


class NativeEnv(Environment):
    """A MuJoCo task of ``envs/mjx.py`` stepped by MuJoCo's C engine (module docstring).

    A step is one host call with one flat uint32 array in and one out (each array a callback
    passes costs ~15 us, as much as a lane's physics): in, the state's words, the action's and
    the params' float32 bits; out, the new words and the float32 bits of ``[obs, reward,
    terminated, info...]``.

    Args:
        task: the MJX env whose task this is (model, hooks; its MJX model is never built).
        threads: host threads stepping a batch's lanes (default: the cores this process may
            use, at most ``MAX_THREADS``). Results do not depend on it: each lane's state is
            loaded whole before its step.
    """

    def __init__(self, task: MjxEnv, threads: int | None = None):
        self.task = task
        self.model = m = task.model
        self.name, self.horizon, self.dt = task.name, task.horizon, task.dt
        self.obs_dim, self.action_dim = task.obs_dim, task.action_dim
        self.action_low, self.action_high = task.action_low, task.action_high
        sizes = {"time": 1, "qpos": m.nq, "qvel": m.nv, "act": m.na, "warmstart": m.nv}
        ends = np.cumsum(list(sizes.values()))
        self._slices = {k: slice(e - n, e) for (k, n), e in zip(sizes.items(), ends, strict=True)}
        self.state_size = int(ends[-1])
        if mujoco.mj_stateSize(m, STATE_SPEC) != self.state_size:
            raise ValueError(f"{task.name}: MuJoCo's state has parts NativeState does not hold")
        default = self.default_params
        self._param_shapes = {
            f: np.shape(getattr(default, f)) for f in default.__dataclass_fields__
        }
        # One MjData per worker and one model cache, used under a lock: XLA may call back from
        # several threads (one per device), and its callback threads come and go, so MuJoCo
        # objects must not live in thread-locals (their teardown outside Python crashes).
        self._lock = threading.Lock()
        self._cache: dict[bytes, mujoco.MjModel] = {}
        self._batches: dict[bytes, tuple[list[mujoco.MjModel], SimpleNamespace]] = {}
        # mj_step releases the GIL: a batch's lanes are split over ``threads`` workers, each
        # with its own MjData (while the callback runs, XLA's own threads wait for it).
        self.threads = max(1, threads or min(MAX_THREADS, len(os.sched_getaffinity(0))))
        self._datas = [mujoco.MjData(m) for _ in range(self.threads)]
        self._pool = ThreadPoolExecutor(self.threads - 1) if self.threads > 1 else None
        # The reward's info keys and the data fields beyond qpos/qvel the hooks read (copied out
        # of MjData after each lane's step), from one call of the hooks on the model's state.
        view = _FieldsRead(_read=set(), **vars(self._hook_view(self._datas[0], 1)))
        lanes = self._lane_params(self.flat_params(default)[None])
        task._obs(view, np)
        _, _, info = task._reward(view, view, np.zeros((1, m.nu)), lanes, np)
        self._info_keys = tuple(info)
        self._extra_fields = tuple(f for f in HOOK_FIELDS[2:] if f in view._read)

    @property
    def default_params(self) -> MjxParams:
        return self.task.default_params

    def __repr__(self) -> str:
        return f"NativeEnv({self.task!r})"

    # Params --------------------------------------------------------------------------------

    def flat_params(self, params: MjxParams) -> jax.Array:
        """Every field of the params, float32, raveled in field order into one row (P,)."""
        leaves = [
            jnp.ravel(jnp.asarray(getattr(params, f), jnp.float32)) for f in self._param_shapes
        ]
        return jnp.concatenate(leaves)

    def _lane_params(self, rows: np.ndarray) -> SimpleNamespace:
        """Rows [n, P] back into fields [n, *shape] (for the task hooks)."""
        out, offset = {}, 0
        for field, shape in self._param_shapes.items():
            size = int(np.prod(shape))
            out[field] = rows[:, offset : offset + size].reshape(len(rows), *shape)
            offset += size
        return SimpleNamespace(**out)

    def host_model(self, row: np.ndarray) -> mujoco.MjModel:
        """The ``MjModel`` of one task (its ``flat_params`` row), cached; call under the lock.

        Each model field is written in; elements equal to the float32 rounding of the model's
        own value keep the float64 value (module docstring).
        """
        key = row.tobytes()
        model = self._cache.get(key)
        if model is None:
            if len(self._cache) >= MAX_CACHED_MODELS:
                self._cache.clear()
            model = copy.copy(self.model)
            fields = self._lane_params(row[None])
            for field in MODEL_FIELDS:
                own = getattr(self.model, field)
                given = getattr(fields, field)[0]
                same = given == own.astype(np.float32)
                getattr(model, field)[:] = np.where(same, own, given.astype(np.float64))
            self._cache[key] = model
        return model

    def _batch(self, rows: np.ndarray) -> tuple[list[mujoco.MjModel], SimpleNamespace]:
        """The models and hook params of a batch's rows [n, P] float32, cached by the whole
        batch (a collection steps the same tasks every step); call under the lock."""
        key = rows.tobytes()
        batch = self._batches.get(key)
        if batch is None:
            if len(self._batches) >= MAX_CACHED_MODELS:
                self._batches.clear()
            rows = np.array(rows, np.float32)
            batch = [self.host_model(row) for row in rows], self._lane_params(rows)
            self._batches[key] = batch
        return batch

    # Host side ----------------------------------------------------------------------------

    def _load(self, data: mujoco.MjData, state: np.ndarray) -> None:
        """One float64 state vector into ``data``."""
        mujoco.mj_setState(self.model, data, state, STATE_SPEC)

    def _save(self, data: mujoco.MjData, state: np.ndarray) -> None:
        mujoco.mj_getState(self.model, data, state, STATE_SPEC)

    @staticmethod
    def _hook_view(data: mujoco.MjData, n: int) -> SimpleNamespace:
        """Empty float64 arrays [n, ...] for the data fields the task hooks read."""
        return SimpleNamespace(**{k: np.zeros((n, *getattr(data, k).shape)) for k in HOOK_FIELDS})

    def host_step(self, packed: np.ndarray) -> np.ndarray:
        """Every lane's step, batch axes leading: uint32 ``[words, ctrl bits, params bits]`` ->
        ``[new words, float32 bits of obs, reward, terminated, info...]``; the callback behind
        ``step``."""
        batch, state, rest = self.unpacked(packed)
        ctrl, rows = rest[:, : self.action_dim], rest[:, self.action_dim :]
        return self.packed_out(batch, *self.host_step64(state, ctrl, rows))

    def unpacked(self, packed: np.ndarray) -> tuple[tuple, np.ndarray, np.ndarray]:
        """``_packed``'s host side: (batch shape, float64 states [n, state_size], the float32
        values after the words [n, k])."""
        packed = np.asarray(packed)
        flat = packed.reshape(-1, packed.shape[-1])
        words = 2 * self.state_size
        state = from_words(flat[:, :words].reshape(len(flat), self.state_size, 2))
        rest = np.ascontiguousarray(flat[:, words:]).view(np.float32)
        return packed.shape[:-1], state, rest

    @staticmethod
    def packed_out(batch: tuple, new: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``unpacked``'s inverse for the step's output: float64 states [n, state_size] and
        values [n, k] -> uint32 ``[new words, float32 bits of values]`` with batch axes leading."""
        words = to_words(new).reshape(len(new), -1)
        out = np.concatenate([words, values.astype(np.float32).view(np.uint32)], 1)
        return out.reshape(*batch, -1)

    def host_step64(
        self, state: np.ndarray, ctrl: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``host_step`` in float64 for lanes [n]: states [n, state_size] (``NativeState``'s
        vector), ctrl [n, nu] in env units, params rows [n, P] -> (new states, values [n, V])."""
        n = len(state)
        task = self.task
        loaded = np.concatenate([state, np.asarray(ctrl, np.float64)], axis=1)  # STEP_SPEC
        ctrl = loaded[:, self.state_size :]
        substep = getattr(task, "_native_before_substep", None)
        extra = {f: np.empty((n, *getattr(self._datas[0], f).shape)) for f in self._extra_fields}
        new = np.empty_like(loaded[:, : self.state_size])

        def run(worker: int, lanes: range) -> None:  # rows of new/extra are the lanes' own
            data = self._datas[worker]
            for i in lanes:
                model = models[i]
                mujoco.mj_setState(model, data, loaded[i], STEP_SPEC)
                if substep is None:
                    mujoco.mj_step(model, data, nstep=task.frame_skip)
                else:
                    for _ in range(task.frame_skip):
                        substep(model, data)
                        mujoco.mj_step(model, data)
                mujoco.mj_getState(model, data, new[i], STATE_SPEC)
                for name, out in extra.items():
                    out[i] = getattr(data, name)

        with self._lock:
            models, lanes = self._batch(rows)
            # A before-substep hook edits the (shared, cached) model: one thread then.
            workers = 1 if substep is not None else min(len(self._datas), n // LANES_PER_WORKER)
            if workers <= 1:
                run(0, range(n))
            else:  # the calling thread steps the first chunk, the pool the others
                chunks = [range(c[0], c[-1] + 1) for c in np.array_split(np.arange(n), workers)]
                others = [self._pool.submit(run, w, c) for w, c in enumerate(chunks) if w]
                run(0, chunks[0])
                for done in others:
                    done.result()
        sl = self._slices
        before = SimpleNamespace(qpos=state[:, sl["qpos"]])
        after = SimpleNamespace(qpos=new[:, sl["qpos"]], qvel=new[:, sl["qvel"]], **extra)
        obs = task._obs(after, np)
        reward, terminated, info = task._reward(before, after, ctrl, lanes, np)
        terms = [reward, terminated, *(info[k] for k in self._info_keys)]
        return new, np.concatenate([obs, np.stack(terms, axis=-1)], axis=-1)

    def host_forward_obs(self, packed: np.ndarray) -> np.ndarray:
        """Every lane's observation after ``mj_forward`` (for tasks whose first observation
        needs derived quantities, as gymnasium's ``set_state`` computes them): uint32 ``[words,
        params bits]`` -> float32 obs."""
        batch, state, rows = self.unpacked(packed)
        n = len(state)
        with self._lock:
            models, _ = self._batch(rows)
            data = self._datas[0]
            fields = self._hook_view(data, n)
            for i in range(n):
                self._load(data, state[i])
                mujoco.mj_forward(models[i], data)
                for name in HOOK_FIELDS:
                    getattr(fields, name)[i] = getattr(data, name)
        obs = self.task._obs(fields, np)
        return np.asarray(obs, np.float32).reshape(*batch, self.obs_dim)

    # JAX side ------------------------------------------------------------------------------

    def _packed(self, physics: jax.Array, *floats: jax.Array) -> jax.Array:
        """The state's words and float32 arrays' bits as one flat uint32 array."""
        bits = [
            jax.lax.bitcast_convert_type(jnp.asarray(x, jnp.float32), jnp.uint32) for x in floats
        ]
        return jnp.concatenate([physics.reshape(-1), *bits])

    def reset(self, key: PRNGKey, params: MjxParams) -> tuple[jax.Array, NativeState]:
        """The MJX env's reset distribution (``_init_qpos_qvel``), zero warm start and time.

        The observation is computed in JAX from ``(qpos, qvel)`` (exact: they are float32
        draws), or on the host after ``mj_forward`` for tasks that need derived quantities
        (``forward_on_reset``), so the auto-reset of every collection step costs no host call
        for the locomotion tasks.
        """
        qpos, qvel = self.task._init_qpos_qvel(key)
        m = self.model
        zeros = jnp.zeros((m.na + m.nv,), jnp.float32)
        physics = float64_words(jnp.concatenate([jnp.zeros((1,)), qpos, qvel, zeros]))
        state = NativeState(physics=physics, t=jnp.zeros((), jnp.int32))
        if self.task.forward_on_reset:
            obs = jax.pure_callback(
                self.host_forward_obs,
                jax.ShapeDtypeStruct((self.obs_dim,), jnp.float32),
                self._packed(physics, self.flat_params(params)),
                vmap_method="broadcast_all",
            )
        else:
            obs = self.task._obs(SimpleNamespace(qpos=qpos, qvel=qvel)).astype(jnp.float32)
        return obs, state

    def step(
        self, key: PRNGKey, state: NativeState, action: jax.Array, params: MjxParams
    ) -> StepOutput:
        """``frame_skip`` ``mj_step`` calls on the host with the scaled action as ``ctrl``
        (gymnasium's ``do_simulation``); obs, reward and termination from the task's hooks in
        float64, returned as float32."""
        del key
        words = 2 * self.state_size
        n_values = self.obs_dim + 2 + len(self._info_keys)
        out = jax.pure_callback(
            self.host_step,
            jax.ShapeDtypeStruct((words + n_values,), jnp.uint32),
            self._packed(state.physics, self.scale_action(action), self.flat_params(params)),
            vmap_method="broadcast_all",
        )
        physics = out[:words].reshape(state.physics.shape)
        values = jax.lax.bitcast_convert_type(out[words:], jnp.float32)
        obs, reward = values[: self.obs_dim], values[self.obs_dim]
        terminated = values[self.obs_dim + 1] > 0.5
        info = dict(zip(self._info_keys, values[self.obs_dim + 2 :], strict=True))
        t = state.t + 1
        new = NativeState(physics=physics, t=t)
        return obs, new, reward, terminated, time_limit(t, self.horizon, terminated), info
