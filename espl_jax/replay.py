"""Replay buffers as pure functions over a pytree, with a leading task axis.

One ``ReplayBuffer`` holds every task's transitions: ``data`` leaves are [T, capacity, ...],
``position`` and ``size`` are [T] (the fill counts live inside the struct). A single-task run is
T = 1. PEARL's per-task RL buffers and encoder buffers (DESIGN "Meta-RL") are two such structs.
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


def sample_n_step(
    buffer: ReplayBuffer, tasks: jax.Array, keys: jax.Array, n: int, steps: int, gamma: float
) -> tuple[Transition, jax.Array]:
    """Like ``sample``, but each transition is an up-to-``steps``-step one: from a uniformly drawn
    start, the rewards of the entries that follow it in the same episode are summed with
    discounts γ^k, ``next_obs`` and ``terminated`` are the last used entry's, and the returned
    discount [B, n] is γ^m for the m ≤ ``steps`` entries used (the critic's target is then
    Σ γ^k r_k + γ^m (1 − terminated) V(s_m), the n-step return; the intermediate entropy terms
    are left out, as is usual for n-step SAC).

    An entry continues the previous one when it was written after it, the previous one did not
    terminate, and its ``obs`` is exactly the previous ``next_obs``: a reset (termination,
    truncation, a new collection phase) always breaks that equality, so no episode flags are
    stored. Starts near the newest entry use fewer steps.
    """
    offsets = jnp.arange(steps)

    def one(task, key):
        size, head, capacity = buffer.size[task], buffer.position[task], buffer.capacity
        idx = jax.random.randint(key, (n,), 0, jnp.maximum(size, 1))
        rows = (idx[:, None] + offsets) % capacity  # [n, steps]
        d = jax.tree.map(lambda x: x[task, rows], buffer.data)
        newer = (head - 1 - idx) % capacity  # entries written after idx
        follows = (
            jnp.all(d.obs[:, 1:] == d.next_obs[:, :-1], axis=-1)
            & ~d.terminated[:, :-1]
            & (offsets[1:] <= newer[:, None])
        )
        used = jnp.cumprod(jnp.concatenate([jnp.ones((n, 1), bool), follows], axis=1), axis=1)
        used = used.astype(d.reward.dtype)  # [n, steps], 1 then 0 once the chain breaks
        last = jnp.sum(used, axis=1).astype(jnp.int32) - 1
        pick = jnp.arange(n)
        batch = Transition(
            obs=d.obs[:, 0],
            action=d.action[:, 0],
            reward=jnp.sum(used * gamma**offsets * d.reward, axis=1),
            next_obs=d.next_obs[pick, last],
            terminated=d.terminated[pick, last],
        )
        return batch, gamma ** (last + 1).astype(d.reward.dtype)

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
