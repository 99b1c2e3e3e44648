"""Env steps per second of the MuJoCo envs under a jitted ``lax.scan`` of random actions, per
physics backend (``--physics mjx,native``: MJX in the program, or MuJoCo's C engine through one
host callback per step, ``envs/native.py``).

For each env and batch size, one jitted function runs ``--steps`` steps of ``batch`` vmapped envs
(batch 1: a single env, not vmapped) with uniform random actions in [-1, 1], resetting each env
when it terminates or truncates (``env.reset`` is evaluated every step and selected with
``jnp.where``, so its cost is included). On CPU, ``vmap`` itself costs MJX several times its
single-env speed at batch 1 (batched solver loops and factorizations), hence the unbatched path.
Compile time (``jit(...).lower(...).compile()``) is measured separately from run time; the run
is timed after one warm-up call, best of ``--repeats``. Prints a markdown table::

    python benchmarks/env_throughput.py --envs inverted_double_pendulum,hopper --batch 1,16,256
    python benchmarks/env_throughput.py --physics mjx,native --batch 1,5,16,40 \
        --envs hopper,walker2d,halfcheetah,inverted_double_pendulum --json results/throughput.json

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from espl_jax import envs
from espl_jax.cli import cache_turned_off

# JAX_COMPILATION_CACHE_DIR=off means no cache here as on the command line (JAX alone would cache
# into a folder named "off" and hide compile times).
cache_turned_off()

DEFAULT_ENVS = (
    "inverted_double_pendulum",
    "inverted_pendulum_swingup",
    "hopper",
    "walker2d",
    "halfcheetah",
)


def make_run(env, steps: int, per_env_params: bool, batched: bool = True):
    """Builds ``run(key, params, obs, state) -> (obs, state, total_reward, n_done)``.

    Args:
        env: an ``envs`` environment.
        steps: scan length.
        per_env_params: if true, ``params`` carries a leading batch axis (one physics per env,
            as in meta-RL); otherwise all envs share one params.
        batched: vmap over envs (leaves of ``obs``/``state`` have a leading (B,) axis); if false,
            a single env.

    Returns:
        The (unjitted) run function.
    """

    def step_one(key, params, obs, state):
        key_action, key_step, key_reset = jax.random.split(key, 3)
        action = jax.random.uniform(key_action, (env.action_dim,), minval=-1.0, maxval=1.0)
        obs, state, reward, terminated, truncated, _ = env.step(key_step, state, action, params)
        done = jnp.logical_or(terminated, truncated)
        obs_reset, state_reset = env.reset(key_reset, params)
        obs, state = jax.tree.map(
            lambda r, s: jnp.where(done, r, s), (obs_reset, state_reset), (obs, state)
        )
        return obs, state, reward, done

    vmapped = jax.vmap(step_one, in_axes=(0, 0 if per_env_params else None, 0, 0))

    def run(key, params, obs, state):
        batch = jax.tree.leaves(obs)[0].shape[0] if batched else 1

        def body(carry, key_t):
            obs, state, total, n_done = carry
            if batched:
                obs, state, reward, done = vmapped(
                    jax.random.split(key_t, batch), params, obs, state
                )
            else:
                obs, state, reward, done = step_one(key_t, params, obs, state)
            return (obs, state, total + reward.sum(), n_done + done.sum()), None

        init = (obs, state, jnp.zeros(()), jnp.zeros((), jnp.int32))
        (obs, state, total, n_done), _ = jax.lax.scan(body, init, jax.random.split(key, steps))
        return obs, state, total, n_done

    return run


def benchmark(
    name: str, batch: int, steps: int, repeats: int, per_env_params: bool, physics: str = "mjx"
) -> dict:
    """Compiles and times one (env, batch, physics) configuration.

    Returns:
        dict with ``compile_s``, ``run_s`` (best of ``repeats``), ``steps_per_s`` (env steps, i.e.
        ``batch * steps / run_s``) and ``episodes`` (resets during the timed run).
    """
    env = envs.make(name, physics=physics) if name in envs.MUJOCO else envs.make(name)
    key = jax.random.key(0)
    params = env.default_params
    batched = batch > 1
    if batched:
        if per_env_params:
            params = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), params)
        reset = jax.vmap(env.reset, in_axes=(0, 0 if per_env_params else None))
        obs, state = jax.jit(reset)(jax.random.split(key, batch), params)
    else:
        obs, state = jax.jit(env.reset)(key, params)
    run = make_run(env, steps, per_env_params and batched, batched)
    compile_s, best, out = compile_and_time(run, key, (params, obs, state), repeats)
    return dict(
        compile_s=compile_s,
        run_s=best,
        steps_per_s=batch * steps / best,
        episodes=int(out[3]),
    )


def compile_and_time(run, key: jax.Array, args: tuple, repeats: int) -> tuple[float, float, object]:
    """``(compile_s, best run_s, output)`` of ``jit(run)(key, *args)``.

    Compile is timed apart (``lower(...).compile()``); one warm-up call, then the best of
    ``repeats`` calls, each with a fresh key.
    """
    start = time.perf_counter()
    compiled = jax.jit(run).lower(key, *args).compile()
    compile_s = time.perf_counter() - start
    out = jax.block_until_ready(compiled(key, *args))  # warm-up
    best = float("inf")
    for i in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(compiled(jax.random.key(i + 1), *args))
        best = min(best, time.perf_counter() - start)
    return compile_s, best, out


def _fmt_rate(x: float) -> str:
    return f"{x / 1e3:.1f}k" if x >= 1e3 else f"{x:.0f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default=",".join(DEFAULT_ENVS), help="comma-separated names")
    parser.add_argument("--batch", default="1,16,256", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=1000, help="scan length per call")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls (best is kept)")
    parser.add_argument(
        "--per-env-params",
        action="store_true",
        help="vmap over a batch of params (one mjx.Model per env, as in meta-RL); batch > 1",
    )
    parser.add_argument(
        "--physics", default="mjx", help="comma-separated MuJoCo backends: mjx, native"
    )
    parser.add_argument("--json", help="also write the rows, command and machine to this file")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.envs.split(",") if n.strip()]
    batches = [int(b) for b in args.batch.split(",")]
    backends = [p.strip() for p in args.physics.split(",") if p.strip()]
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, {args.steps} steps per call")
    print()
    print("| env | physics | batch | compile (s) | run (s) | env steps/s | resets |")
    print("|---|---|---:|---:|---:|---:|---:|")
    rows = []
    for name in names:
        for batch in batches:
            for physics in backends:
                r = benchmark(name, batch, args.steps, args.repeats, args.per_env_params, physics)
                rows.append(dict(env=name, physics=physics, batch=batch, **r))
                print(
                    f"| {name} | {physics} | {batch} | {r['compile_s']:.1f} | {r['run_s']:.2f} "
                    f"| {_fmt_rate(r['steps_per_s'])} | {r['episodes']} |",
                    flush=True,
                )
    if args.json:
        write_result(args.json, rows, argv)


def machine() -> dict:
    """Where a benchmark ran: enough to tell two result files' machines apart."""
    return dict(
        platform=platform.platform(),
        processor=platform.processor() or platform.machine(),
        cpus=os.cpu_count(),
        jax=jax.__version__,
        jax_backend=jax.default_backend(),
        devices=[str(d.device_kind) for d in jax.devices()],
    )


def write_result(
    path: str,
    rows: list[dict],
    argv: list[str] | None,
    script: str = "benchmarks/env_throughput.py",
) -> None:
    """The rows as JSON with the command, commit, machine and date that produced them."""
    import sys

    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    record = dict(
        command=f"python {script} " + " ".join(argv or sys.argv[1:]),
        commit=commit or None,
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        machine=machine(),
        # The 1-, 5- and 15-minute load averages when the file was written: on 2 cores anything
        # else running changes the figures.
        load_average=[round(x, 2) for x in os.getloadavg()],
        rows=rows,
    )
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
