"""The seed axis: a run trains ``config.seeds`` seeds at once (``--seeds S``), and every tree of
its state — ``TrainState``, actor params, metrics, evaluation returns — carries them on its
leading axis. This module is that axis: how it is split over devices and hosts, mapped over and
brought back (docs/design.md "One trainer"):

- ``SeedAxis``: the device mesh the seeds are split over, ``place`` (shard a seed-stacked tree
  over it) and ``over_seeds`` (jit a one-seed function, vmapped over the seeds and
  ``shard_map``-ped over the devices).
- ``gather``: a seed-stacked tree back on the host as numpy, every seed on every process.
- ``one_seed`` takes one seed out of such a tree as numpy (for export, the hall of fame, the
  end-of-run report, the Python API); ``take`` is the same slice of the leading axis without
  the host copy, usable under ``jit`` (a phase's i-th drawn policy in meta-RL collection).

The seeds' keys are ``keys.seed_keys``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import numpy as np

from espl_jax.config import UserError


def take(tree: Any, i: Any) -> Any:
    """Every leaf's entry ``i`` of its leading axis (``x[i]``); traceable."""
    return jax.tree.map(lambda x: x[i], tree)


def one_seed(tree: Any, s: int) -> Any:
    """Seed ``s`` of a seed-stacked tree, every leaf a numpy array (``np.asarray(x[s])``)."""
    return jax.tree.map(np.asarray, take(tree, s))


def gather(tree: Any) -> Any:
    """Numpy copies of a pytree's arrays, every seed on every process.

    In a multi-process run (``--distributed``) an array sharded over other hosts' devices is
    all-gathered first; that is a collective, so every process must call this at the same point.
    In one process it is ``jax.device_get``.
    """
    leaves, treedef = jax.tree.flatten(tree)
    remote = [
        i for i, x in enumerate(leaves) if isinstance(x, jax.Array) and not x.is_fully_addressable
    ]
    if remote:
        from jax.experimental import multihost_utils

        gathered = multihost_utils.process_allgather([leaves[i] for i in remote], tiled=True)
        for i, value in zip(remote, gathered, strict=True):
            leaves[i] = value
    return jax.tree.unflatten(treedef, [np.asarray(x) for x in jax.device_get(leaves)])


@dataclass(frozen=True)
class SeedAxis:
    """``seeds`` seeds over at most ``devices`` devices (0: as many as divide ``seeds``).

    Attributes:
        seeds: ``config.seeds``.
        devices: ``config.devices``.
    """

    seeds: int
    devices: int

    @cached_property
    def mesh(self) -> jax.sharding.Mesh | None:
        """A one-axis mesh ("seeds") over the devices the seed axis is split across, or None
        for one device. ``devices: 0`` takes the most of ``jax.devices()`` (every host's, after
        ``jax.distributed.initialize()``) that divides ``seeds``."""
        available = jax.devices()
        wanted = self.devices or len(available)
        if wanted > len(available):
            raise UserError(f"devices: {wanted} asked for, {len(available)} available")
        n = max(d for d in range(1, wanted + 1) if self.seeds % d == 0)
        if n == 1:
            return None
        return jax.sharding.Mesh(np.asarray(available[:n]), ("seeds",))

    def place(self, state: Any) -> Any:
        """Shard a seed-stacked pytree over ``mesh`` (each device holds whole seeds); jit then
        runs the vmapped chunk SPMD, one device's seeds per device, with no communication."""
        if self.mesh is None:
            return state
        sharding = jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec("seeds"))
        return jax.device_put(state, sharding)

    def over_seeds(self, fn, donate: bool = False, shared: tuple[int, ...] = ()):
        """``fn`` of one seed, jitted and vmapped over the leading seed axis of every argument
        but those at the positions ``shared`` (the same for every seed, e.g. task params).

        With a mesh it is ``shard_map``-ped: each device vmaps ``fn`` over its own seeds, with
        no communication between devices (the shared arguments are replicated). A seed computes
        what it computes on one device up to the last bit of rounding (XLA compiles the
        per-device program apart, and its matrix products round differently:
        tests/test_sharding.py).
        """

        def batched(*args):
            per_seed = [i not in shared for i in range(len(args))]
            mapped = jax.vmap(fn, in_axes=tuple(0 if p else None for p in per_seed))
            if self.mesh is None:
                return mapped(*args)
            seeds, replicated = jax.sharding.PartitionSpec("seeds"), jax.sharding.PartitionSpec()
            specs = tuple(seeds if p else replicated for p in per_seed)
            return jax.shard_map(
                mapped, mesh=self.mesh, in_specs=specs, out_specs=seeds, check_vma=False
            )(*args)

        return jax.jit(batched, donate_argnums=0 if donate else ())

    @property
    def device_info(self) -> dict[str, Any]:
        """eval.json's ``devices``: how many devices the seeds ran on, and of what platform."""
        devices = self.mesh.devices.ravel() if self.mesh is not None else jax.devices()[:1]
        info = {"count": len(devices), "platform": devices[0].platform}
        if jax.process_count() > 1:  # a --distributed run: the devices span these processes
            info["processes"] = len({d.process_index for d in devices})
        return info
