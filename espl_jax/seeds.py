"""The seed axis: a run trains ``config.seeds`` seeds at once (``--seeds S``), and every tree of
its state — ``TrainState``, actor params, metrics, evaluation returns — carries them on its
leading axis (vmapped in ``Trainer.over_seeds``, sharded over devices by ``Trainer.place``).

``one_seed`` takes one seed out of such a tree as numpy (for export, the hall of fame, the
end-of-run report, the Python API); ``take`` is the same slice of the leading axis without the
host copy, usable under ``jit`` (a phase's i-th drawn policy in meta-RL collection).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def take(tree: Any, i: Any) -> Any:
    """Every leaf's entry ``i`` of its leading axis (``x[i]``); traceable."""
    return jax.tree.map(lambda x: x[i], tree)


def one_seed(tree: Any, s: int) -> Any:
    """Seed ``s`` of a seed-stacked tree, every leaf a numpy array (``np.asarray(x[s])``)."""
    return jax.tree.map(np.asarray, take(tree, s))
