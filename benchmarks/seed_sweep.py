"""Seed sweep: how many seeds of a shipped config learn a formula that clears the env's bar.

    python benchmarks/seed_sweep.py --env cartpole --seeds 0-4 [--mode vmapped|sequential]
        [--set finetune=false ...] [--out runs/sweeps] [--json sweep.json]

Trains the env's shipped config (``configs/ENV.yaml``, with ``--set`` overrides) once per seed
— all seeds in one vmapped run (``--seeds N --seed K``: seed i is ``PRNGKey(K + i)``, the key of
a one-seed ``--seed K+i`` run) or one run after another — and prints, per seed: the return of
the exported formula over ``eval_episodes`` episodes (1000 in JAX; the Box2D configs use 100 in
gymnasium), its length, the training episodes used, and wall and CPU time, then the count of
seeds that meet the env's bar with the best and the median. ``--json`` writes the same.

On a 2-core CPU a vmapped run of S seeds costs about 0.8·S one-seed runs of wall time (the
cores are already busy with one seed's matrix products): vmapped is the default.
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import yaml

from espl_jax import config as config_lib
from espl_jax import run, rundir
from espl_jax.cli import run_main
from espl_jax.config import UserError

# The bars of the robustness issue (and the paper's Table 2 for context).
BARS = {
    "cartpole": 990.0,
    "mountaincar": 90.0,
    "pendulum": -170.0,
    "inverted_double_pendulum": 9300.0,
    "inverted_pendulum_swingup": 800.0,
    "lunarlander": 200.0,
    "hopper": 2000.0,
    "bipedalwalker": 250.0,
}


def parse_seeds(text: str) -> list[int]:
    """ "0-4" -> [0, 1, 2, 3, 4]; "0,2,5" -> [0, 2, 5]; contiguous ranges only for vmapped."""
    seeds: list[int] = []
    for part in text.split(","):
        if "-" in part:
            low, high = part.split("-")
            seeds.extend(range(int(low), int(high) + 1))
        else:
            seeds.append(int(part))
    if not seeds or min(seeds) < 0:
        raise UserError(f"--seeds must name non-negative seeds, got {text!r}")
    return seeds


def parse_overrides(items: list[str]) -> dict:
    values = {}
    for item in items:
        if "=" not in item:
            raise UserError(f"--set takes KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        values[key] = yaml.safe_load(value)
    return values


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def train(config, run_dir: Path) -> tuple[dict, float, float]:
    wall, cpu = time.perf_counter(), cpu_seconds()
    result = run.train(config, run_dir, show_progress=False)
    return result, time.perf_counter() - wall, cpu_seconds() - cpu


def sweep(env: str, seeds: list[int], mode: str, overrides: dict, out: Path) -> dict:
    base = config_lib.resolve(env, **overrides)
    tag = time.strftime("%Y%m%d-%H%M%S")
    rows = []
    if mode == "vmapped":
        if seeds != list(range(seeds[0], seeds[0] + len(seeds))):
            raise UserError("--mode vmapped needs a contiguous range of seeds, e.g. 0-4")
        config = config_lib.from_mapping({"seed": seeds[0], "seeds": len(seeds)}, base=base)
        run_dir = out / f"{env}-seeds{seeds[0]}-{seeds[-1]}-{tag}"
        result, wall, cpu = train(config, run_dir)
        for entry in result["per_seed"]:
            rows.append(
                {
                    "seed": seeds[0] + entry["seed"],
                    "return": entry["jax_eval"]["mean"],
                    "std": entry["jax_eval"]["std"],
                    "episodes": entry["jax_eval"]["episodes"],
                    "length": entry.get("length"),
                    "formula": entry.get("formula"),
                    "exported": entry.get("exported", "final"),
                    "training_episodes": result["training"]["episodes"],
                    "wall_seconds": wall / len(seeds),
                    "cpu_seconds": cpu / len(seeds),
                    "run_dir": str(run_dir),
                }
            )
        # Per-seed training episodes are in metrics.jsonl; eval.json keeps the best seed's.
        episodes = _episodes_per_seed(run_dir)
        for r in rows:
            r["training_episodes"] = episodes.get(r["seed"] - seeds[0], r["training_episodes"])
    else:
        for seed in seeds:
            config = config_lib.from_mapping({"seed": seed, "seeds": 1}, base=base)
            run_dir = out / f"{env}-seed{seed}-{tag}"
            result, wall, cpu = train(config, run_dir)
            rows.append(
                {
                    "seed": seed,
                    "return": result["jax_eval"]["mean"],
                    "std": result["jax_eval"]["std"],
                    "episodes": result["jax_eval"]["episodes"],
                    "length": result.get("length"),
                    "formula": result.get("formula"),
                    "exported": result["per_seed"][0].get("exported", "final"),
                    "training_episodes": result["training"]["episodes"],
                    "wall_seconds": wall,
                    "cpu_seconds": cpu,
                    "run_dir": str(run_dir),
                }
            )
    bar = BARS.get(env)
    returns = [r["return"] for r in rows]
    return {
        "env": env,
        "mode": mode,
        "overrides": overrides,
        "bar": bar,
        "met": sum(r >= bar for r in returns) if bar is not None else None,
        "seeds": len(rows),
        "best": max(returns),
        "median": statistics.median(returns),
        "per_seed": rows,
    }


def _episodes_per_seed(run_dir: Path) -> dict[int, int]:
    episodes: dict[int, int] = {}
    for row in rundir.read_metrics(run_dir / rundir.METRICS_FILE):
        episodes[row["seed"]] = max(episodes.get(row["seed"], 0), row["episodes"])
    return episodes


def report(summary: dict) -> str:
    lines = [
        f"{summary['env']} ({summary['mode']}, overrides {summary['overrides'] or 'none'})",
        f"{'seed':>4} {'return':>10} {'± std':>8} {'eps':>5} {'length':>7} {'train eps':>9} "
        f"{'wall s':>7} {'cpu s':>7}  exported",
    ]
    for r in summary["per_seed"]:
        length = f"{r['length']:.0f}" if r["length"] is not None else "-"
        lines.append(
            f"{r['seed']:>4} {r['return']:>10.2f} {r['std']:>8.2f} {r['episodes']:>5} "
            f"{length:>7} {r['training_episodes']:>9} {r['wall_seconds']:>7.0f} "
            f"{r['cpu_seconds']:>7.0f}  {r['exported']}"
        )
    if summary["bar"] is not None:
        lines.append(
            f"{summary['met']}/{summary['seeds']} seeds >= {summary['bar']:g}; "
            f"best {summary['best']:.2f}, median {summary['median']:.2f}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/seed_sweep.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--env", default="cartpole")
    p.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 0,3,7 (default 0-4)")
    p.add_argument("--mode", choices=["vmapped", "sequential"], default="vmapped")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set finetune=false (repeatable)")  # fmt: skip
    p.add_argument("--out", default="runs/sweeps", help="where the run directories go")
    p.add_argument("--json", help="write the summary as JSON here")
    args = p.parse_args(argv)
    summary = sweep(
        args.env, parse_seeds(args.seeds), args.mode, parse_overrides(args.set), Path(args.out)
    )
    print(report(summary))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
