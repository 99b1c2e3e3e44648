"""Run by tests/test_sharding.py in a process with 2 CPU devices (XLA_FLAGS set by the test).

Trains the tiny config for one short iteration twice — 2 seeds sharded over 2 devices, and the
same 2 seeds on one device — and prints, as JSON, what the sharded run recorded and used and how
far each seed's learned params are from the one-device run's.
"""

import json
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import TINY  # noqa: E402

from espl_jax import config as config_lib  # noqa: E402
from espl_jax import run  # noqa: E402
from espl_jax.trainer import Trainer  # noqa: E402

out = Path(sys.argv[1])
tiny = {**TINY, "seeds": 2, "iterations": 1, "chunk_iterations": 1, "updates_per_iteration": 2}


def learned(run_dir: Path) -> list[np.ndarray]:
    _, state, _ = run.load_run(run_dir)
    return [np.asarray(leaf) for leaf in jax.tree.leaves((state.actor, state.critic))]


sharded_config = config_lib.from_mapping({**tiny, "devices": 2})
placed = Trainer(sharded_config).init_seeds()
sharded = run.train(sharded_config, out / "sharded", show_progress=False)
run.train(config_lib.from_mapping({**tiny, "devices": 1}), out / "one_device", show_progress=False)
two, one = learned(out / "sharded"), learned(out / "one_device")
report = {
    "jax_devices": len(jax.devices()),
    "eval_devices": sharded["devices"],
    "state_devices": sorted({len(leaf.sharding.device_set) for leaf in jax.tree.leaves(placed)}),
    # per seed: the largest difference of any learned leaf between 2 devices and 1
    "max_abs_diff": [
        max(float(np.max(np.abs(a[s] - b[s]))) for a, b in zip(two, one, strict=True))
        for s in (0, 1)
    ],
    # how different two seeds are: a swapped or duplicated shard would show up at this size
    "seed_gap": max(float(np.max(np.abs(b[0] - b[1]))) for b in one),
}
print(json.dumps(report))
