"""CSP against PEARL and Hyper on one task family, at equal budget: a table and the learning curves.

    python benchmarks/meta_compare.py --env cartpole_fl_ood --seeds 0-2
        [--actors symbolic,pearl,hyper] [--set iterations=10 ...] [--out runs/meta]
        [--json compare.json] [--plot compare.png]
    python benchmarks/meta_compare.py --runs RUN_DIR [RUN_DIR ...] [--json ...] [--plot ...]

The first form trains the family's shipped config (``configs/ENV.yaml`` with ``--set``
overrides) once per actor and seed, one run after another; the budget keys (iterations, env
steps, updates, batch sizes) are the same for the three actors, only ``--actor`` changes. The
second form reads run directories trained elsewhere (e.g. several at a time) instead.

Prints, per actor: the test-task return under PEARL's protocol (``eval.json``: the last
trajectory's return, mean over runs and test tasks), per seed and its mean, the training-task
return, env steps, wall time per seed, and for CSP the adapted formulas' mean length and selected
paths per action. ``--plot`` draws the test-task return after each chunk (``eval_return`` in
``metrics.jsonl``) against env steps: the mean over seeds, the range shaded. Not part of the
test suite.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from seed_sweep import parse_overrides, parse_seeds

from espl_jax import config as config_lib
from espl_jax import run, rundir
from espl_jax.cli import run_main
from espl_jax.config import UserError

NAMES = {"symbolic": "CSP", "pearl": "PEARL", "hyper": "Hyper"}


def train_all(env: str, actors: list[str], seeds: list[int], overrides: dict, out: Path):
    """Train every (actor, seed) one after another; the run directories, in order."""
    tag = time.strftime("%Y%m%d-%H%M%S")
    dirs = []
    for actor in actors:
        for seed in seeds:
            config = config_lib.resolve(env, actor=actor, seed=seed, seeds=1, **overrides)
            run_dir = out / f"{env}-{actor}-seed{seed}-{tag}"
            started = time.perf_counter()
            run.train(config, run_dir, show_progress=False)
            (run_dir / "wall_seconds.txt").write_text(f"{time.perf_counter() - started:.1f}\n")
            dirs.append(run_dir)
    return dirs


def read_run(run_dir: Path) -> dict:
    """One finished meta-RL run: its config, result and learning curve."""
    config = run.saved_config(run_dir)
    result = rundir.read_eval(run_dir)
    if result is None or "test" not in result:
        raise UserError(f"{run_dir} has no meta-RL eval.json (unfinished, or a single-task run)")
    wall_file = run_dir / "wall_seconds.txt"
    wall = (
        float(wall_file.read_text())
        if wall_file.is_file()
        else result["training"]["wall_seconds_training"]
    )
    curve = [
        (r["env_steps"], r["eval_return"])
        for r in rundir.read_metrics(run_dir / rundir.METRICS_FILE)
        if "eval_return" in r
    ]
    return {
        "env": config.env,
        "actor": config.actor,
        "seed": config.seed,
        "budget": budget(config),
        "test_return": result["test"]["mean"],
        "train_return": result["train"]["mean"],
        "env_steps": result["training"]["env_steps"],
        "wall_seconds": wall,
        "length": result.get("length"),
        "selected_paths_per_action": result.get("selected_paths_per_action"),
        "curve": curve,
        "run_dir": str(run_dir),
    }


def budget(config) -> dict:
    """The keys that must match for a comparison at equal budget."""
    keys = (
        "iterations", "updates_per_iteration", "batch_size", "meta_batch", "initial_steps",
        "tasks_per_iteration", "prior_steps", "posterior_steps", "critic_hidden",
    )  # fmt: skip
    values = config.to_dict()
    return {k: values[k] for k in keys}


def summarise(runs: list[dict]) -> dict:
    envs = {r["env"] for r in runs}
    if len(envs) != 1:
        raise UserError(f"runs of one family only, got {sorted(envs)}")
    budgets = {json.dumps(r["budget"], sort_keys=True) for r in runs}
    actors = []
    for actor in NAMES:
        mine = sorted((r for r in runs if r["actor"] == actor), key=lambda r: r["seed"])
        if not mine:
            continue
        returns = [r["test_return"] for r in mine]
        lengths = [r["length"] for r in mine if r["length"] is not None]
        paths = [r["selected_paths_per_action"] for r in mine if r["length"] is not None]
        actors.append(
            {
                "actor": actor,
                "name": NAMES[actor],
                "seeds": [r["seed"] for r in mine],
                "test_return": returns,
                "test_mean": statistics.mean(returns),
                "train_mean": statistics.mean(r["train_return"] for r in mine),
                "env_steps": mine[0]["env_steps"],
                "wall_seconds_mean": statistics.mean(r["wall_seconds"] for r in mine),
                "length_mean": statistics.mean(lengths) if lengths else None,
                "paths_per_action_mean": statistics.mean(paths) if paths else None,
            }
        )
    return {
        "env": envs.pop(),
        "equal_budget": len(budgets) == 1,
        "budget": runs[0]["budget"],
        "actors": actors,
        "runs": runs,
    }


def report(summary: dict) -> str:
    lines = [
        f"{summary['env']}: test-task return under PEARL's protocol"
        + ("" if summary["equal_budget"] else "  (WARNING: the runs' budgets differ)"),
        f"{'actor':<6} {'seeds':>5} {'test mean':>9} {'per seed':<26} {'train':>7} "
        f"{'env steps':>9} {'wall s':>7} {'length':>6} {'paths':>5}",
    ]
    for a in summary["actors"]:
        per_seed = ", ".join(f"{v:.1f}" for v in a["test_return"])
        length = f"{a['length_mean']:.1f}" if a["length_mean"] is not None else "-"
        paths = f"{a['paths_per_action_mean']:.1f}" if a["paths_per_action_mean"] else "-"
        lines.append(
            f"{a['name']:<6} {len(a['seeds']):>5} {a['test_mean']:>9.2f} {per_seed:<26} "
            f"{a['train_mean']:>7.2f} {a['env_steps']:>9} {a['wall_seconds_mean']:>7.0f} "
            f"{length:>6} {paths:>5}"
        )
    return "\n".join(lines)


def plot(summary: dict, out: Path) -> None:
    """Test-task return against env steps per actor: mean over seeds, min–max shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6, 4))
    for a in summary["actors"]:
        curves = [r["curve"] for r in summary["runs"] if r["actor"] == a["actor"]]
        n = min(len(c) for c in curves)
        steps = np.asarray([s for s, _ in curves[0][:n]])
        values = np.asarray([[v for _, v in c[:n]] for c in curves])
        seeds = f"{len(curves)} seed" + ("s" if len(curves) > 1 else "")
        ax.plot(steps, values.mean(axis=0), "o-", label=f"{a['name']} ({seeds})")
        ax.fill_between(steps, values.min(axis=0), values.max(axis=0), alpha=0.2)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("test-task return (PEARL's protocol)")
    ax.set_title(summary["env"])
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/meta_compare.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--env", default="cartpole_fl_ood")
    p.add_argument("--seeds", default="0-2", help="e.g. 0-2 or 0,3 (default 0-2)")
    p.add_argument("--actors", default="symbolic,pearl,hyper")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every actor (repeatable)")  # fmt: skip
    p.add_argument("--out", default="runs/meta", help="where the run directories go")
    p.add_argument("--runs", nargs="+", metavar="RUN_DIR", help="summarise these runs instead")
    p.add_argument("--json", help="write the summary as JSON here")
    p.add_argument("--plot", help="write the learning curves here (PNG)")
    args = p.parse_args(argv)
    if args.runs:
        dirs = [Path(d) for d in args.runs]
    else:
        actors = [a.strip() for a in args.actors.split(",")]
        unknown = [a for a in actors if a not in NAMES]
        if unknown:
            raise UserError(f"--actors: unknown {unknown}; choose from {', '.join(NAMES)}")
        overrides = parse_overrides(args.set)
        dirs = train_all(args.env, actors, parse_seeds(args.seeds), overrides, Path(args.out))
    summary = summarise([read_run(d) for d in dirs])
    print(report(summary))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    if args.plot:
        plot(summary, Path(args.plot))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
