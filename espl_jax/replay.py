"""Replay buffers as pure functions over a pytree, with a leading task axis.

One ``ReplayBuffer`` holds every task's transitions: ``data`` leaves are [T, capacity, ...],
``position`` and ``size`` are [T] (the fill counts live inside the struct). A single-task run is
T = 1. PEARL's per-task RL buffers and encoder buffers (docs/design.md "State") are two such
structs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Transition:
    """One transition, or a batch of them on leading axes.

    ``terminated`` marks a true end (no bootstrap); time-limit truncation is not stored, so the
    critic bootstraps through it (gymnax 1.0 / brax convention).
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    terminated: jax.Array


@struct.dataclass
class ReplayBuffer:
    data: Transition  # arrays [tasks, capacity, ...]
    position: jax.Array  # int32 [tasks], next write index
    size: jax.Array  # int32 [tasks], number of valid entries

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[-1]


def init(tasks: int, capacity: int, obs_dim: int, action_dim: int) -> ReplayBuffer:
    data = Transition(
        obs=jnp.zeros((tasks, capacity, obs_dim)),
        action=jnp.zeros((tasks, capacity, action_dim)),
        reward=jnp.zeros((tasks, capacity)),
        next_obs=jnp.zeros((tasks, capacity, obs_dim)),
        terminated=jnp.zeros((tasks, capacity), bool),
    )
    zeros = jnp.zeros((tasks,), jnp.int32)
    return ReplayBuffer(data, zeros, zeros)


def insert(buffer: ReplayBuffer, tasks: jax.Array, batch: Transition) -> ReplayBuffer:
    """Append ``batch`` [R, n, ...] to the buffers of the R *distinct* ``tasks`` [R], FIFO.

    Rows wrap around the end of a task's buffer, overwriting its oldest entries.
    """
    n = batch.reward.shape[1]
    capacity = buffer.capacity
    rows = (buffer.position[tasks][:, None] + jnp.arange(n)) % capacity  # [R, n]
    data = jax.tree.map(
        lambda store, new: store.at[tasks[:, None], rows].set(new), buffer.data, batch
    )
    return ReplayBuffer(
        data,
        buffer.position.at[tasks].set((buffer.position[tasks] + n) % capacity),
        buffer.size.at[tasks].set(jnp.minimum(buffer.size[tasks] + n, capacity)),
    )


def clear(buffer: ReplayBuffer, tasks: jax.Array) -> ReplayBuffer:
    """Empty the buffers of ``tasks`` (PEARL clears a task's encoder buffer on each visit)."""
    return buffer.replace(
        position=buffer.position.at[tasks].set(0), size=buffer.size.at[tasks].set(0)
    )


def sample(buffer: ReplayBuffer, tasks: jax.Array, keys: jax.Array, n: int) -> Transition:
    """``n`` transitions per task of ``tasks`` [B], uniformly with replacement among the valid
    entries (as rlkit does), one key per task: a batch [B, n, ...]."""

    def one(task, key):
        idx = jax.random.randint(key, (n,), 0, jnp.maximum(buffer.size[task], 1))
        return jax.tree.map(lambda x: x[task, idx], buffer.data)

    return jax.vmap(one)(tasks, keys)


def capacity_for(requested: int, chunk: int) -> int:
    """Smallest multiple of ``chunk`` that holds ``requested`` transitions."""
    return -(-requested // chunk) * chunk


def resize(buffer: ReplayBuffer, capacity: int) -> ReplayBuffer:
    """The same transitions in buffers of another capacity (zero-padded or cut at the end).

    Exact only for buffers that have not wrapped (entries are rows 0 … size−1, oldest first)
    and fit: a run extended by ``--resume --iterations`` then holds exactly what a run planned
    that long holds at the same iteration. The trainer sizes a single-task buffer by the run's
    total env steps (capped by ``buffer_size``), so a buffer whose capacity depends on
    ``iterations`` never wraps.
    """
    old = buffer.capacity

    def fit(x):
        if capacity <= old:
            return x[:, :capacity]
        pad = jnp.zeros((x.shape[0], capacity - old, *x.shape[2:]), x.dtype)
        return jnp.concatenate([x, pad], axis=1)

    size = jnp.minimum(buffer.size, capacity)
    return ReplayBuffer(jax.tree.map(fit, buffer.data), size % capacity, size)
