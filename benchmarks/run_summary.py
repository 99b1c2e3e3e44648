"""Collect finished runs' headline figures into one results JSON (results as data, not prose).

For each run directory (each seed of a vmapped meta-RL run): the command that reproduces it (from
its config.yaml; ``config`` holds the keys it varies from the defaults), its seed, physics
backend, budget, training wall time and returns (meta-RL: the protocol's test and train means;
single task: the exported policy's JAX return and policy.py's reference return)::

    python benchmarks/run_summary.py /work/sweeps/hp_native_s* --label "CSP, native physics" \\
        --json results/hopper_params_native.json

Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from env_throughput import write_result

from espl_jax import config as config_lib
from espl_jax import rundir

# Config keys a row records when they differ from the defaults (what a comparison varies).
VARIED = (
    "critic",
    "critic_layer_norm",
    "critic_hidden",
    "updates_per_iteration",
    "iterations",
    "schedule_iterations",
    "keep_best_formula",
    "target_l0_ratio",
    "hyper_trunk",  # recorded on Hyper's rows only: the other kinds never read it
)


def summary(run_dir: Path) -> list[dict]:
    """The run's rows: one, or for a meta-RL run of several vmapped seeds one per seed (each
    seed's protocol returns and its own learning curve; the formula's length and paths only on
    the kept seed's row, the only one exported). A single-task run stays one row (its kept
    seed), as its eval.json reports."""
    cfg = config_lib.load(run_dir / "config.yaml")
    record = json.loads((run_dir / "eval.json").read_text())
    seeds = f"--seeds {cfg.seeds} " if cfg.seeds != 1 else ""
    row = {
        "run": str(run_dir),
        "command": (
            f"python -m espl_jax.train --env {cfg.env} --actor {cfg.actor} {seeds}"
            f"--seed {cfg.seed} --physics {cfg.physics}"
        ),
        "env": cfg.env,
        "actor": cfg.actor,
        "seed": record["train_seed"],
        "physics": record.get("physics"),
        "env_steps": record["training"]["env_steps"],
        "iterations": record["training"]["iterations"],
        "wall_seconds_training": record["training"]["wall_seconds_training"],
    }
    defaults = config_lib.Config()
    row["config"] = {
        k: config_lib._plain(getattr(cfg, k))
        for k in VARIED
        if getattr(cfg, k) != getattr(defaults, k) and (k != "hyper_trunk" or cfg.actor == "hyper")
    }
    metrics = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    row["curve"] = curve(metrics, record.get("best_seed", 0))
    if "test" not in record:
        row["jax_return"] = record["jax_eval"]["mean"]
        if "reference_eval" in record:
            row["reference_return"] = record["reference_eval"]["mean"]
        if "length" in record:
            row["length"] = record["length"]
        return [row]
    # Only the kept seed's formula is exported, so only its row has a length and paths.
    exported = {k: record[k] for k in ("length", "selected_paths_per_action") if k in record}
    if cfg.seeds == 1:
        returns = {"test_return": record["test"]["mean"], "train_return": record["train"]["mean"]}
        return [row | returns | exported]
    rows = []
    for entry in record["per_seed"]:  # "seed" there is the index in the vmapped batch
        kept = entry["seed"] == record["best_seed"]
        mine = {
            "seed": cfg.seed + entry["seed"],
            "test_return": entry["test_return"],
            "train_return": entry["train_return"],
            "curve": curve(metrics, entry["seed"]),
            "vmapped_seeds": cfg.seeds,
            "kept": kept,
        }
        rows.append(row | mine | (exported if kept else {}))
    return rows


def curve(metrics: list[dict], index: int) -> list:
    """(env steps, progress-evaluation return) after each chunk, of the seed at ``index`` in the
    run's vmapped batch (metrics.jsonl's "seed")."""
    points = {
        m["env_steps"]: m["eval_return"]
        for m in metrics
        if m.get("eval_return") is not None and m.get("seed", index) == index
    }
    return sorted(points.items())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--label", default="", help="what the runs are, for the reader")
    parser.add_argument("--json", required=True)
    args = parser.parse_args(argv)
    rows = [row for d in args.runs for row in summary(d)]
    for row in rows:
        row["label"] = args.label
        print(json.dumps(row))
    write_result(args.json, rows, argv, script="benchmarks/run_summary.py")


if __name__ == "__main__":
    main()
