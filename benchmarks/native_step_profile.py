"""Where one native MuJoCo batch step's time goes: a copy of ``NativeEnv.host_step`` (one host
worker) with a clock between its parts, inside env_throughput's jitted scan of random actions, 5
lanes, best of 5 scans of 200 steps. "outside" is the rest of the step: XLA's host-callback
mechanics and the env's JAX-side work (action, reset draws, selects). Issue 31's note::

    python benchmarks/native_step_profile.py hopper

Not part of the test suite. Keep it in step with ``envs/native.py``'s ``host_step`` and
``host_step64``.
"""

import sys
import time
from types import SimpleNamespace

import jax
import mujoco
import numpy as np
from env_throughput import make_run

from espl_jax import envs
from espl_jax.envs.native import STATE_SPEC, STEP_SPEC

name = sys.argv[1]
env = envs.make(name, physics="native")
T = {}


def tick(k, t0):
    t1 = time.perf_counter()
    T[k] = T.get(k, 0) + t1 - t0
    return t1


def host_step(packed):
    t = time.perf_counter()
    batch, state, rest = env.unpacked(packed)
    ctrl, rows = rest[:, : env.action_dim], rest[:, env.action_dim :]
    t = tick("in", t)
    n = len(state)
    task = env.task
    loaded = np.concatenate([state, np.asarray(ctrl, np.float64)], axis=1)
    ctrl = loaded[:, env.state_size :]
    extra = {f: np.empty((n, *getattr(env._datas[0], f).shape)) for f in env._extra_fields}
    new = np.empty_like(loaded[:, : env.state_size])
    models, lanes = env._batch(rows)
    t = tick("setup", t)
    data = env._datas[0]
    for i in range(n):
        mujoco.mj_setState(models[i], data, loaded[i], STEP_SPEC)
        t = tick("load", t)
        mujoco.mj_step(models[i], data, nstep=task.frame_skip)
        t = tick("physics", t)
        mujoco.mj_getState(models[i], data, new[i], STATE_SPEC)
        for name, out in extra.items():
            out[i] = getattr(data, name)
        t = tick("save", t)
    sl = env._slices
    before = SimpleNamespace(qpos=state[:, sl["qpos"]])
    after = SimpleNamespace(qpos=new[:, sl["qpos"]], qvel=new[:, sl["qvel"]], **extra)
    obs = task._obs(after, np)
    reward, terminated, info = task._reward(before, after, ctrl, lanes, np)
    terms = [reward, terminated, *(info[k] for k in env._info_keys)]
    values = np.concatenate([obs, np.stack(terms, axis=-1)], axis=-1)
    t = tick("obs_reward", t)
    out = env.packed_out(batch, new, values)
    tick("out", t)
    return out


env.host_step = host_step
batch = 5
key = jax.random.key(0)
params = env.default_params
obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(key, batch), params)
run = jax.jit(make_run(env, 200, False, True))
jax.block_until_ready(run(key, params, obs, state))
best = 1e9
for _ in range(5):
    T.clear()
    t = time.perf_counter()
    jax.block_until_ready(run(key, params, obs, state))
    dt = time.perf_counter() - t
    if dt < best:
        best = dt
        bt = dict(T)
print(
    name,
    f"total {best / 200 * 1e6:.0f} us/step",
    {k: round(v / 200 * 1e6) for k, v in bt.items()},
    "outside",
    round((best - sum(bt.values())) / 200 * 1e6),
)
