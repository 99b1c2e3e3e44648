"""The seed axis sharded over 2 CPU devices gives the same per-seed results as one device.

Runs tests/sharded_seeds.py in a subprocess with XLA_FLAGS=--xla_force_host_platform_device_count=2
(the flag must be set before JAX starts). Not bitwise: XLA compiles the sharded program (one seed
per device) apart from the two-seed one, and their matrix products round differently in the last
bit (1.5e-8 after one update, measured) — the same holds between a 2-seed vmapped run and two
1-seed runs on one device. So the test allows 1e-5 after two updates, far below the gap between
two seeds, which is what a misplaced shard would produce.
"""

import json
import os
import subprocess
import sys
from pathlib import Path


def test_two_cpu_devices_give_the_per_seed_results_of_one(tmp_path, jax_cache):
    script = Path(__file__).with_name("sharded_seeds.py")
    env = {**os.environ, **jax_cache, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    done = subprocess.run(
        [sys.executable, str(script), str(tmp_path)], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["jax_devices"] == 2
    assert report["eval_devices"] == {"count": 2, "platform": "cpu"}
    assert report["state_devices"] == [2]  # every leaf of the state is split over both devices
    assert report["seed_gap"] > 1e-3
    assert max(report["max_abs_diff"]) < 1e-5, report
    assert report["shared_argument"] == [7.0, 14.0]
