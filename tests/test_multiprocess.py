"""A --distributed run of two processes on this machine equals a one-process run on 2 devices.

Two CLI processes join one process group (``jax.distributed.initialize`` on 127.0.0.1, CPU
collectives), each with one CPU device, and train the tiny MLP config's 2 seeds, one seed per
process; then they resume the run for one more iteration. The same run in one process with 2 CPU
devices (XLA_FLAGS) is the reference: each device runs the same per-seed program in both, so the
metrics and eval.json agree exactly (bar the wall time). This is what two hosts do, with the
network between them replaced by the loopback interface.
"""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import yaml
from conftest import TINY_MLP

CONFIG = {**TINY_MLP, "seeds": 2, "iterations": 2, "chunk_iterations": 1}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def train_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "espl_jax.train", "--no-progress", *args]


def two_processes(env: dict, *args: str) -> None:
    group = ["--distributed", "--coordinator", f"127.0.0.1:{free_port()}", "--num-processes", "2"]
    procs = [
        subprocess.Popen(
            train_cmd(*args, *group, "--process-id", str(i)),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in (0, 1)
    ]
    outputs = [p.communicate(timeout=600)[0] for p in procs]
    for p, out in zip(procs, outputs, strict=True):
        assert p.returncode == 0, out[-3000:]


def one_process(env: dict, *args: str) -> None:
    env = {**env, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    done = subprocess.run(train_cmd(*args), env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]


def results(run_dir: Path) -> tuple[str, dict]:
    record = json.loads((run_dir / "eval.json").read_text())
    record["training"].pop("wall_seconds_training")
    return (run_dir / "metrics.jsonl").read_text(), record


def test_two_processes_train_and_resume_as_one_process_with_two_devices(tmp_path, jax_cache):
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    env = {**os.environ, **jax_cache, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    multi, single = tmp_path / "multi", tmp_path / "single"
    two_processes(env, "--config", str(config), "--out", str(multi))
    one_process(env, "--config", str(config), "--out", str(single))

    metrics, record = results(multi)
    assert record["devices"] == {"count": 2, "platform": "cpu", "processes": 2}
    assert sorted(p.name for p in (multi / "checkpoints").iterdir()) == ["1", "2"]
    single_metrics, single_record = results(single)
    assert single_record.pop("devices") == {"count": 2, "platform": "cpu"}
    record.pop("devices")
    assert metrics == single_metrics
    assert record == single_record
    rows = [json.loads(line) for line in metrics.splitlines()]
    assert {r["seed"] for r in rows} == {0, 1}
    assert rows[-1]["train_return"] != rows[-2]["train_return"]  # the two seeds differ

    two_processes(env, "--resume", str(multi), "--iterations", "3")
    one_process(env, "--resume", str(single), "--iterations", "3")
    assert results(multi)[0] == results(single)[0]
    assert max(json.loads(line)["iteration"] for line in results(multi)[0].splitlines()) == 3


def test_distributed_needs_a_run_directory():
    done = subprocess.run(
        train_cmd("--env", "cartpole", "--distributed"), capture_output=True, text=True
    )
    assert done.returncode != 0
    assert "--distributed needs --out" in done.stderr
    assert "Traceback" not in done.stderr
