"""Meta-RL runs killed with SIGKILL at every named kill point, then resumed.

One run of a tiny CSP config is killed five times in a row, each time at the next point of
``espl_jax.faults`` a meta-RL run passes, and resumed with ``--resume`` after each kill (so each
resume also finds the lock file of a killed holder): during the warm-up collection, in the middle
of a chunk, while a checkpoint is written, during the final protocol and during the test-task
exports; the last resume finishes it. It must end as an uninterrupted run of the same config
does: the same TrainState (params, optimizers, per-task and encoder buffers, keys), metrics,
eval.json (but its wall-clock field), tasks.json and test_tasks/ files.

Both families are held to that, bit for bit. For cartpole_fl_ood (stepped in JAX) the whole
simulator state is in the checkpoint. lunarlander_params is stepped in gymnasium (Box2D) on the
host through the same rollout path; its checkpoint holds what determines each episode in
progress (reset seed, params, actions so far: ``envs/box2d.py``), which the resumed process
replays, so its resumed run is equal too.

Slow: 6 min (cartpole_fl_ood) and 10 min (lunarlander_params) on a 2-core CPU shared with another
training run; the uninterrupted run compiles, the killed ones load its programs from the cache.
"""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from espl_jax import config as config_lib
from espl_jax import faults, meta_report, run, rundir, runlock

REPO = Path(__file__).resolve().parent.parent
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("jax_cache")]

# A CSP run small enough to compile and train in ~2 min: three iterations of one chunk each, so
# that each kill point below falls in a different place of the run.
TINY_META = {
    "actor": "symbolic", "layout": "csp", "seeds": 1, "iterations": 3, "chunk_iterations": 1,
    "updates_per_iteration": 4, "meta_batch": 3, "batch_size": 8, "context_batch": 6,
    "initial_steps": 30, "tasks_per_iteration": 2, "prior_steps": 20, "posterior_steps": 20,
    "task_buffer_size": 200, "critic_hidden": [16], "std_hidden": [8], "encoder_hidden": [16],
    "generator_hidden": [8], "latent_dim": 2, "eval_steps": 40, "eval_runs": 1,
    "schedule_iterations": 2,
}  # fmt: skip
# (kill point, checkpoints committed after the kill): each resume starts from the newest one.
KILLS = [
    ("warmup", {0}),  # the initial state only
    ("chunk:2", {0, 1}),  # iteration 1 done, iteration 2 running
    ("checkpoint-write:3", {1, 2}),  # iteration 3 trained and logged, its checkpoint not committed
    ("protocol", {2, 3}),  # training done, the final protocol half run
    ("test-task-export", {2, 3}),  # test_tasks/0/ written, the others not
]


def committed(run_dir: Path) -> set[int]:
    return {
        int(p.name)
        for p in (run_dir / rundir.CHECKPOINT_DIR).iterdir()
        if p.name.isdigit() and (p / "commit_success.txt").is_file()
    }


def train_cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "espl_jax.train", "--no-progress", *args],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip


def assert_killed_at(point: str, run_dir: Path) -> None:
    """What the run directory holds after a kill at ``point``: nothing of the final export before
    the protocol, and the metrics rows of a chunk whose checkpoint was not committed."""
    done = {r["iteration"] for r in rundir.read_metrics(run_dir / rundir.METRICS_FILE)}
    assert done == {"warmup": set(), "chunk:2": {1}}.get(point, {1, 2, 3}), (point, done)
    assert (run_dir / meta_report.TASKS_FILE).is_file() == (
        point in ("protocol", "test-task-export")
    )
    assert not (run_dir / rundir.EVAL_FILE).exists()
    exported = sorted(p.name for p in (run_dir / meta_report.TEST_TASKS_DIR).glob("*"))
    assert exported == (["0"] if point == "test-task-export" else [])
    assert (run_dir / runlock.LOCK_FILE).read_text().startswith("pid ")  # the dead holder's


def assert_trees_equal(a, b) -> None:
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def files(run_dir: Path, pattern: str) -> dict[str, str]:
    return {str(p.relative_to(run_dir)): p.read_text() for p in sorted(run_dir.glob(pattern))}


def assert_same_finished_run(a: Path, b: Path) -> None:
    (_, state_a, step_a), (_, state_b, step_b) = run.load_run(a), run.load_run(b)
    assert step_a == step_b
    assert_trees_equal(state_a, state_b)
    assert rundir.read_metrics(a / rundir.METRICS_FILE) == rundir.read_metrics(
        b / rundir.METRICS_FILE
    )
    records = [json.loads((d / rundir.EVAL_FILE).read_text()) for d in (a, b)]
    for record in records:
        del record["training"]["wall_seconds_training"]
    assert records[0] == records[1]
    for pattern in (
        meta_report.TASKS_FILE,
        f"{meta_report.TEST_TASKS_DIR}/*/*",
        "coefficients.json",
    ):
        assert files(a, pattern) == files(b, pattern), pattern
    assert len(files(b, f"{meta_report.TEST_TASKS_DIR}/*/*")) == 2 * len(
        records[0]["test"]["per_task"]
    )


@pytest.mark.parametrize("env", ["cartpole_fl_ood", "lunarlander_params"])
def test_meta_run_killed_at_every_point_ends_as_an_uninterrupted_one(env, tmp_path, jax_cache):
    config = config_lib.from_mapping({**TINY_META, "env": env})
    reference = tmp_path / "uninterrupted"
    run.train(config, reference, show_progress=False)

    config_file = tmp_path / "tiny.yaml"
    config_lib.save(config, config_file)
    killed = tmp_path / "killed"
    start = ["--config", str(config_file), "--out", str(killed)]
    for n, (point, checkpoints) in enumerate(KILLS):
        env_vars = {**os.environ, **jax_cache, faults.ENV_VAR: point}
        proc = train_cli(["--resume", str(killed)] if n else start, env_vars)
        assert proc.returncode == -signal.SIGKILL, (point, proc.stderr)
        assert committed(killed) == checkpoints, point
        assert_killed_at(point, killed)
    finished = train_cli(["--resume", str(killed)], {**os.environ, **jax_cache})
    assert finished.returncode == 0, finished.stderr
    assert (killed / runlock.LOCK_FILE).read_text() == ""
    assert_same_finished_run(reference, killed)
