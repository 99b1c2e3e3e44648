"""The files of a run directory: their names, atomic writes, eval.json and metrics.jsonl.

Every module that reads or writes a run directory imports this one (the host loop in
:mod:`espl_jax.run`, the meta-RL report, the hall of fame, export, evaluate, analyze, the API), so
none of them imports another for a file helper. A run directory holds:

    config.yaml         the resolved config
    metrics.jsonl       one row per iteration and seed (+ deterministic eval after each chunk)
    learning_curve.png  return, L0 ratio, penalty and τ against env steps
    checkpoints/        orbax checkpoints of the seed-stacked TrainState
    expression.txt      the best seed's simplified formula, rounded for reading
    policy.py           standalone act(obs) -> action in the env's own units
    eval.json           returns of the exported policy, per seed and for the best one
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from espl_jax.config import UserError

if TYPE_CHECKING:
    from espl_jax.learner import Trainer
    from espl_jax.sac import TrainState

CHECKPOINT_DIR = "checkpoints"
METRICS_FILE = "metrics.jsonl"
EVAL_FILE = "eval.json"
POLICY_FILE = "policy.py"
EXPRESSION_FILE = "expression.txt"
CURVE_FILE = "learning_curve.png"
# Training seconds up to each checkpoint, so a resumed run reports the time of all its parts.
TIMING_FILE = "timing.json"


def write_atomic(path: Path, text: str) -> None:
    """Write a file so that a kill leaves either the old or the new content, never a part."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: Path, record: dict[str, Any]) -> None:
    """A run-directory JSON file, written atomically."""
    write_atomic(path, json.dumps(record, indent=2) + "\n")


def record_training_seconds(run_dir: Path, iteration: int, seconds: float) -> None:
    """Note in timing.json that the run had trained ``seconds`` when it saved the checkpoint of
    ``iteration``. Entries after ``iteration`` (from a part that a resume discarded) are dropped."""
    kept = {k: v for k, v in _timing(run_dir).items() if int(k) < iteration}
    kept[str(iteration)] = round(seconds, 1)
    write_json(run_dir / TIMING_FILE, kept)


def training_seconds_before(run_dir: Path, iteration: int) -> float | None:
    """Training seconds the run had spent when it saved the checkpoint of ``iteration``; None if
    timing.json does not say (deleted, or a run from before the file existed)."""
    return _timing(run_dir).get(str(iteration))


def _timing(run_dir: Path) -> dict[str, float]:
    try:
        record = json.loads((run_dir / TIMING_FILE).read_text())
    except (OSError, ValueError):  # missing or cut short: the times are unknown, not an error
        return {}
    if not isinstance(record, dict):
        return {}
    return {k: v for k, v in record.items() if k.isdigit() and isinstance(v, int | float)}


def write_eval(run_dir: Path, result: dict[str, Any], warnings: list[str]) -> None:
    """eval.json: ``result`` with the run's warnings, if any, written atomically."""
    if warnings:
        result["warnings"] = list(warnings)
    write_json(run_dir / EVAL_FILE, result)


def read_eval(run_dir: str | Path) -> dict[str, Any] | None:
    """The run's eval.json, or None if it has none yet.

    Raises:
        UserError: eval.json exists but is not a JSON object (corrupt).
    """
    path = Path(run_dir) / EVAL_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UserError(f"{path} is unreadable ({type(err).__name__}: {first_line(err)})") from None
    if not isinstance(record, dict):
        raise UserError(f"{path} is unreadable (not a JSON object)")
    return record


def return_summary(returns: np.ndarray) -> dict[str, float | int]:
    """eval.json's record of a set of episode returns (``jax_eval``, ``reference_eval``)."""
    return {
        "mean": float(np.mean(returns)),
        "std": float(np.std(returns)),
        "min": float(np.min(returns)),
        "max": float(np.max(returns)),
        "episodes": int(len(returns)),
    }


def result_header(
    trainer: Trainer, state: TrainState, best: int, train_seconds: float
) -> dict[str, Any]:
    """What every eval.json starts with: the run, its chosen seed, its budget, its devices."""
    return {
        "env": trainer.config.env,
        "actor": trainer.config.actor,
        "best_seed": best,  # index into the run's seeds (export, analyze)
        "train_seed": trainer.config.seed + best,  # the --seed that trains it alone
        "training": {
            "episodes": int(state.episodes[best]),
            "env_steps": int(state.env_steps[best]),
            "iterations": int(state.iteration[best]),
            "wall_seconds_training": round(train_seconds, 1),
        },
        "devices": trainer.seed_axis.device_info,
        **({"physics": trainer.physics} if trainer.physics else {}),
    }


