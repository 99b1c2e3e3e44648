"""Where one native MuJoCo batch step's time goes: a copy of ``NativeEnv.host_step`` (one host
worker) with a clock between its parts, inside env_throughput's jitted scan of random actions, 5
lanes, best of 5 scans of 200 steps. "outside" is the rest of the step: XLA's host-callback
mechanics and the env's JAX-side work (action, reset draws, selects). Issue 31's note::

    python benchmarks/native_step_profile.py hopper

Not part of the test suite. Keep it in step with ``envs/native.py``'s ``host_step64``.
"""

import sys
import time
from types import SimpleNamespace

import jax
import mujoco
import numpy as np
from env_throughput import make_run

from espl_jax import envs
from espl_jax.envs.native import HOOK_FIELDS, from_words, to_words

name = sys.argv[1]
env = envs.make(name, physics="native")
T = {}


def tick(k, t0):
    t1 = time.perf_counter()
    T[k] = T.get(k, 0) + t1 - t0
    return t1


def host_step(words, ctrl, rows):
    t = time.perf_counter()
    words, ctrl, rows = np.asarray(words), np.asarray(ctrl), np.asarray(rows)
    batch = ctrl.shape[:-1]
    state = from_words(words).reshape(-1, env.state_size)
    ctrl = np.asarray(ctrl.reshape(len(state), -1), np.float64)
    rows = rows.reshape(len(state), -1)
    t = tick("in", t)
    n = len(state)
    task = env.task
    after = env._hook_view(env._datas[0], n)
    new = np.empty_like(state)
    models = [env.host_model(row) for row in rows]
    t = tick("setup", t)
    data = env._datas[0]
    for i in range(n):
        env._load(data, state[i])
        data.ctrl[:] = ctrl[i]
        t = tick("load", t)
        mujoco.mj_step(models[i], data, nstep=task.frame_skip)
        t = tick("physics", t)
        env._save(data, new[i])
        for nm in HOOK_FIELDS:
            getattr(after, nm)[i] = getattr(data, nm)
        t = tick("save", t)
    before = SimpleNamespace(qpos=state[:, env._slices["qpos"]])
    lanes = env._lane_params(rows)
    t = tick("lanes", t)
    obs = task._obs(after, np)
    reward, terminated, info = task._reward(before, after, ctrl, lanes, np)
    terms = [reward, terminated, *(info[k] for k in env._info_keys)]
    values = np.concatenate([obs, np.stack(terms, axis=-1)], axis=-1)
    t = tick("obs_reward", t)
    out = to_words(new).reshape(words.shape), values.astype(np.float32).reshape(*batch, -1)
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
