"""One training iteration, and a chunk of them, as pure functions of the ``TrainState``
(Algorithm 1 lines 3–18, Algorithm 2 lines 3–30; docs/design.md "One trainer"):

1. τ and l_min from the schedules (Algorithm 1 lines 3, 8); from t_s on, with ``finetune``,
   ESPL's path probabilities frozen to the exported mask.
2. Collection on the task set (``espl_jax.task_sets``: ESPL's one mask and K steps, or PEARL's
   prior and posterior phases).
3. ``updates_per_iteration`` SAC steps in one ``lax.scan`` (``espl_jax.sac``).

A *chunk* is a ``lax.scan`` over iterations; the trainer compiles it once, ``vmap``-ed over seeds
(``espl_jax.seeds``), and the host runs between chunks (``espl_jax.run``).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from espl_jax import rollout, selector
from espl_jax.sac import SAC, Metrics, TrainState
from espl_jax.task_sets import TaskSet


@dataclass(frozen=True)
class Iteration:
    """One iteration of Algorithm 1 or 2: ``iteration(state) -> (state, metrics)``.

    Attributes:
        tasks: where experience is collected.
        sac: the update (its ``actor`` is the policy kind that acts).
        updates_per_iteration: SAC steps per iteration.
        schedule_iterations: t_s, the iterations of the τ and l_min schedules.
        target_temperature, target_l0_ratio: where the schedules end.
        finetune: ESPL's fine-tune phase (frozen mask from t_s on) where the kind has one.
    """

    tasks: TaskSet
    sac: SAC
    updates_per_iteration: int
    schedule_iterations: int
    target_temperature: float
    target_l0_ratio: float
    finetune: bool

    def schedules(self, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(τ, l_min) at iteration t (Algorithm 1, lines 3 and 8)."""
        tau = selector.temperature(t, self.schedule_iterations, self.target_temperature)
        l_min = selector.l_min_schedule(t, self.schedule_iterations, self.target_l0_ratio)
        return tau, l_min

    @property
    def finetunes(self) -> bool:
        """ESPL's fine-tune phase applies (``finetune`` and a learned p to freeze)."""
        return self.finetune and self.sac.actor.freezes_mask

    def frozen(self, iteration: jax.Array) -> jax.Array | None:
        """Whether the mask is frozen at this iteration (None when there is no fine-tuning)."""
        if not self.finetunes:
            return None
        return iteration >= self.schedule_iterations

    def freeze_mask(self, actor_params: dict, iteration: jax.Array) -> dict:
        """From t_s on, p := the exported mask (0/1); idempotent, so applied every iteration."""
        if not self.finetunes:
            return actor_params
        frozen = self.sac.actor.freeze(actor_params)
        return rollout.where(self.frozen(iteration), frozen, actor_params)

    def learn(
        self, state: TrainState, collect_metrics: Metrics, key: jax.Array
    ) -> tuple[TrainState, Metrics]:
        """The rest of an iteration after collection: ``updates_per_iteration`` SAC steps in one
        scan (Algorithm 1, lines 8–17; Algorithm 2, lines 13–30), counted."""
        tau, l_min = self.schedules(state.iteration)
        frozen = self.frozen(state.iteration)

        def update(s, k):
            return self.sac.update(s, k, tau, l_min, frozen)

        keys = jax.random.split(key, self.updates_per_iteration)
        state, u_metrics = jax.lax.scan(update, state, keys)
        state = state.replace(iteration=state.iteration + 1)
        u_metrics = jax.tree.map(jnp.mean, u_metrics)
        batch_l0 = u_metrics.pop("batch_l0_ratio")
        metrics = {
            **collect_metrics,
            **u_metrics,
            "tau": tau,
            "l_min": l_min,
            "l0_ratio": self.tasks.l0_ratio(self.sac.actor, state.actor, batch_l0),
            "env_steps": state.env_steps,
            "episodes": state.episodes,
            "iteration": state.iteration,
        }
        return state, metrics

    def __call__(self, state: TrainState) -> tuple[TrainState, Metrics]:
        """One iteration of Algorithm 1 or 2 in JAX (collection, then ``learn``)."""
        state = state.replace(actor=self.freeze_mask(state.actor, state.iteration))
        state, collect_metrics, k_update = self.tasks.collect(self.sac.actor, state)
        return self.learn(state, collect_metrics, k_update)

    def chunk(self, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
        """``length`` iterations in one scan, for one seed."""
        return jax.lax.scan(lambda s, _: self(s), state, None, length=length)
