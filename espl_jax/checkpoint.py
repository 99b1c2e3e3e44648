"""Orbax checkpoints of the (seed-stacked) TrainState, with readable errors."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp

from espl_jax import faults
from espl_jax.config import UserError

KEEP = 2  # the newest and the one before it: a crash while writing never loses the last good one


def manager(directory: str | Path) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=KEEP, create=True)
    # The handler is named so that a fresh manager can read a checkpoint's metadata (shapes).
    return ocp.CheckpointManager(
        Path(directory).resolve(), options=options, item_handlers=ocp.StandardCheckpointHandler()
    )


def save(mngr: ocp.CheckpointManager, iteration: int, state: Any) -> None:
    """Write the state under ``iteration`` and wait until it is committed to disk."""
    mngr.save(iteration, args=ocp.args.StandardSave(_without_empty(state)), force=True)
    faults.kill_point(f"checkpoint-write:{iteration}")
    mngr.wait_until_finished()


def _without_empty(tree: Any) -> Any:
    """Zero-size arrays become None: orbax refuses to save them, and MJX data has some (e.g.
    ``act`` for models without actuator state). They carry no values; restore takes them from
    the template."""
    return jax.tree.map(lambda x: None if x.size == 0 else x, tree)


def restore_latest(directory: str | Path, like: Any) -> tuple[int, Any]:
    """The newest complete checkpoint in ``directory``, restored into the structure of ``like``.

    Args:
        directory: the checkpoint directory.
        like: the pytree to restore into, or a function ``like(stored)`` of the checkpoint's
            metadata tree (leaves with ``.shape``; nested dicts and lists) returning it, for a
            checkpoint whose array shapes differ from what today's config would build.

    Raises:
        UserError: no checkpoint, or one that cannot be read (corrupt or from another config).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise UserError(f"no checkpoints in {directory.parent}: {directory.name}/ is missing")
    # orbax logs its own ERROR line on unreadable metadata; the UserError below is the one message.
    with _quiet_absl(), manager(directory) as mngr:
        step = mngr.latest_step()
        if step is None:
            raise UserError(f"no complete checkpoint in {directory}")
        try:
            if callable(like):
                like = like(mngr.item_metadata(step).tree)
            abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _without_empty(like))
            state = mngr.restore(step, args=ocp.args.StandardRestore(abstract))
        except Exception as err:  # orbax raises many types for unreadable data
            raise UserError(
                f"checkpoint {directory / str(step)} is unreadable ({type(err).__name__}: "
                f"{_first_line(err)}); it may be corrupt or from another config"
            ) from None
    state = jax.tree.map(lambda r, t: t if r is None else r, state, like, is_leaf=_is_none)
    return step, state


def _first_line(err: Exception) -> str:
    lines = [line for line in str(err).splitlines() if line.strip()]
    return (lines[0] if lines else "no message")[:200]


def _is_none(x: Any) -> bool:
    return x is None


@contextlib.contextmanager
def _quiet_absl():
    """Silence absl (orbax) log records below CRITICAL for the duration of the block."""
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)