def warn_on_failure(warnings: list[str], what: str, fn, *args) -> bool:
    """Run an optional step; a failure becomes a warning (printed and recorded), not a crash."""
    try:
        fn(*args)
        return True
    except Exception as err:  # an optional step may fail in any way; the run is kept
        message = f"{what} failed: {type(err).__name__}: {first_line(err)}"
        print(f"warning: {message}", file=sys.stderr)
        warnings.append(message)
        return False


def first_line(err: Exception) -> str:
    """The first non-empty line of an error's message, at most 300 characters."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    return (lines[0] if lines else "no message")[:300]


# Metrics ---------------------------------------------------------------------------------------


def append_metrics(path: Path, metrics: dict, eval_returns: np.ndarray | None) -> None:
    seeds, length = np.asarray(metrics["iteration"]).shape
    with path.open("a") as f:
        for i in range(length):
            for s in range(seeds):
                row = {k: _scalar(v[s, i]) for k, v in metrics.items()}
                row["seed"] = s
                if i == length - 1 and eval_returns is not None:
                    row["eval_return"] = float(eval_returns[s].mean())
                f.write(json.dumps(row) + "\n")


def _scalar(x: Any) -> float | int:
    x = np.asarray(x)
    return int(x) if np.issubdtype(x.dtype, np.integer) else float(x)


def truncate_metrics(path: Path, iteration: int) -> None:
    """Drop rows written after the checkpoint a resumed run restarts from (and a partial last
    line left by a kill mid-write)."""
    if not path.exists():
        return
    rows = [r for r in read_metrics(path) if r["iteration"] <= iteration]
    write_atomic(path, "".join(json.dumps(r) + "\n" for r in rows))


def read_metrics(path: str | Path) -> list[dict]:
    """The rows of a metrics.jsonl. A last line cut short (a kill mid-write) is skipped.

    Raises:
        UserError: a row other than the last is not valid JSON (the file is corrupt).
    """
    path = Path(path)
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path} is unreadable ({type(err).__name__}: {first_line(err)})") from None
    rows = []
    for number, line in enumerate(lines, 1):
        try:
            row = json.loads(line)
            if not isinstance(row, dict) or "iteration" not in row:
                raise ValueError("not a metrics row")
        except ValueError as err:
            if number == len(lines):
                break  # cut short by a kill while it was written: the checkpoint is older
            raise UserError(f"{path} is corrupt at line {number} ({first_line(err)})") from None
        rows.append(row)
    return rows


def plot_learning_curve(metrics_path: Path, out: Path, title: str) -> None:
    """Return (training episodes and deterministic eval), L0 ratio, penalty and τ vs env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_metrics(metrics_path)
    if not rows:
        return
    fig, axes = plt.subplots(2, 2, figsize=(10, 7), sharex=True)
    panels = [
        ("train_return", "return", axes[0, 0]),
        ("l0_ratio", "L0 ratio (E||m||0 / N)", axes[0, 1]),
        ("penalty", "operator penalty", axes[1, 0]),
        ("tau", "temperature τ", axes[1, 1]),
    ]
    seeds = sorted({r["seed"] for r in rows})
    for s in seeds:
        mine = [r for r in rows if r["seed"] == s]
        steps = [r["env_steps"] for r in mine]
        for key, label, ax in panels:
            values = [
                r[key] if r.get("episodes_finished", 1) or key != "train_return" else math.nan
                for r in mine
            ]
            ax.plot(
                steps,
                values,
                lw=1,
                alpha=0.6 if key == "train_return" else 1.0,
                label=f"seed {s} (training)" if key == "train_return" else f"seed {s}",
            )
            ax.set_ylabel(label)
        evals = [(r["env_steps"], r["eval_return"]) for r in mine if "eval_return" in r]
        if evals:
            axes[0, 0].plot(*zip(*evals, strict=True), "o-", lw=2, label=f"seed {s} (formula)")
    axes[0, 1].set_yscale("log")
    for ax in axes[1]:
        ax.set_xlabel("environment steps")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"ESPL on {title}")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
