"""Which host loop steps a batch of MuJoCo envs fastest on this CPU (the choice in envs/native.py).

Each candidate steps ``batch`` copies of a gymnasium model (one ``MjModel`` per env, as a meta-RL
batch of tasks has) ``frame_skip`` substeps per env step with random controls, restoring each
env's state from a float64 state vector and saving it back every env step, as the native backend
must (its state lives in the JAX state):

- ``loop``: ``mj_setState``, ``mj_step(model, data, nstep=frame_skip)``, ``mj_getState`` per env
  (one ``MjData``, Python loop; what ``envs/native.py`` does, with its own state layout);
- ``rollout-N``: ``mujoco.rollout.Rollout(nthread=N).rollout`` over the batch, one env step per
  call (its thread pool steps the envs in parallel);
- ``mjbatch-N``: ``mjbatch.Batch`` with N threads, per-sim models through ``expand``, one env step
  per ``step(nstep=frame_skip)`` call (optional package; skipped if not installed).

Prints a markdown table and, with ``--json``, writes the rows with the command and machine::

    python benchmarks/native_backends.py --envs hopper,walker2d --batch 1,5,16,40 \\
        --json results/native_backends.json
"""

from __future__ import annotations

import argparse
import copy
import time

import mujoco
import numpy as np
from env_throughput import write_result
from mujoco import rollout

from espl_jax.envs.mjx import MJX_ENVS

SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS | mujoco.mjtState.mjSTATE_WARMSTART


def _models(name: str, batch: int):
    task = MJX_ENVS[name]()
    return task, [copy.copy(task.model) for _ in range(batch)]


def loop(name: str, batch: int, steps: int, rng) -> float:
    task, models = _models(name, batch)
    data = mujoco.MjData(models[0])
    size = mujoco.mj_stateSize(models[0], SPEC)
    states = np.zeros((batch, size))
    for i in range(batch):
        mujoco.mj_getState(models[i], data, states[i], SPEC)
    start = time.perf_counter()
    for _ in range(steps):
        ctrl = rng.uniform(-1, 1, (batch, models[0].nu))
        for i, model in enumerate(models):
            mujoco.mj_setState(model, data, states[i], SPEC)
            data.ctrl[:] = ctrl[i]
            mujoco.mj_step(model, data, nstep=task.frame_skip)
            mujoco.mj_getState(model, data, states[i], SPEC)
    return batch * steps / (time.perf_counter() - start)


def pooled_rollout(name: str, batch: int, steps: int, rng, threads: int) -> float:
    task, models = _models(name, batch)
    datas = [mujoco.MjData(models[0]) for _ in range(threads)]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    states = np.zeros((batch, mujoco.mj_stateSize(models[0], spec)))
    for i in range(batch):
        mujoco.mj_getState(models[i], datas[0], states[i], spec)
    with rollout.Rollout(nthread=threads) as pool:
        start = time.perf_counter()
        for _ in range(steps):
            ctrl = rng.uniform(-1, 1, (batch, 1, models[0].nu))
            ctrl = np.repeat(ctrl, task.frame_skip, axis=1)
            out, _ = pool.rollout(models, datas, states, ctrl)
            states = out[:, -1]
    return batch * steps / (time.perf_counter() - start)


def mjbatch_steps(name: str, batch: int, steps: int, rng, threads: int) -> float:
    import mjbatch

    task = MJX_ENVS[name]()
    sims = mjbatch.Batch(task.model, batch, num_threads=threads)
    for field in ("body_mass", "body_inertia", "dof_damping", "geom_friction"):
        sims.expand(field)  # one model per sim, as for a batch of tasks
    ctrl = sims.bind("ctrl")
    state = sims.bind("state")
    saved = np.array(state)
    start = time.perf_counter()
    for _ in range(steps):
        state[:] = saved
        ctrl[:] = rng.uniform(-1, 1, ctrl.shape)
        sims.step(nstep=task.frame_skip)
        saved = np.array(state)
    return batch * steps / (time.perf_counter() - start)


def candidates(threads: list[int]):
    out = {"loop": loop}
    for n in threads:
        out[f"rollout-{n}"] = lambda *a, n=n: pooled_rollout(*a, threads=n)
    try:
        import mjbatch  # noqa: F401

        for n in threads:
            out[f"mjbatch-{n}"] = lambda *a, n=n: mjbatch_steps(*a, threads=n)
    except ImportError:
        pass
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default="hopper,walker2d")
    parser.add_argument("--batch", default="1,5,16,40")
    parser.add_argument("--steps", type=int, default=400, help="env steps per measurement")
    parser.add_argument("--threads", default="1,2", help="thread counts for the pools")
    parser.add_argument("--json", help="also write the rows, command and machine here")
    args = parser.parse_args(argv)
    threads = [int(t) for t in args.threads.split(",")]
    rows = []
    print("| env | batch | candidate | env steps/s |")
    print("|---|---:|---|---:|")
    for name in args.envs.split(","):
        for batch in (int(b) for b in args.batch.split(",")):
            for label, fn in candidates(threads).items():
                rate = fn(name, batch, args.steps, np.random.default_rng(0))
                rows.append(dict(env=name, batch=batch, candidate=label, steps_per_s=rate))
                print(f"| {name} | {batch} | {label} | {rate:.0f} |", flush=True)
    if args.json:
        write_result(args.json, rows, argv, script="benchmarks/native_backends.py")


if __name__ == "__main__":
    main()
