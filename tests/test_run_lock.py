"""One writer per run directory (``espl_jax.runlock``): a second process is refused with the
holder's pid, and a lock left by a process killed with SIGKILL blocks nothing."""

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import TINY, TINY_MLP, committed_checkpoints

from espl_jax import config as config_lib
from espl_jax import evaluate, rundir, runlock, train
from espl_jax.cli import run_main
from espl_jax.config import UserError

REPO = Path(__file__).resolve().parent.parent
HOLDER = f"pid {os.getpid()} on host {socket.gethostname()}"


def test_a_held_directory_is_refused_naming_the_holder(tmp_path):
    lock = tmp_path / runlock.LOCK_FILE
    with runlock.hold(tmp_path):
        assert lock.read_text() == HOLDER + "\n"
        refusal = re.escape(f"in use by another process ({HOLDER})")
        with pytest.raises(UserError, match=refusal), runlock.hold(tmp_path):
            pass
        assert lock.read_text() == HOLDER + "\n"  # the refusal changed nothing
    assert lock.read_text() == ""
    with runlock.hold(tmp_path):  # free again
        pass


def test_a_lock_left_by_a_killed_process_blocks_nothing(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\nfrom espl_jax import runlock\n"
         f"with runlock.hold({str(tmp_path)!r}):\n    print('held', flush=True)\n"
         "    time.sleep(600)\n"],
        cwd=REPO, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(UserError, match=f"pid {holder.pid} on host"), runlock.hold(tmp_path):
            pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # The killed holder's line stays in the file, but the kernel has dropped its flock.
    assert f"pid {holder.pid} on" in (tmp_path / runlock.LOCK_FILE).read_text()
    with runlock.hold(tmp_path):
        assert (tmp_path / runlock.LOCK_FILE).read_text() == HOLDER + "\n"


@pytest.mark.parametrize(
    "module, args",
    [(train.main, ["--resume", "{run}", "--no-progress"]), (evaluate.main, ["{run}"])],
    ids=["resume", "evaluate"],
)
def test_commands_that_write_a_run_refuse_a_held_one(module, args, tmp_path, capfd):
    config_lib.save(config_lib.from_mapping(TINY), tmp_path / "config.yaml")
    with runlock.hold(tmp_path):
        capfd.readouterr()
        status = run_main(module, [a.format(run=tmp_path) for a in args])
        err = capfd.readouterr().err
    assert status == 2
    assert err.splitlines() == [f"error: {tmp_path} is in use by another process ({HOLDER}): "
                                "one process writes a run directory at a time; wait for it to "
                                "end, or stop it and --resume"]  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == [runlock.LOCK_FILE, "config.yaml"]


def test_two_trainings_of_one_run_directory_then_kill_9_and_resume(tmp_path, jax_cache):
    """Two ``train --out SAME``: the second is refused naming the first's pid, as is a
    ``--resume`` while the first runs; after ``kill -9`` of the first, ``--resume`` works."""
    endless = {**TINY_MLP, "iterations": 100_000, "buffer_size": 64}  # killed, never finished
    config_file = tmp_path / "endless.yaml"
    config_lib.save(config_lib.from_mapping(endless), config_file)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "espl_jax.train", "--no-progress"]
    env = {**os.environ, **jax_cache}

    def cli(*args: str) -> subprocess.Popen:
        return subprocess.Popen(
            [*cmd, *args], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip

    first = subprocess.Popen(
        [*cmd, "--config", str(config_file), "--out", str(run_dir)],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        checkpoints = run_dir / rundir.CHECKPOINT_DIR
        while not committed_checkpoints(checkpoints) - {0}:  # a trained one, for the resume below
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "no checkpoint in time"
            time.sleep(0.2)
        second = cli("--config", str(config_file), "--out", str(run_dir))
        resumer = cli("--resume", str(run_dir))  # beside it: the two only read before refusing
        for refused in (second, resumer):
            _, stderr = refused.communicate(timeout=600)
            assert refused.returncode == 2, stderr
            lines = stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error: "), stderr
            assert f"in use by another process (pid {first.pid} on host" in lines[0]
        assert first.poll() is None, "the first run must hold the directory throughout"
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    assert first.returncode == -signal.SIGKILL
    assert f"pid {first.pid} on" in (run_dir / runlock.LOCK_FILE).read_text()

    # The stale lock blocks nothing: resume up to the newest checkpoint and finish the run there.
    trained = max(committed_checkpoints(run_dir / rundir.CHECKPOINT_DIR))
    resumed = cli("--resume", str(run_dir), "--iterations", str(trained))
    _, stderr = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, stderr
    assert rundir.read_eval(run_dir)["training"]["iterations"] == trained
    assert (run_dir / runlock.LOCK_FILE).read_text() == ""
