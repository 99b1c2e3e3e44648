"""Where an iteration's time goes, per actor kind and physics backend: collection vs updates.

For an env or task family and each ``--actors`` kind and ``--physics`` backend (MuJoCo tasks),
with the shipped config, this times (after one warm-up call, best of ``--repeats``) the jitted,
seed-vmapped pieces of one iteration:

- ``collect``: one iteration's collection (``TaskSet.collect``; meta-RL: PEARL's prior and
  posterior phases; single task: ``steps_per_iteration`` steps);
- ``updates``: ``--updates`` SAC steps (``Iteration.learn`` without collection), from a buffer
  filled by one collection, reported per update (the shipped ``updates_per_iteration`` gives the
  iteration's update time);
- ``adapt``: meta-RL only, the protocol on the test tasks (``Trainer.compiled_adapt``), once.

Compile times are printed beside (the first call minus a timed one). Prints a markdown table::

    python benchmarks/meta_cost.py --env invdoublepend_params --actors symbolic,pearl,hyper
    python benchmarks/meta_cost.py --env hopper_params --actors symbolic --physics mjx,native
    python benchmarks/meta_cost.py --env hopper --actors symbolic --physics mjx,native \
        --json results/iteration_cost_hopper.json
    python benchmarks/meta_cost.py --env hopper_params --actors hyper --config small_trunk.yaml

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import time

import jax
from env_throughput import write_result

from espl_jax import config as config_lib
from espl_jax import envs
from espl_jax.learner import Trainer


def _timed(fn, *args, repeats: int):
    """(first call's seconds, best later call's seconds, last result)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return first, best, out


def measure(
    env: str,
    actor: str,
    updates: int,
    repeats: int,
    physics: str = "auto",
    config_file: str | None = None,
) -> dict:
    shipped = config_lib.resolve(env=env, config_file=config_file, actor=actor, physics=physics)
    overrides = dict(env=env, actor=actor, physics=physics, updates_per_iteration=updates)
    if envs.is_family(env):
        # A short initial collection: it only has to put data in the buffers (whose size, and
        # so the cost of sampling them, does not depend on how full they are).
        overrides["initial_steps"] = 200
    trainer = Trainer(config_lib.resolve(config_file=config_file, **overrides))
    state = trainer.init_seeds()
    state = jax.block_until_ready(trainer.compiled_warmup()(state))
    key = jax.random.PRNGKey(1)
    keys = key[None]

    def collect_one(s, k):  # an iteration's collection, on the task set of the run
        return trainer.task_set.collect(trainer.actor, s.replace(key=k))[0]

    collect = trainer.seed_axis.over_seeds(collect_one)
    c_first, c_best, state = _timed(collect, state, keys, repeats=repeats)

    def learn(s, k):
        return trainer.iteration.learn(s, {}, k)[0]

    learn = trainer.seed_axis.over_seeds(learn)
    u_first, u_best, _ = _timed(learn, state, keys, repeats=repeats)

    a_first = a_best = float("nan")
    if trainer.meta:
        test_params = trainer.tasks[1]
        a_first, a_best, _ = _timed(trainer.compiled_adapt, state, test_params, keys, repeats=1)
    return {
        "env": env,
        "actor": actor,
        "config": config_file,
        "physics": trainer.physics,
        "collect_s": c_best,
        "collect_compile_s": c_first - c_best,
        "update_ms": 1000 * u_best / updates,
        "updates_per_iteration": shipped.updates_per_iteration,
        "updates_compile_s": u_first - u_best,
        "adapt_s": a_best,
        "adapt_compile_s": a_first - a_best,
        "steps_per_iteration": trainer.task_set.steps_per_iteration,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--env", default="cartpole_fl_ood", help="an env or family, or several, comma-separated"
    )
    parser.add_argument("--actors", default="symbolic,pearl,hyper")
    parser.add_argument("--physics", default="auto", help="comma-separated: auto, mjx, native")
    parser.add_argument("--updates", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--config", help="a YAML file over configs/ENV.yaml (as train's --config), e.g. a variant"
    )
    parser.add_argument("--json", help="also write the rows, command and machine here")
    args = parser.parse_args(argv)
    rows = []
    for env in args.env.split(","):
        for a in args.actors.split(","):
            for p in args.physics.split(","):
                rows.append(measure(env, a, args.updates, args.repeats, p, args.config))
                print(rows[-1], flush=True)
    print(f"\n{args.updates} updates per timed call, best of {args.repeats}\n")
    print(
        "| env | actor | physics | collection / iteration (s) | updates / iteration (s) "
        "| protocol on the test tasks (s) | compile: collect, updates, protocol (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        updates_s = r["update_ms"] * r["updates_per_iteration"] / 1000
        print(
            f"| {r['env']} | {r['actor']} | {r['physics'] or '-'} | {r['collect_s']:.2f} "
            f"({r['steps_per_iteration']} env steps) | {updates_s:.2f} "
            f"({r['updates_per_iteration']} × {r['update_ms']:.1f} ms) | {r['adapt_s']:.1f} "
            f"| {r['collect_compile_s']:.0f}, {r['updates_compile_s']:.0f}, "
            f"{r['adapt_compile_s']:.0f} |"
        )
    if args.json:
        write_result(args.json, rows, argv, script="benchmarks/meta_cost.py")


if __name__ == "__main__":
    main()
