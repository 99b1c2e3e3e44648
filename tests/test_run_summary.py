"""``benchmarks/run_summary.py`` turns run directories into results rows: a meta-RL run of
several vmapped seeds gives one row per seed, each with its own protocol returns and learning
curve (the mean over seeds that the README's meta-RL table reads), and a command naming --seeds."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from espl_jax import config as config_lib

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "run_summary.py"


def fake_meta_run(run: Path, env: str = "lunarlander_params", actor: str = "symbolic") -> None:
    """The three files run_summary reads, as a 2-seed run of ``env`` (base seed 5) writes them:
    metrics.jsonl's "seed" and eval.json's per_seed "seed" are indices into the batch."""
    run.mkdir()
    config_lib.save(
        config_lib.resolve(env, None, actor=actor, seeds=2, seed=5), run / "config.yaml"
    )
    rows = [
        {"iteration": it, "env_steps": 1000 * it, "seed": s, "eval_return": 10.0 * it + s}
        for it in (5, 10)
        for s in (0, 1)
    ]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    record = {
        "best_seed": 1,
        "train_seed": 6,
        "training": {"env_steps": 10000, "iterations": 10, "wall_seconds_training": 12.5},
        "test": {"mean": 40.0},
        "train": {"mean": 30.0},
        "length": 71.0,
        "selected_paths_per_action": 10.0,
        "per_seed": [
            {"seed": 0, "test_return": -20.0, "train_return": -60.0},
            {"seed": 1, "test_return": 40.0, "train_return": 30.0},
        ],
    }
    (run / "eval.json").write_text(json.dumps(record))


def summarise(tmp_path: Path, *runs: str) -> list[dict]:
    out = tmp_path / "summary.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *(str(tmp_path / r) for r in runs), "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=SCRIPT.parent,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(out.read_text())["rows"]


def test_vmapped_meta_run_gives_one_row_per_seed(tmp_path: Path):
    fake_meta_run(tmp_path / "run")
    rows = summarise(tmp_path, "run")
    assert [(r["seed"], r["test_return"], r["kept"]) for r in rows] == [
        (5, -20.0, False),
        (6, 40.0, True),
    ]
    assert [r["curve"] for r in rows] == [
        [[5000, 50.0], [10000, 100.0]],
        [[5000, 51.0], [10000, 101.0]],
    ]
    assert "length" in rows[1] and "length" not in rows[0]  # only the kept seed is exported
    assert all("--seeds 2 --seed 5" in r["command"] for r in rows)


def test_hyper_trunk_is_recorded_on_hyper_rows_only(tmp_path: Path):
    """hopper_params ships a smaller Hyper trunk than HypeRL's; the CSP and PEARL rows of the same
    family never read it, so only Hyper's rows say it."""
    fake_meta_run(tmp_path / "hyper", "hopper_params", "hyper")
    fake_meta_run(tmp_path / "pearl", "hopper_params", "pearl")
    rows = summarise(tmp_path, "hyper", "pearl")
    assert [r["actor"] for r in rows] == ["hyper"] * 2 + ["pearl"] * 2
    assert all(r["config"]["hyper_trunk"] == [256] for r in rows[:2])
    assert all("hyper_trunk" not in r["config"] for r in rows[2:])
