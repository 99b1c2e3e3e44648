"""The learner: one ``Trainer`` for ESPL (Algorithm 1) and CSP, PEARL and Hyper (Algorithm 2).

The library side of training (``python -m espl_jax.train`` is the command line, ``espl_jax.run``
the loop that writes a run directory). The ``Trainer`` says what is trained — the env, the task
set, the policy kind, PEARL's encoder, the SAC update, the initial state — and compiles the
programs the host loop runs, each ``vmap``-ed over seeds. The rest lives by concern:

- ``espl_jax.task_sets``: the tasks and the collection on them; a single-task env is the
  one-task, no-context case (T = 1 task, a (0,)-sized latent, no encoder), a meta-RL family
  gives T = ``n_train`` tasks, a latent z from PEARL's encoder and per-task buffers.
- ``espl_jax.iteration``: one iteration (schedules, collection, ``updates_per_iteration`` SAC
  steps) and a chunk of them (a ``lax.scan`` over iterations), pure functions of the state.
- ``espl_jax.seeds``: the seed axis over devices and hosts (mesh, ``shard_map``, ``gather``).
- ``espl_jax.rollout``: collection, evaluation and PEARL's protocol, for every env.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import envs, pearl, replay, rollout
from espl_jax.config import Config, UserError, view
from espl_jax.iteration import Iteration
from espl_jax.keys import seed_keys
from espl_jax.policies import META_ACTORS, SINGLE_TASK_ACTORS, Actor, make_actor, no_latent
from espl_jax.sac import SAC, SACConfig, TrainState, task_keys
from espl_jax.seeds import SeedAxis
from espl_jax.task_sets import TaskSet, task_set


def resolve_physics(physics: str) -> str:
    """The MuJoCo backend ``physics`` names: ``auto`` is MuJoCo's C engine when JAX computes on
    the CPU (MJX is several times slower there) and MJX on an accelerator."""
    if physics == "auto":
        return "native" if jax.default_backend() == "cpu" else "mjx"
    return physics


def make_env(name: str, physics: str = "mjx"):
    """``envs.make`` / ``envs.make_family`` with the unknown-name error turned into a user error.

    Args:
        name: an env or a task family.
        physics: the backend of a MuJoCo env or family (``envs.PHYSICS``); others ignore it.

    Returns:
        ``(env, family)``: the env to step (for a family: its env with the family's horizon)
        and the ``TaskFamily``, or None for a single-task env.
    """
    kwargs = {"physics": physics} if name in envs.MUJOCO else {}
    try:
        if envs.is_family(name):
            family = envs.make_family(name, **kwargs)
            return family.env, family
        return envs.make(name, **kwargs), None
    except ValueError as err:
        raise UserError(str(err)) from None


@dataclass(frozen=True)
class Trainer:
    """Static description of a run: config, environment and algorithm. Hashable (jit-static)."""

    config: Config

    # What is trained ----------------------------------------------------------------------------

    @cached_property
    def _env_and_family(self):
        # Concrete arrays (MJX's put_model) even when first asked for inside a jit trace, as
        # ``benchmarks/meta_cost.py`` does: a cached tracer would leak into later traces.
        with jax.ensure_compile_time_eval():
            env, family = make_env(self.config.env, resolve_physics(self.config.physics))
        if self.config.physics != "auto" and self.config.env not in envs.MUJOCO:
            raise UserError(
                f"physics: {self.config.physics} applies to the MuJoCo tasks only, and "
                f"{self.config.env} is not one; leave physics at auto"
            )
        kinds = META_ACTORS if family is not None else SINGLE_TASK_ACTORS
        if self.config.actor not in kinds:
            what = "meta-RL task family" if family is not None else "single-task env"
            raise UserError(
                f"--actor {self.config.actor} does not apply to {self.config.env}, a {what}; "
                f"choose one of {', '.join(kinds)}"
            )
        return env, family

    @property
    def env(self):
        return self._env_and_family[0]

    @property
    def family(self):
        """The ``envs.TaskFamily`` of a meta-RL run, else None."""
        return self._env_and_family[1]

    @property
    def physics(self) -> str | None:
        """The MuJoCo backend this run steps (``"native"`` or ``"mjx"``), None for other envs."""
        if self.config.env not in envs.MUJOCO:
            return None
        return resolve_physics(self.config.physics)

    @property
    def meta(self) -> bool:
        return self.family is not None

    @cached_property
    def task_set(self) -> TaskSet:
        """The tasks trained on and the collection on them (``espl_jax.task_sets``)."""
        return task_set(self.config, self.env, self.family)

    @property
    def tasks(self) -> tuple[Any, Any]:
        """(train, test) task params with a leading task axis. Single-task: the env's default
        params, once, as both."""
        return self.task_set.params

    @cached_property
    def actor(self) -> Actor:
        latent_dim = self.task_set.latent_dim
        return make_actor(self.config, self.env.obs_dim, self.env.action_dim, latent_dim)

    @property
    def encoder(self) -> pearl.Encoder | None:
        return self.task_set.encoder

    @cached_property
    def sac(self) -> SAC:
        return SAC(view(SACConfig, self.config), self.actor, self.task_set)

    @cached_property
    def iteration(self) -> Iteration:
        """One iteration, ``trainer.iteration(state) -> (state, metrics)``, and its parts."""
        cfg = self.config
        return Iteration(
            tasks=self.task_set,
            sac=self.sac,
            updates_per_iteration=cfg.updates_per_iteration,
            schedule_iterations=cfg.schedule_iterations,
            target_temperature=cfg.target_temperature,
            target_l0_ratio=cfg.target_l0_ratio,
            finetune=cfg.finetune,
        )

    # State ---------------------------------------------------------------------------------

    def init(self, key: jax.Array) -> TrainState:
        """A fresh TrainState for one seed. ``key`` is a raw uint32[2] key (checkpointable)."""
        env, tasks = self.env, self.task_set
        key, k_learner, k_reset = jax.random.split(key, 3)
        slots = tasks.rollout_slots
        params = jax.tree.map(lambda x: x[:slots], tasks.params[0])
        state = jax.vmap(lambda k, p: rollout.reset(env, p, k, env.action_dim))(
            task_keys(k_reset, slots), params
        )
        zero_i = jnp.zeros((), jnp.int32)
        learner = self.sac.init_learner(k_learner)
        anchor = {}
        if self.actor.one_formula:  # the hall of fame's anchor (espl_jax.halloffame)
            anchor = dict(
                anchor=learner["actor"],
                anchor_return=jnp.asarray(-jnp.inf),
                anchor_iteration=jnp.asarray(-1, jnp.int32),
            )
        return TrainState(
            **learner,
            **anchor,
            buffer=replay.init(tasks.num_train, tasks.buffer_capacity, env.obs_dim, env.action_dim),
            encoder_buffer=tasks.encoder_buffer(env.obs_dim, env.action_dim),
            rollout=state,
            key=key,
            iteration=zero_i,
            env_steps=zero_i,
            episodes=zero_i,
        )

    @cached_property
    def seed_axis(self) -> SeedAxis:
        """The seeds over the devices (``espl_jax.seeds``)."""
        return SeedAxis(self.config.seeds, self.config.devices)

    def seed_keys(self) -> jax.Array:
        """[S, 2]: seed i of a ``--seeds S --seed K`` run is ``PRNGKey(K + i)``, the key of a
        one-seed ``--seed K+i`` run. (Its training rounds differently under vmap, and RL
        amplifies that: the keys are the single run's, the returns another draw.)"""
        return seed_keys(self.config.seed, self.config.seeds)

    def init_seeds(self) -> TrainState:
        """States for ``config.seeds`` seeds stacked on a leading axis (sharded, see ``place``)."""
        axis = self.seed_axis
        return axis.over_seeds(self.init)(axis.place(self.seed_keys()))

    def warmup(self, state: TrainState) -> TrainState:
        """Before the first iteration: the task set's warmup (PEARL's ``num_initial_steps``
        prior-z steps on every training task; none for a single task)."""
        return self.task_set.warmup(self.actor, state)

    # Compiled programs, vmapped over seeds ------------------------------------------------------

    def compiled_warmup(self):
        """jit(vmap(warmup)) over seeds; the state buffers are donated."""
        return self.seed_axis.over_seeds(self.warmup, donate=True)

    def compiled_chunk(self, length: int):
        """jit(vmap(chunk)) over the leading seed axis; the state buffers are donated."""
        return self.seed_axis.over_seeds(lambda s: self.iteration.chunk(s, length), donate=True)

    def compiled_evaluate(self, episodes: int):
        """jit(vmap(evaluate)) over seeds: (actor params [S, ...], keys [S, 2]) -> [S, E]:
        single task, deterministic episodes of each seed's exported formula."""
        env, actor, params = self.env, self.actor, jax.tree.map(lambda x: x[0], self.tasks[0])
        return self.seed_axis.over_seeds(
            lambda p, k: rollout.evaluate_learned(env, actor, p, params, k, episodes)
        )

    def adapt(self, state: TrainState, task_params: Any, key: jax.Array) -> rollout.Adapted:
        """Meta-RL: PEARL's protocol, ``eval_runs`` runs on each task of ``task_params`` [N]:
        an ``Adapted`` with leaves [N, runs]."""
        cfg = self.config

        def one(p, k):
            return rollout.adapt_and_evaluate(
                self.env, self.actor, self.encoder, state.actor, state.encoder, p, k,
                cfg.eval_steps, cfg.eval_exploration_trajectories,
            )  # fmt: skip

        return rollout.runs_on_tasks(one, task_params, key, cfg.eval_runs)

    @cached_property
    def compiled_adapt(self):
        """jit(vmap(adapt)) over seeds: (state [S], task params [N], keys [S, 2]) -> Adapted
        [S, N, runs]. The tasks are an argument, not a constant, so the progress evaluations and
        the final one on the test tasks and on as many training tasks share one compile (minutes
        for the MJX families)."""
        return self.seed_axis.over_seeds(self.adapt, shared=(1,))

    def task_policy(self, actor_params: dict, z: np.ndarray | None) -> dict:
        """The task policy at z (numpy), for export: ESPL's own params, CSP's Φ/Ψ at z."""
        z = no_latent() if z is None else jnp.asarray(z)
        return jax.tree.map(np.asarray, self.actor.at(actor_params, z))
