"""How fast the one rollout path steps a Box2D env (gymnasium on the host, ``envs/box2d.py``).

The Box2D env is a functional ``Environment`` whose step is one ``jax.pure_callback`` per env step
for the whole seed batch, inside the compiled ``lax.scan`` of ``SingleTask.collect``. For each
``--seeds`` count, with the shipped config of ``--env`` (only ``seeds`` changed), this times (after
one warm-up call, best and median of ``--repeats``) one iteration's collection
(``steps_per_iteration`` env steps per seed), the part of it spent inside the gymnasium env
class's own ``step``/``reset`` (which depends on the episodes played: a LunarLander step costs
45-200 us with the number of engine particles alive) and the rest, the path's own overhead per env
step; with ``--iteration``, also whole iterations (collection and ``updates_per_iteration`` SAC
updates). The load average is recorded beside each row, since other jobs may share the cores::

    python benchmarks/box2d_paths.py --env lunarlander --seeds 1,2,3 --iteration 3

Until commit bc50bc1 this script also timed the host driver that the Box2D envs had before
(``espl_jax/host.py``: a Python loop over a gymnasium ``SyncVectorEnv`` calling the jitted policy
once per step; ``host_meta.py`` for task families), interleaved with this path:
``results/box2d_paths_lunarlander.json`` and ``results/box2d_paths_lunarlander_params.json`` hold
those measurements (check out that commit to rerun them).

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np
from env_throughput import write_result

from espl_jax import config as config_lib
from espl_jax.learner import Trainer


class EnvClock:
    """Seconds spent inside the gymnasium env class's own ``step`` and ``reset`` (patched on the
    class): the rest of a collection is the path's overhead."""

    def __init__(self, env_class):
        self.seconds = 0.0
        for name in ("step", "reset"):
            original = getattr(env_class, name)

            def timed(obj, *args, _original=original, **kwargs):
                started = time.perf_counter()
                try:
                    return _original(obj, *args, **kwargs)
                finally:
                    self.seconds += time.perf_counter() - started

            setattr(env_class, name, timed)


CLOCKS: dict[str, EnvClock] = {}


def _timed(fn) -> float:
    started = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - started


def measure(env: str, seeds: int, repeats: int, iterations: int) -> dict:
    cfg = config_lib.resolve(env=env, seeds=seeds)
    trainer = Trainer(cfg)
    clock = CLOCKS.setdefault(env, EnvClock(type(trainer.env.make_env().unwrapped)))

    def one_seed_collect(s):  # an iteration's collection (the update key is dropped)
        return trainer.task_set.collect(trainer.actor, s)[:2]

    collect_fn = trainer.seed_axis.over_seeds(one_seed_collect)
    holder = {"state": trainer.init_seeds()}

    def collect():  # the episodes go on across calls
        holder["state"], metrics = collect_fn(holder["state"])
        return metrics

    first = _timed(collect)
    times, env_times, loads = [], [], []
    for _ in range(repeats):
        loads.append(os.getloadavg()[0])
        clock.seconds = 0.0
        times.append(_timed(collect))
        env_times.append(clock.seconds)
    overhead = np.asarray(times) - np.asarray(env_times)
    steps = cfg.steps_per_iteration * seeds
    row = {
        "env": env,
        "path": "callback",
        "seeds": seeds,
        "env_steps": steps,
        "collect_s": min(times),
        "collect_median_s": float(np.median(times)),
        "collect_first_s": first,
        "env_steps_per_s": steps / min(times),
        "env_steps_per_s_median": steps / float(np.median(times)),
        "env_class_median_s": float(np.median(env_times)),
        "overhead_us_per_step": float(np.median(overhead)) / cfg.steps_per_iteration * 1e6,
        "iteration_s": None,
        "iteration_median_s": None,
        "updates_per_iteration": cfg.updates_per_iteration,
        "load_1min": loads,
    }
    if iterations:
        chunk = trainer.compiled_chunk(1)

        def iteration():
            holder["state"], metrics = chunk(holder["state"])
            return metrics

        row["iteration_first_s"] = _timed(iteration)
        its = []
        for _ in range(iterations):
            loads.append(os.getloadavg()[0])
            its.append(_timed(iteration))
        row["iteration_s"], row["iteration_median_s"] = min(its), float(np.median(its))
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="lunarlander", help="lunarlander or bipedalwalker")
    parser.add_argument("--seeds", default="1,2,3", help="comma-separated seed counts")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--iteration", type=int, default=0, help="also time whole iterations (this many repeats)"
    )
    parser.add_argument("--json", help="also write the rows, command and machine here")
    args = parser.parse_args(argv)
    rows = [measure(args.env, int(s), args.repeats, args.iteration) for s in args.seeds.split(",")]
    print(f"\n{args.env}: best / median of {args.repeats}\n")
    print(
        "| seeds | collection (s) | env steps/s | in the env class (s) | overhead per step (us) "
        "| iteration (s) | load (1 min) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        it = "-"
        if r["iteration_s"] is not None:
            it = f"{r['iteration_s']:.2f} / {r['iteration_median_s']:.2f}"
        load = ", ".join(f"{x:.1f}" for x in r["load_1min"])
        print(
            f"| {r['seeds']} | {r['collect_s']:.2f} / {r['collect_median_s']:.2f} "
            f"| {r['env_steps_per_s']:.0f} / {r['env_steps_per_s_median']:.0f} "
            f"| {r['env_class_median_s']:.2f} | {r['overhead_us_per_step']:.0f} | {it} | {load} |"
        )
    if args.json:
        write_result(args.json, rows, argv, script="benchmarks/box2d_paths.py")


if __name__ == "__main__":
    main()
