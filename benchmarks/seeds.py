"""Wall time of training chunks at several vmapped seed counts, or meta-RL task counts.

Seeds (any JAX env)::

    python benchmarks/seeds.py --env cartpole                      # 1, 2, 4, 8 seeds
    python benchmarks/seeds.py --env cartpole --seeds 1 2 --iterations 2 --updates 50

Tasks (a meta-RL task family; one seed unless a single ``--seeds`` value is given)::

    python benchmarks/seeds.py --env cartpole_fl_ood --tasks 1 5 10 40 --iterations 1

What is timed. For each seed count S, ``Trainer(cfg).init_seeds()`` builds S seeds' states
(sharded over devices as a run shards them, ``SeedAxis.place``) and ``trainer.compiled_chunk(n)``
the chunk of ``n = --iterations`` iterations, jit(vmap) over seeds. The chunk runs once (compile
and run), then ``--repeats`` times; "compile (s)" is the first call less the best later one, and
the best run gives "s / iteration" (collection + ``updates_per_iteration`` SAC updates, all
seeds) and "ms / update (all seeds)" (s / iteration divided by updates_per_iteration, so it
includes the collection's share). "ratio" is s / iteration over that of the first row (one
seed, one task): S vmapped seeds cost S x one seed when the ratio is S, and are free when it is 1.

Tasks mode varies ``meta_batch``, the number of tasks whose buffers every SGD step samples (RL
batch and context per task, PEARL's meta batch; ``espl_jax/task_sets.py``,
``MetaTasks.sample_batch``). It is the task axis of the update (the batch of the critic and
actor losses is meta_batch x batch_size transitions); the tasks collected on per iteration
(``tasks_per_iteration``) and the number of training tasks (the family's ``n_train``) stay the
config's. Meta-RL states need PEARL's initial collection before the first iteration:
``espl_jax.run.warmup`` runs once per row, timed apart ("warm-up (s)", compile included).

``--updates``, ``--steps`` (single task: ``steps_per_iteration``; meta-RL: ``prior_steps`` +
``posterior_steps`` per visited task, split as the config splits them) and ``--initial-steps``
(meta-RL warm-up per training task) shorten a run. ``--json PATH`` writes the rows. Host (Box2D)
envs are not supported (their collection is not a compiled chunk). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import jax

from espl_jax import config, run
from espl_jax.learner import Trainer


def build_config(args: argparse.Namespace, seeds: int, meta_batch: int | None) -> config.Config:
    overrides: dict[str, Any] = dict(
        seeds=seeds,
        chunk_iterations=args.iterations,
        updates_per_iteration=args.updates,
        meta_batch=meta_batch,
        initial_steps=args.initial_steps,
    )
    base = config.resolve(args.env, actor=args.actor)
    if args.steps is not None:
        if Trainer(base).meta:
            total = base.prior_steps + base.posterior_steps
            prior = max(1, round(args.steps * base.prior_steps / total))
            overrides.update(prior_steps=prior, posterior_steps=max(0, args.steps - prior))
        else:
            overrides.update(steps_per_iteration=args.steps)
    return config.resolve(args.env, actor=args.actor, **overrides)


def time_chunk(cfg: config.Config, iterations: int, repeats: int) -> dict[str, Any]:
    """Compile, warm-up and best-of-``repeats`` times of one chunk of ``iterations``."""
    trainer = Trainer(cfg)
    # Build the env outside any trace, as run.train does: an MJX env first built inside
    # init_seeds' jit would keep tracers of its model (cached_property).
    trainer.env  # noqa: B018
    state = trainer.init_seeds()
    warmup_s = None
    if trainer.meta:
        started = time.perf_counter()
        state = jax.block_until_ready(run.warmup(trainer, state))
        warmup_s = time.perf_counter() - started
    chunk = trainer.compiled_chunk(iterations)
    # Compile = the first call less the best steady one: AOT ``lower().compile()`` of a chunk
    # that captures an MJX model fails when called ("compiled for N inputs but called with M").
    started = time.perf_counter()
    state, _ = jax.block_until_ready(chunk(state))
    first = time.perf_counter() - started
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        state, _ = jax.block_until_ready(chunk(state))
        best = min(best, time.perf_counter() - started)
    compile_s = first - best
    per_iteration = best / iterations
    return {
        "env": cfg.env,
        "seeds": cfg.seeds,
        "meta_batch": cfg.meta_batch if trainer.meta else None,
        "devices": trainer.seed_axis.device_info,
        "iterations": iterations,
        "updates_per_iteration": cfg.updates_per_iteration,
        "env_steps_per_iteration": trainer.task_set.steps_per_iteration,
        "batch_size": cfg.batch_size,
        "warmup_s": warmup_s,
        "compile_s": compile_s,
        "s_per_iteration": per_iteration,
        "ms_per_update": 1000 * per_iteration / cfg.updates_per_iteration,
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env", default="cartpole")
    p.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="seed counts (default 1 2 4 8)"
    )
    p.add_argument(
        "--tasks",
        type=int,
        nargs="+",
        default=None,
        help="meta-RL: meta_batch values (tasks per SGD step), e.g. 1 5 10 40",
    )
    p.add_argument("--actor", default=None, help="actor override (symbolic, mlp, pearl, hyper)")
    p.add_argument("--iterations", type=int, default=10, help="iterations per timed chunk")
    p.add_argument("--updates", type=int, default=None, help="updates_per_iteration override")
    p.add_argument("--steps", type=int, default=None, help="env steps per iteration override")
    p.add_argument(
        "--initial-steps", type=int, default=None, help="meta-RL warm-up steps per task override"
    )
    p.add_argument("--repeats", type=int, default=1, help="timed runs (best is kept)")
    p.add_argument("--json", default=None, metavar="PATH", help="write the rows as JSON")
    args = p.parse_args(argv)

    if args.tasks is not None:
        if args.seeds is not None and len(args.seeds) > 1:
            p.error("--tasks takes one --seeds value")
        seeds = args.seeds[0] if args.seeds else 1
        if not Trainer(config.resolve(args.env, actor=args.actor)).meta:
            p.error(f"--tasks needs a meta-RL task family; {args.env} is a single-task env")
        sweep = [(seeds, t) for t in args.tasks]
        axis = "tasks (meta_batch)"
    else:
        sweep = [(s, None) for s in args.seeds or [1, 2, 4, 8]]
        axis = "seeds"

    load = os.getloadavg()
    print(
        f"env {args.env}, actor {config.resolve(args.env, actor=args.actor).actor}, "
        f"jax {jax.__version__}, backend {jax.default_backend()}, "
        f"{len(jax.devices())} device(s), load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    rows = []
    for seeds, tasks in sweep:
        row = time_chunk(build_config(args, seeds, tasks), args.iterations, args.repeats)
        row["ratio"] = row["s_per_iteration"] / (rows[0] if rows else row)["s_per_iteration"]
        if not rows:
            r = row
            print(
                f"{r['iterations']} iterations per chunk, {r['env_steps_per_iteration']} env "
                f"steps and {r['updates_per_iteration']} updates (batch {r['batch_size']}) "
                "per iteration and seed\n"
            )
            print(
                f"| {axis} | compile (s) | warm-up (s) | s / iteration | ms / update (all seeds) "
                "| ratio to first row |"
            )
            print("|---:|---:|---:|---:|---:|---:|")
        rows.append(row)
        n = row["seeds"] if tasks is None else tasks
        warm = "" if row["warmup_s"] is None else f"{row['warmup_s']:.1f}"
        print(
            f"| {n} | {row['compile_s']:.1f} | {warm} | {row['s_per_iteration']:.3f} "
            f"| {row['ms_per_update']:.2f} | {row['ratio']:.2f} |",
            flush=True,
        )
    load = os.getloadavg()
    print(f"\nload average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"load_average_after": load, "rows": rows}, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
