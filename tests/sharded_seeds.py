"""Run by tests/test_sharding.py in a process with 2 CPU devices (XLA_FLAGS set by the test).

Initialises the tiny MLP config's 2 seeds (the seed axis is sharded the same way for every
actor kind; the MLP compiles in seconds, the symbolic network in minutes) and trains them for one
short chunk twice — sharded over 2 devices and on one device — and prints, as JSON, where the
sharded state lives, what the trainer records for eval.json, and how far each seed's learned
params are from one device's.
"""

import json
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import TINY_MLP  # noqa: E402

from espl_jax import config as config_lib  # noqa: E402
from espl_jax.learner import Trainer  # noqa: E402

tiny = {**TINY_MLP, "seeds": 2, "iterations": 1, "chunk_iterations": 1, "updates_per_iteration": 2}


def train(devices: int) -> tuple[Trainer, list[np.ndarray], set[int]]:
    trainer = Trainer(config_lib.from_mapping({**tiny, "devices": devices}))
    trainer.env  # noqa: B018  (built outside any trace, as run.train does)
    state = trainer.init_seeds()
    placed = {len(leaf.sharding.device_set) for leaf in jax.tree.leaves(state)}
    state, _ = trainer.compiled_chunk(1)(state)
    learned = [np.asarray(leaf) for leaf in jax.tree.leaves((state.actor, state.critic))]
    return trainer, learned, placed


sharded, two, placed = train(devices=2)
_, one, _ = train(devices=1)
# An argument shared by every seed (task params in Trainer.compiled_adapt) is replicated, not
# split over the devices: seed s gets x[s] * sum(t).
with_shared = sharded.seed_axis.over_seeds(lambda x, t: x * t.sum(), shared=(1,))
report = {
    "jax_devices": len(jax.devices()),
    "eval_devices": sharded.seed_axis.device_info,
    "state_devices": sorted(placed),
    # per seed: the largest difference of any learned leaf between 2 devices and 1
    "max_abs_diff": [
        max(float(np.max(np.abs(a[s] - b[s]))) for a, b in zip(two, one, strict=True))
        for s in (0, 1)
    ],
    # how different two seeds are: a swapped or duplicated shard would show up at this size
    "seed_gap": max(float(np.max(np.abs(b[0] - b[1]))) for b in one),
    "shared_argument": np.asarray(
        with_shared(np.array([1.0, 2.0]), np.array([1.0, 2.0, 4.0]))
    ).tolist(),
}
print(json.dumps(report))
