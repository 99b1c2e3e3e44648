"""The learner: one ``Trainer`` for ESPL (Algorithm 1) and CSP, PEARL and Hyper (Algorithm 2).

The library side of training (``python -m espl_jax.train`` is the command line, ``espl_jax.run``
the loop that writes a run directory).

A single-task env is the one-task, no-context case: T = 1 task (the env's default params), a
(0,)-sized latent, no encoder. A meta-RL task family gives T = ``n_train`` training tasks, a
latent z from PEARL's encoder, and per-task buffers. One *iteration*:

1. τ and l_min from the schedules (Algorithm 1 lines 3, 8).
2. Collection (``collect``). ESPL: one Bernoulli mask (line 4), ``steps_per_iteration`` steps on
   the task, episodes continuing across iterations. Meta-RL (PEARL's ``rl_algorithm``):
   ``tasks_per_iteration`` distinct training tasks; each has its encoder buffer cleared, then a
   prior phase (``prior_steps``, z ~ N(0, I) per trajectory, into both buffers) and a posterior
   phase (``posterior_steps``, z from the posterior of a context drawn from the fresh encoder
   buffer, per trajectory, into the RL buffer only). CSP draws a Bernoulli mask of σ(Ψ(z)) with
   every z. Before the first iteration ``warmup`` fills every training task with
   ``initial_steps`` prior-z steps (both buffers).
3. ``updates_per_iteration`` SAC steps in one ``lax.scan`` (``espl_jax.sac``).

A *chunk* is a ``lax.scan`` over iterations, compiled once and ``vmap``-ed over seeds; the host
runs between chunks (``espl_jax.run``). Every env steps through the same collection, evaluation
and protocol (``espl_jax.rollout``): the JAX envs inside the program, the host-stepped ones
(MuJoCo's C engine, gymnasium's Box2D) through one host callback per env step for the batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import envs, pearl, replay, rollout, selector
from espl_jax.config import Config, UserError
from espl_jax.keys import POSTERIOR_DRAW, seed_keys
from espl_jax.policies import META_ACTORS, SINGLE_TASK_ACTORS, Actor, make_actor
from espl_jax.rollout import Rollout
from espl_jax.sac import SAC, Metrics, TrainState, task_keys
from espl_jax.seeds import take


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


def _stack(params: Any) -> Any:
    """A batch of one task: every leaf gets a leading axis of 1."""
    return jax.tree.map(lambda x: np.asarray(x)[None], params)


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
    def tasks(self) -> tuple[Any, Any]:
        """(train, test) task params with a leading task axis. Single-task: the env's default
        params, once, as both."""
        # Concrete numpy arrays even when first asked for inside a jit trace (cached_property).
        with jax.ensure_compile_time_eval():
            if self.meta:
                train, test = self.family.tasks(self.config.task_seed)
                return jax.tree.map(np.asarray, train), jax.tree.map(np.asarray, test)
            params = _stack(self.env.default_params)
        return params, params

    @property
    def num_train_tasks(self) -> int:
        return self.family.n_train if self.meta else 1

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim if self.meta else 0

    @cached_property
    def actor(self) -> Actor:
        return make_actor(self.config, self.env.obs_dim, self.env.action_dim, self.latent_dim)

    @cached_property
    def encoder(self) -> pearl.Encoder | None:
        if not self.meta:
            return None
        use_next = self.family.use_next_obs_in_context
        cfg = self.config
        return pearl.Encoder(cfg.encoder_hidden, cfg.latent_dim, use_next, cfg.posterior_var_floor)

    @cached_property
    def sac(self) -> SAC:
        return SAC(self.config, self.actor, self.encoder, self.num_train_tasks)

    @property
    def rollout_slots(self) -> int:
        """Tasks collected on at once: the single task, or ``tasks_per_iteration``."""
        return min(self.config.tasks_per_iteration, self.num_train_tasks) if self.meta else 1

    @property
    def steps_per_iteration(self) -> int:
        cfg = self.config
        if not self.meta:
            return cfg.steps_per_iteration
        return self.rollout_slots * (cfg.prior_steps + cfg.posterior_steps)

    @property
    def buffer_capacity(self) -> int:
        cfg = self.config
        if self.meta:
            return cfg.task_buffer_size
        wanted = min(cfg.buffer_size, cfg.iterations * cfg.steps_per_iteration)
        return replay.capacity_for(wanted, cfg.steps_per_iteration)

    # State ---------------------------------------------------------------------------------

    def init(self, key: jax.Array) -> TrainState:
        """A fresh TrainState for one seed. ``key`` is a raw uint32[2] key (checkpointable)."""
        cfg, env = self.config, self.env
        key, k_learner, k_reset = jax.random.split(key, 3)
        slots = self.rollout_slots
        params = jax.tree.map(lambda x: x[:slots], self.tasks[0])
        state = jax.vmap(lambda k, p: rollout.reset(env, p, k, env.action_dim))(
            task_keys(k_reset, slots), params
        )
        tasks = self.num_train_tasks
        encoder_buffer = None
        if self.meta:
            capacity = max(cfg.initial_steps, cfg.prior_steps)
            encoder_buffer = replay.init(tasks, capacity, env.obs_dim, env.action_dim)
        zero_i = jnp.zeros((), jnp.int32)
        learner = self.sac.init_learner(k_learner)
        anchor = {}
        if not self.meta and self.actor.symbolic is not None:
            anchor = dict(
                anchor=learner["actor"],
                anchor_return=jnp.asarray(-jnp.inf),
                anchor_iteration=jnp.asarray(-1, jnp.int32),
            )
        return TrainState(
            **learner,
            **anchor,
            buffer=replay.init(tasks, self.buffer_capacity, env.obs_dim, env.action_dim),
            encoder_buffer=encoder_buffer,
            rollout=state,
            key=key,
            iteration=zero_i,
            env_steps=zero_i,
            episodes=zero_i,
        )

    def seed_keys(self) -> jax.Array:
        """[S, 2]: seed i of a ``--seeds S --seed K`` run is ``PRNGKey(K + i)``, the key of a
        one-seed ``--seed K+i`` run. (Its training rounds differently under vmap, and RL
        amplifies that: the keys are the single run's, the returns another draw.)"""
        return seed_keys(self.config.seed, self.config.seeds)

    def init_seeds(self) -> TrainState:
        """States for ``config.seeds`` seeds stacked on a leading axis (sharded, see ``place``)."""
        return self.over_seeds(self.init)(self.place(self.seed_keys()))

    @cached_property
    def mesh(self) -> jax.sharding.Mesh | None:
        """A one-axis mesh ("seeds") over the devices the seed axis is split across, or None
        for one device. ``devices: 0`` takes the most of ``jax.devices()`` (every host's, after
        ``jax.distributed.initialize()``) that divides ``seeds``."""
        available = jax.devices()
        wanted = self.config.devices or len(available)
        if wanted > len(available):
            raise UserError(f"devices: {wanted} asked for, {len(available)} available")
        n = max(d for d in range(1, wanted + 1) if self.config.seeds % d == 0)
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
        devices = self.mesh.devices.ravel() if self.mesh is not None else jax.devices()[:1]
        info = {"count": len(devices), "platform": devices[0].platform}
        if jax.process_count() > 1:  # a --distributed run: the devices span these processes
            info["processes"] = len({d.process_index for d in devices})
        return info

    # Collection -----------------------------------------------------------------------------

    def _collect(self, r, task_params, actor_params, part, mask, key, steps, draw=None):
        return rollout.collect(
            self.env, self.actor, self.config.exploration_correlation,
            r, task_params, actor_params, part, mask, key, steps, draw,
        )  # fmt: skip

    def start_iteration(self, key: jax.Array, actor_params: dict):
        """ESPL's iteration randomness: (next state key, Bernoulli mask, collect key, update
        key). The mask is Algorithm 1, line 4; one mask serves the whole collection."""
        key, k_mask, k_collect, k_update = jax.random.split(key, 4)
        policy = self.actor.at(actor_params, jnp.zeros((0,)))
        return key, self.actor.collect_mask(k_mask, policy), k_collect, k_update

    def record_collection(
        self,
        state: TrainState,
        *,
        rollout_state: Rollout,
        done: jax.Array,
        finished_returns: jax.Array,
        steps: int,
    ) -> tuple[TrainState, Metrics]:
        """The state and metrics after collection; ``done`` and ``finished_returns`` cover every
        collected step (any shape)."""
        finished = jnp.sum(done)
        state = state.replace(
            rollout=rollout_state,
            env_steps=state.env_steps + steps,
            episodes=state.episodes + finished,
        )
        metrics = {
            "episodes_finished": finished,
            "train_return": jnp.sum(finished_returns) / jnp.maximum(finished, 1),
        }
        return state, metrics

    def collect_single(self, state: TrainState, mask: Any, key: jax.Array):
        """ESPL: K steps on the one task with one fixed mask (Algorithm 1, lines 5–7)."""
        no_z = jnp.zeros((0,))
        steps = self.config.steps_per_iteration
        r, transitions, done, finished = jax.vmap(
            lambda r, p, k: self._collect(r, p, state.actor, no_z, mask, k, steps)
        )(state.rollout, self.tasks[0], task_keys(key, 1))
        one_task = jnp.zeros(1, jnp.int32)
        state = state.replace(buffer=replay.insert(state.buffer, one_task, transitions))
        return self.record_collection(
            state, rollout_state=r, done=done, finished_returns=finished, steps=steps
        )

    # Trajectories a collection phase draws a z for; a phase with more episodes reuses them in
    # turn (only very short episodes, early in training, get there: 32 × 12 steps ≥ 400).
    DRAWS_PER_PHASE = 32

    def draws(self, params: dict, mu: jax.Array, var: jax.Array, key: jax.Array):
        """The policies of a phase's trajectories, drawn up front: ``DRAWS_PER_PHASE`` latents
        z ~ N(mu, var), their generated parts and (CSP) Bernoulli masks of σ(Ψ(z)), so the
        (hyper)networks that generate a policy run once per trajectory, not at every step."""
        k_z, k_mask = jax.random.split(key)
        n = self.DRAWS_PER_PHASE
        z = mu + jnp.sqrt(var) * jax.random.normal(k_z, (n, mu.shape[-1]))
        parts = jax.vmap(self.actor.generate, (None, 0))(params, z)
        masks = jax.vmap(lambda k, p: self.actor.collect_mask(k, self.actor.policy(params, p)))(
            jax.random.split(k_mask, n), parts
        )
        return parts, masks

    def _draw(self, params: dict, mu: jax.Array, var: jax.Array, key: jax.Array):
        """draw(i) -> (policy part, mask) of the i-th trajectory of a phase (``draws``)."""
        parts, masks = self.draws(params, mu, var, key)
        n = self.DRAWS_PER_PHASE

        def draw(i):
            return take((parts, masks), i % n)

        return draw

    def phase_latents(self, state: TrainState, tasks: jax.Array, key: jax.Array, posterior: bool):
        """(mu, var) [R, L] the phase's z are drawn from: the prior N(0, I), or the posterior of a
        context drawn from each task's (fresh) encoder buffer."""
        n = tasks.shape[0]
        if not posterior:
            return jnp.zeros((n, self.latent_dim)), jnp.ones((n, self.latent_dim))
        context = replay.sample(
            state.encoder_buffer, tasks, jax.random.split(key, n), self.config.context_batch
        )
        return jax.vmap(self.encoder.posterior, (None, 0))(state.encoder, context)

    def _meta_phase(self, state, tasks, key, steps, posterior, to_encoder):
        """One PEARL collection phase on the distinct ``tasks`` [R]: reset, ``steps`` steps with
        a z per trajectory from the prior or (``posterior``) from q(z | fresh context)."""
        env = self.env
        n = tasks.shape[0]
        k_reset, k_context, k_collect = jax.random.split(key, 3)
        task_params = jax.tree.map(lambda x: jnp.asarray(x)[tasks], self.tasks[0])
        mu, var = self.phase_latents(state, tasks, k_context, posterior)

        def one(p, k_r, k_c, mu_t, var_t):
            r = rollout.reset(env, p, k_r, env.action_dim)
            draw = self._draw(state.actor, mu_t, var_t, jax.random.fold_in(k_c, POSTERIOR_DRAW))
            part, mask = draw(0)  # the first step draws it again; this fixes the carry's shape
            return self._collect(r, p, state.actor, part, mask, k_c, steps, draw)

        r, transitions, done, finished = jax.vmap(one)(
            task_params, jax.random.split(k_reset, n), jax.random.split(k_collect, n), mu, var
        )
        state = state.replace(buffer=replay.insert(state.buffer, tasks, transitions))
        if to_encoder:
            state = state.replace(
                encoder_buffer=replay.insert(state.encoder_buffer, tasks, transitions)
            )
        return state, r, done, finished

    def collect_meta(self, state: TrainState, key: jax.Array) -> tuple[TrainState, Metrics]:
        """PEARL's collection for one iteration (module docstring, step 2)."""
        cfg = self.config
        k_tasks, k_prior, k_posterior = jax.random.split(key, 3)
        tasks = jax.random.choice(
            k_tasks, self.num_train_tasks, (self.rollout_slots,), replace=False
        )
        state = state.replace(encoder_buffer=replay.clear(state.encoder_buffer, tasks))
        state, r, done, finished = self._meta_phase(
            state, tasks, k_prior, cfg.prior_steps, posterior=False, to_encoder=True
        )
        dones, returns = [done], [finished]
        if cfg.posterior_steps:
            state, r, done, finished = self._meta_phase(
                state, tasks, k_posterior, cfg.posterior_steps, posterior=True, to_encoder=False
            )
            dones.append(done)
            returns.append(finished)
        return self.record_collection(
            state,
            rollout_state=r,
            done=jnp.concatenate([d.ravel() for d in dones]),
            finished_returns=jnp.concatenate([f.ravel() for f in returns]),
            steps=self.steps_per_iteration,
        )

    def warmup(self, state: TrainState) -> TrainState:
        """Before the first iteration: ``initial_steps`` prior-z steps on every training task,
        into both buffers (PEARL's ``num_initial_steps``). Single-task runs have none."""
        if not self.meta or not self.config.initial_steps:
            return state
        key, k_warmup = jax.random.split(state.key)
        tasks = jnp.arange(self.num_train_tasks)
        state, r, done, _ = self._meta_phase(
            state.replace(key=key), tasks, k_warmup, self.config.initial_steps,
            posterior=False, to_encoder=True,
        )  # fmt: skip
        return state.replace(
            env_steps=state.env_steps + self.num_train_tasks * self.config.initial_steps,
            episodes=state.episodes + jnp.sum(done),
        )

    def compiled_warmup(self):
        """jit(vmap(warmup)) over seeds; the state buffers are donated."""
        return self.over_seeds(self.warmup, donate=True)

    # One iteration and a chunk of them --------------------------------------------------------

    def schedules(self, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(τ, l_min) at iteration t (Algorithm 1, lines 3 and 8)."""
        cfg = self.config
        tau = selector.temperature(t, cfg.schedule_iterations, cfg.target_temperature)
        l_min = selector.l_min_schedule(t, cfg.schedule_iterations, cfg.target_l0_ratio)
        return tau, l_min

    def learn(
        self, state: TrainState, collect_metrics: Metrics, key: jax.Array
    ) -> tuple[TrainState, Metrics]:
        """The rest of an iteration after collection: ``updates_per_iteration`` SAC steps in one
        scan (Algorithm 1, lines 8–17; Algorithm 2, lines 13–30), counted."""
        tau, l_min = self.schedules(state.iteration)
        frozen = self.frozen(state.iteration)

        def update(s, k):
            return self.sac.update(s, k, tau, l_min, frozen)

        keys = jax.random.split(key, self.config.updates_per_iteration)
        state, u_metrics = jax.lax.scan(update, state, keys)
        state = state.replace(iteration=state.iteration + 1)
        u_metrics = jax.tree.map(jnp.mean, u_metrics)
        batch_l0 = u_metrics.pop("batch_l0_ratio")
        metrics = {
            **collect_metrics,
            **u_metrics,
            "tau": tau,
            "l_min": l_min,
            # ESPL: E||m||_0 / N of the learned p; meta-RL: of σ(Ψ(z)), over the updates' tasks
            "l0_ratio": batch_l0 if self.meta else self.l0_ratio(state),
            "env_steps": state.env_steps,
            "episodes": state.episodes,
            "iteration": state.iteration,
        }
        return state, metrics

    @property
    def finetunes(self) -> bool:
        """ESPL's fine-tune phase applies (``finetune`` and a path selector)."""
        return self.config.finetune and not self.meta and self.actor.uses_selector

    def frozen(self, iteration: jax.Array) -> jax.Array | None:
        """Whether the mask is frozen at this iteration (None when there is no fine-tuning)."""
        if not self.finetunes:
            return None
        return iteration >= self.config.schedule_iterations

    def freeze_mask(self, actor_params: dict, iteration: jax.Array) -> dict:
        """From t_s on, p := the exported mask (0/1); idempotent, so applied every iteration."""
        if not self.finetunes:
            return actor_params
        frozen = self.actor.freeze(actor_params)
        return rollout.where(self.frozen(iteration), frozen, actor_params)

    def iteration(self, state: TrainState) -> tuple[TrainState, Metrics]:
        """One iteration of Algorithm 1 or 2 in JAX (collection, then ``learn``)."""
        state = state.replace(actor=self.freeze_mask(state.actor, state.iteration))
        if self.meta:
            key, k_collect, k_update = jax.random.split(state.key, 3)
            state, c_metrics = self.collect_meta(state.replace(key=key), k_collect)
            return self.learn(state, c_metrics, k_update)
        key, mask, k_collect, k_update = self.start_iteration(state.key, state.actor)
        state, c_metrics = self.collect_single(state, mask, k_collect)
        return self.learn(state.replace(key=key), c_metrics, k_update)

    def l0_ratio(self, state: TrainState) -> jax.Array:
        """Single task: E||m||_0 / N, the fraction of paths the selector keeps (1 without one)."""
        return self.actor.l0_ratio(self.actor.at(state.actor, jnp.zeros((0,))))

    def chunk(self, state: TrainState, length: int) -> tuple[TrainState, Metrics]:
        """``length`` iterations in one scan, for one seed."""
        return jax.lax.scan(lambda s, _: self.iteration(s), state, None, length=length)

    def compiled_chunk(self, length: int):
        """jit(vmap(chunk)) over the leading seed axis; the state buffers are donated."""
        return self.over_seeds(lambda s: self.chunk(s, length), donate=True)

    # Evaluation ---------------------------------------------------------------------------------

    def evaluate(self, actor_params: dict, key: jax.Array, episodes: int) -> jax.Array:
        """Single task: returns of ``episodes`` deterministic episodes of the eval-mask policy
        (the exported formula)."""
        policy = self.actor.at(actor_params, jnp.zeros((0,)))
        params = jax.tree.map(lambda x: x[0], self.tasks[0])
        return rollout.evaluate(
            self.env, self.actor, policy, self.actor.eval_mask(policy), params, key, episodes
        )

    def compiled_evaluate(self, episodes: int):
        """jit(vmap(evaluate)) over seeds: (actor params [S, ...], keys [S, 2]) -> [S, E]."""
        return self.over_seeds(lambda p, k: self.evaluate(p, k, episodes))

    def adapt(self, state: TrainState, task_params: Any, key: jax.Array) -> rollout.Adapted:
        """Meta-RL: PEARL's protocol, ``eval_runs`` runs on each task of ``task_params`` [N]:
        an ``Adapted`` with leaves [N, runs]."""
        cfg = self.config
        n = jax.tree.leaves(task_params)[0].shape[0]

        def one(p, k):
            return rollout.adapt_and_evaluate(
                self.env, self.actor, self.encoder, state.actor, state.encoder, p, k,
                cfg.eval_steps, cfg.eval_exploration_trajectories,
            )  # fmt: skip

        keys = jax.random.split(key, n * cfg.eval_runs).reshape(n, cfg.eval_runs, -1)
        return jax.vmap(jax.vmap(one, (None, 0)), (0, 0))(task_params, keys)

    @cached_property
    def compiled_adapt(self):
        """jit(vmap(adapt)) over seeds: (state [S], task params [N], keys [S, 2]) -> Adapted
        [S, N, runs]. The tasks are an argument, not a constant, so the progress evaluations and
        the final one on the test tasks and on as many training tasks share one compile (minutes
        for the MJX families)."""
        return self.over_seeds(self.adapt, shared=(1,))

    def task_policy(self, actor_params: dict, z: np.ndarray | None) -> dict:
        """The task policy at z (numpy), for export: ESPL's own params, CSP's Φ/Ψ at z."""
        z = jnp.zeros((0,)) if z is None else jnp.asarray(z)
        return jax.tree.map(np.asarray, self.actor.at(actor_params, z))
