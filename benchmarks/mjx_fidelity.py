"""MJX speed against fidelity: env steps/s and deviation from CPU MuJoCo under solver settings.

    python benchmarks/mjx_fidelity.py                                  # all envs and settings
    python benchmarks/mjx_fidelity.py --envs hopper --settings env,4:4 --batch 1 --steps 50

For each MJX env (``hopper``, ``walker2d``, ``inverted_double_pendulum``; ``envs/mjx.py``) and each
solver setting ``ITERATIONS:LS_ITERATIONS`` (``env`` = the model's own, i.e. gymnasium's XML:
Newton, 100 iterations, 50 line-search iterations), the env's host ``MjModel`` is copied with
``opt.iterations`` / ``opt.ls_iterations`` changed (solver, tolerance, integrator and everything
else unchanged) and put on the device with ``mjx.put_model``; the env's own ``step`` then runs
on it. Two measurements:

* **speed**: env steps/s of ``benchmarks/env_throughput.py``'s harness (one jitted ``lax.scan``
  of ``--steps`` steps, uniform random actions, reset when done; batch 1 unbatched, other
  batches vmapped; compile apart, one warm-up, best of ``--repeats``).
* **fidelity**: the same ``--steps`` random actions (scaled to the actuators' range, as
  ``env.step`` does) from the same initial state (the env's reset at key 0), stepped by MJX
  (float32) and by CPU MuJoCo (``mujoco.mj_step``, float64, ``frame_skip`` substeps per env
  step; no reset, termination ignored). Reference: CPU MuJoCo with the env's own settings (what
  gymnasium simulates), and, in the JSON, also CPU MuJoCo with the same reduced settings.
  *free*: max over steps and coordinates of |qpos_MJX - qpos_CPU| and |qvel_MJX - qvel_CPU|
  when both run freely (chaotic systems such as a falling hopper diverge whatever the solver,
  so read this together with the next); *re-synced*: at every step MJX starts from the CPU
  reference's state (qpos, qvel, qacc_warmstart) and takes one env step; the max over steps of
  the one-step error.

Brax's MJX envs set fewer iterations: ``ant.py`` and ``humanoid.py`` use Newton with
``opt.iterations 1``, ``opt.ls_iterations 4``; brax's ``hopper.xml`` / ``walker2d.xml`` set
``iterations="4"`` (line search left at MuJoCo's default 50). The default ``--settings`` cover
those and 6:6. ``--json PATH`` writes the rows. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from env_throughput import compile_and_time, make_run  # same directory: run as a script
from mujoco import mjx

from espl_jax import envs

DEFAULT_ENVS = ("hopper", "walker2d", "inverted_double_pendulum")
DEFAULT_SETTINGS = "env,6:6,4:50,4:4,1:4"


def parse_settings(text: str) -> list[tuple[int, int] | None]:
    out: list[tuple[int, int] | None] = []
    for item in text.split(","):
        item = item.strip()
        if item == "env":
            out.append(None)
        else:
            it, ls = item.split(":")
            out.append((int(it), int(ls)))
    return out


def with_solver(model: mujoco.MjModel, setting: tuple[int, int] | None) -> mujoco.MjModel:
    m = copy.deepcopy(model)
    if setting is not None:
        m.opt.iterations, m.opt.ls_iterations = setting
    return m


def env_with_model(name: str, model: mujoco.MjModel):
    """A fresh env whose ``step`` runs on ``model`` (a copy of its own with other solver opts)."""
    env = envs.make(name)
    env._mx = mjx.put_model(model)
    return env


def speed(env, batch: int, steps: int, repeats: int) -> dict[str, float]:
    key = jax.random.key(0)
    params = env.default_params
    batched = batch > 1
    if batched:
        reset = jax.vmap(env.reset, in_axes=(0, None))
        obs, state = jax.jit(reset)(jax.random.split(key, batch), params)
    else:
        obs, state = jax.jit(env.reset)(key, params)
    run = make_run(env, steps, False, batched)
    compile_s, best, _ = compile_and_time(run, key, (params, obs, state), repeats)
    return dict(compile_s=compile_s, steps_per_s=batch * steps / best)


def cpu_trajectory(model: mujoco.MjModel, frame_skip: int, qpos0, qvel0, ctrls) -> dict:
    """qpos/qvel/qacc_warmstart [T+1, ...] of CPU MuJoCo from (qpos0, qvel0) under ``ctrls``."""
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos0, qvel0
    mujoco.mj_forward(model, data)
    qpos, qvel, warm = [data.qpos.copy()], [data.qvel.copy()], [data.qacc_warmstart.copy()]
    for ctrl in ctrls:
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data, nstep=frame_skip)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
        warm.append(data.qacc_warmstart.copy())
    return {"qpos": np.array(qpos), "qvel": np.array(qvel), "warm": np.array(warm)}


def mjx_step_fn(env, mx: mjx.Model):
    def step(data: mjx.Data, ctrl: jax.Array) -> mjx.Data:
        data = data.replace(ctrl=ctrl.astype(data.ctrl.dtype))
        return jax.lax.fori_loop(0, env.frame_skip, lambda _, d: mjx.step(mx, d), data)

    return step


def fidelity(env, model: mujoco.MjModel, reference: dict, same: dict, ctrls: np.ndarray):
    mx = mjx.put_model(model)
    step = mjx_step_fn(env, mx)
    data0 = mjx.make_data(mx)
    dtype = data0.qpos.dtype
    qpos0, qvel0 = reference["qpos"][0], reference["qvel"][0]

    @jax.jit
    def free(ctrls):
        d = data0.replace(qpos=jnp.asarray(qpos0, dtype), qvel=jnp.asarray(qvel0, dtype))

        def body(d, c):
            d = step(d, c)
            return d, (d.qpos, d.qvel)

        return jax.lax.scan(body, d, ctrls)[1]

    @jax.jit
    def resynced(qpos, qvel, warm, ctrls):
        def one(q, v, w, c):
            d = data0.replace(
                qpos=q.astype(dtype), qvel=v.astype(dtype), qacc_warmstart=w.astype(dtype)
            )
            d = step(d, c)
            return d.qpos, d.qvel

        return jax.vmap(one)(qpos, qvel, warm, ctrls)

    c = jnp.asarray(ctrls, jnp.float32)
    fq, fv = (np.asarray(x, np.float64) for x in free(c))
    out: dict[str, Any] = {}
    for label, ref in (("ref", reference), ("same", same)):
        rq, rv = resynced(
            jnp.asarray(ref["qpos"][:-1]), jnp.asarray(ref["qvel"][:-1]),
            jnp.asarray(ref["warm"][:-1]), c,
        )  # fmt: skip
        out[label] = dict(
            free_qpos=float(np.abs(fq - ref["qpos"][1:]).max()),
            free_qvel=float(np.abs(fv - ref["qvel"][1:]).max()),
            resynced_qpos=float(np.abs(np.asarray(rq) - ref["qpos"][1:]).max()),
            resynced_qvel=float(np.abs(np.asarray(rv) - ref["qvel"][1:]).max()),
        )
    return out


def _fmt(x: float) -> str:
    return f"{x:.1e}"


def _load() -> str:
    a = os.getloadavg()
    return f"{a[0]:.2f} {a[1]:.2f} {a[2]:.2f}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--envs", default=",".join(DEFAULT_ENVS), help="comma-separated env names")
    p.add_argument(
        "--settings",
        default=DEFAULT_SETTINGS,
        help="comma-separated ITERATIONS:LS_ITERATIONS, or env (the model's own)",
    )
    p.add_argument("--batch", default="1,16", help="comma-separated batch sizes for steps/s")
    p.add_argument("--steps", type=int, default=100, help="env steps (speed scan and fidelity)")
    p.add_argument("--repeats", type=int, default=1, help="timed calls (best is kept)")
    p.add_argument("--json", default=None, metavar="PATH", help="write the rows as JSON")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.envs.split(",") if n.strip()]
    settings = parse_settings(args.settings)
    batches = [int(b) for b in args.batch.split(",") if b.strip()]

    print(
        f"jax {jax.__version__}, backend {jax.default_backend()}, {args.steps} env steps; "
        f"load average {_load()}\n"
    )
    head = " | ".join(f"steps/s (batch {b})" for b in batches)
    print(
        f"| env | solver | iterations:ls | {head} | free max abs dqpos | free max abs dqvel "
        "| re-synced max abs dqpos | re-synced max abs dqvel |"
    )
    print("|---|---|---|" + "---:|" * (len(batches) + 4))
    rows = []
    for name in names:
        base = envs.make(name).model
        ref_env = envs.make(name)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1.0, 1.0, (args.steps, ref_env.action_dim))
        ctrls = np.asarray(jax.vmap(ref_env.scale_action)(jnp.asarray(actions, jnp.float32)))
        ctrls = ctrls.astype(np.float64)
        _, state0 = jax.jit(ref_env.reset)(jax.random.key(0), ref_env.default_params)
        qpos0 = np.asarray(state0.data.qpos, np.float64)
        qvel0 = np.asarray(state0.data.qvel, np.float64)
        reference = cpu_trajectory(base, ref_env.frame_skip, qpos0, qvel0, ctrls)
        for setting in settings:
            model = with_solver(base, setting)
            env = env_with_model(name, model)
            row: dict[str, Any] = dict(
                env=name,
                solver=mujoco.mjtSolver(model.opt.solver).name,
                iterations=int(model.opt.iterations),
                ls_iterations=int(model.opt.ls_iterations),
                own_settings=setting is None,
                steps=args.steps,
            )
            for b in batches:
                s = speed(env, b, args.steps, args.repeats)
                row[f"steps_per_s_batch{b}"] = s["steps_per_s"]
                row[f"compile_s_batch{b}"] = s["compile_s"]
            same = cpu_trajectory(model, env.frame_skip, qpos0, qvel0, ctrls)
            dev = fidelity(env, model, reference, same, ctrls)
            row["deviation_vs_cpu_own_settings"] = dev["ref"]
            row["deviation_vs_cpu_same_settings"] = dev["same"]
            row["load_average"] = _load()
            rows.append(row)
            d = dev["ref"]
            rates = " | ".join(f"{row[f'steps_per_s_batch{b}']:.0f}" for b in batches)
            label = f"{row['iterations']}:{row['ls_iterations']}"
            if setting is None:
                label += " (env's own)"
            print(
                f"| {name} | {row['solver']} | {label} | {rates} | {_fmt(d['free_qpos'])} "
                f"| {_fmt(d['free_qvel'])} | {_fmt(d['resynced_qpos'])} "
                f"| {_fmt(d['resynced_qvel'])} |",
                flush=True,
            )
    print(
        "\ndeviations: MJX (float32) against CPU MuJoCo (float64) with the env's own solver "
        "settings; against CPU MuJoCo with the same settings in the JSON"
    )
    print(f"load average after: {_load()}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
