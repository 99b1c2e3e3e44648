"""Replay buffer as pure functions over a pytree (the fill count lives inside the struct)."""

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
    data: Transition  # arrays with leading axis ``capacity``
    position: jax.Array  # int32, next write index
    size: jax.Array  # int32, number of valid entries

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[0]


def init(capacity: int, obs_dim: int, action_dim: int) -> ReplayBuffer:
    data = Transition(
        obs=jnp.zeros((capacity, obs_dim)),
        action=jnp.zeros((capacity, action_dim)),
        reward=jnp.zeros((capacity,)),
        next_obs=jnp.zeros((capacity, obs_dim)),
        terminated=jnp.zeros((capacity,), bool),
    )
    return ReplayBuffer(data, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))


def insert(buffer: ReplayBuffer, batch: Transition) -> ReplayBuffer:
    """Write a batch of ``n`` transitions at the write position, overwriting the oldest.

    The trainer sizes the capacity as a multiple of ``n`` so a batch never straddles the end.
    """
    n = batch.reward.shape[0]
    capacity = buffer.capacity
    data = jax.tree.map(
        lambda store, new: jax.lax.dynamic_update_slice_in_dim(store, new, buffer.position, 0),
        buffer.data,
        batch,
    )
    return ReplayBuffer(
        data, (buffer.position + n) % capacity, jnp.minimum(buffer.size + n, capacity)
    )


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Transition:
    """Uniform sample with replacement among the valid entries (as rlkit does)."""
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree.map(lambda x: x[idx], buffer.data)


def capacity_for(requested: int, chunk: int) -> int:
    """Smallest multiple of ``chunk`` that holds ``requested`` transitions."""
    return -(-requested // chunk) * chunk


def resize(buffer: ReplayBuffer, capacity: int) -> ReplayBuffer:
    """The same transitions in a buffer of another capacity (zero-padded or cut at the end).

    Exact only for a buffer that has not wrapped (its entries are rows 0 … size−1, oldest first)
    and fits: a run extended by ``--resume --iterations`` then holds exactly what a run planned
    that long holds at the same iteration. The trainer sizes a buffer by the run's total env steps
    (capped by ``buffer_size``), so a buffer whose capacity depends on ``iterations`` never wraps.
    """
    old = buffer.capacity

    def fit(x):
        if capacity <= old:
            return x[:capacity]
        return jnp.concatenate([x, jnp.zeros((capacity - old, *x.shape[1:]), x.dtype)])

    size = jnp.minimum(buffer.size, capacity)
    return ReplayBuffer(jax.tree.map(fit, buffer.data), size % capacity, size)
