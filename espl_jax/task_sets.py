"""The tasks a run trains on, how an iteration collects experience on them (Algorithm 1
lines 4–7, Algorithm 2 lines 3–10), and which tasks and latents an update draws (docs/design.md
"One trainer").

Everything single-task runs and meta-RL runs do differently in training lives here, in two task
sets with one interface, but for PEARL's encoder's own training (``espl_jax.sac``): the trainer
(``espl_jax.learner``), the iteration (``espl_jax.iteration``) and the SAC update do not ask
which one they hold.

- ``SingleTask``: a single-task env as a family of one. T = 1 task (the env's default params),
  a (0,)-sized latent, no encoder. ESPL's collection: one Bernoulli mask (Algorithm 1 line 4),
  ``steps_per_iteration`` steps on the task, episodes continuing across iterations.
- ``MetaTasks``: a meta-RL task family's ``n_train`` training tasks, a latent z from PEARL's
  encoder, per-task buffers. PEARL's collection (its ``rl_algorithm``): ``tasks_per_iteration``
  distinct training tasks; each has its encoder buffer cleared, then a prior phase
  (``prior_steps``, z ~ N(0, I) per trajectory, into both buffers) and a posterior phase
  (``posterior_steps``, z from the posterior of a context drawn from the fresh encoder buffer,
  per trajectory, into the RL buffer only). CSP draws a Bernoulli mask of σ(Ψ(z)) with every z.
  Before the first iteration ``warmup`` fills every training task with ``initial_steps``
  prior-z steps (both buffers). An update draws ``meta_batch`` tasks with replacement, a
  context of each and z ~ q(z | c) (``sample_batch``, ``latents``).

Both step their envs through ``espl_jax.rollout.collect``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import pearl, replay, rollout
from espl_jax.config import Config
from espl_jax.keys import POSTERIOR_DRAW
from espl_jax.policies import Actor, no_latent
from espl_jax.rollout import Rollout
from espl_jax.sac import Metrics, TrainState, task_keys
from espl_jax.seeds import take


def _recorded(
    state: TrainState, rollout_state: Rollout, done: jax.Array, returns: jax.Array, steps: int
) -> tuple[TrainState, Metrics]:
    """The state and metrics after collection; ``done`` and ``returns`` (of the episodes that
    ended there) cover every collected step (any shape)."""
    finished = jnp.sum(done)
    state = state.replace(
        rollout=rollout_state,
        env_steps=state.env_steps + steps,
        episodes=state.episodes + finished,
    )
    metrics = {
        "episodes_finished": finished,
        "train_return": jnp.sum(returns) / jnp.maximum(finished, 1),
    }
    return state, metrics


@dataclass(frozen=True)
class SingleTask:
    """One task: the env's default params (Algorithm 1).

    Attributes:
        env: the env.
        steps_per_iteration: K, env steps per iteration.
        buffer_capacity: the replay buffer's capacity.
        exploration_correlation: ρ of the AR(1) exploration noise (``rollout.explore``).
    """

    env: Any
    steps_per_iteration: int
    buffer_capacity: int
    exploration_correlation: float

    num_train = 1
    latent_dim = 0
    rollout_slots = 1  # the one env, whose episodes continue across iterations
    initial_steps = 0  # no warmup
    encoder = None

    @cached_property
    def params(self) -> tuple[Any, Any]:
        """(train, test) task params with a leading task axis: the env's default params, once,
        as both."""
        # Concrete numpy arrays even when first asked for inside a jit trace (cached_property).
        with jax.ensure_compile_time_eval():
            params = jax.tree.map(lambda x: np.asarray(x)[None], self.env.default_params)
        return params, params

    def encoder_buffer(self, obs_dim: int, action_dim: int) -> None:
        return None

    def sample_batch(self, state: TrainState, key: jax.Array, batch_size: int):
        """An update's RL batch [1, B, ...] of the one task; no context."""
        tasks = jnp.zeros((1,), jnp.int32)
        return replay.sample(state.buffer, tasks, task_keys(key, 1), batch_size), None

    def latents(self, encoder: Any, context: Any, key: jax.Array, tasks: int):
        """A (tasks, 0) z and no KL."""
        return jnp.zeros((tasks, 0)), jnp.zeros(())

    def start_iteration(self, actor: Actor, key: jax.Array, actor_params: dict):
        """ESPL's iteration randomness: (next state key, Bernoulli mask, collect key, update
        key). The mask is Algorithm 1, line 4; one mask serves the whole collection."""
        key, k_mask, k_collect, k_update = jax.random.split(key, 4)
        policy = actor.at(actor_params, no_latent())
        return key, actor.collect_mask(k_mask, policy), k_collect, k_update

    def collect_with_mask(self, actor: Actor, state: TrainState, mask: Any, key: jax.Array):
        """ESPL: K steps on the one task with one fixed mask (Algorithm 1, lines 5–7)."""
        steps = self.steps_per_iteration

        def one(r, p, k):
            return rollout.collect(
                self.env, actor, self.exploration_correlation,
                r, p, state.actor, no_latent(), mask, k, steps,
            )  # fmt: skip

        r, transitions, done, finished = jax.vmap(one)(
            state.rollout, self.params[0], task_keys(key, 1)
        )
        one_task = jnp.zeros(1, jnp.int32)
        state = state.replace(buffer=replay.insert(state.buffer, one_task, transitions))
        return _recorded(state, r, done, finished, steps)

    def collect(self, actor: Actor, state: TrainState) -> tuple[TrainState, Metrics, jax.Array]:
        """An iteration's collection: (state, metrics, the key of the iteration's updates)."""
        key, mask, k_collect, k_update = self.start_iteration(actor, state.key, state.actor)
        state, metrics = self.collect_with_mask(actor, state, mask, k_collect)
        return state.replace(key=key), metrics, k_update

    def warmup(self, actor: Actor, state: TrainState) -> TrainState:
        return state

    def l0_ratio(self, actor: Actor, actor_params: dict, batch_l0: jax.Array) -> jax.Array:
        """The iteration's ``l0_ratio``: E||m||_0 / N of the learned p (1 without a selector)."""
        return actor.l0_ratio(actor.at(actor_params, no_latent()))


@dataclass(frozen=True)
class MetaTasks:
    """The training and test tasks of a meta-RL task family (Algorithm 2).

    Attributes:
        family: the ``envs.TaskFamily``.
        task_seed: the seed of its task draws.
        encoder: PEARL's context encoder (its ``latent_dim`` is the latent's).
        tasks_per_iteration, prior_steps, posterior_steps, initial_steps, meta_batch,
            context_batch, task_buffer_size, exploration_correlation: the config's keys.
    """

    family: Any
    task_seed: int
    encoder: pearl.Encoder
    tasks_per_iteration: int
    prior_steps: int
    posterior_steps: int
    initial_steps: int
    meta_batch: int
    context_batch: int
    task_buffer_size: int
    exploration_correlation: float

    # Trajectories a collection phase draws a z for; a phase with more episodes reuses them in
    # turn (only very short episodes, early in training, get there: 32 × 12 steps ≥ 400).
    DRAWS_PER_PHASE = 32

    @property
    def env(self):
        return self.family.env

    @property
    def num_train(self) -> int:
        return self.family.n_train

    @property
    def latent_dim(self) -> int:
        return self.encoder.latent_dim

    @cached_property
    def params(self) -> tuple[Any, Any]:
        """(train [n_train], test [n_test]) task params."""
        # Concrete numpy arrays even when first asked for inside a jit trace (cached_property).
        with jax.ensure_compile_time_eval():
            train, test = self.family.tasks(self.task_seed)
            return jax.tree.map(np.asarray, train), jax.tree.map(np.asarray, test)

    @property
    def rollout_slots(self) -> int:
        """Tasks collected on at once: ``tasks_per_iteration``."""
        return min(self.tasks_per_iteration, self.num_train)

    @property
    def steps_per_iteration(self) -> int:
        return self.rollout_slots * (self.prior_steps + self.posterior_steps)

    @property
    def buffer_capacity(self) -> int:
        return self.task_buffer_size

    def encoder_buffer(self, obs_dim: int, action_dim: int) -> replay.ReplayBuffer:
        capacity = max(self.initial_steps, self.prior_steps)
        return replay.init(self.num_train, capacity, obs_dim, action_dim)

    def sample_batch(self, state: TrainState, key: jax.Array, batch_size: int):
        """An update's (RL batch [meta_batch, B, ...], context [meta_batch, C, ...]) of
        ``meta_batch`` tasks drawn with replacement (PEARL)."""
        k_tasks, k_rl, k_context = jax.random.split(key, 3)
        n = self.meta_batch
        tasks = jax.random.randint(k_tasks, (n,), 0, self.num_train)
        batch = replay.sample(state.buffer, tasks, jax.random.split(k_rl, n), batch_size)
        context = replay.sample(
            state.encoder_buffer, tasks, jax.random.split(k_context, n), self.context_batch
        )
        return batch, context

    def latents(self, encoder: Any, context: Any, key: jax.Array, tasks: int):
        """z ~ q(z | c) per task (reparameterised) and Σ_tasks KL(q ‖ N(0, I))."""
        mu, var = jax.vmap(self.encoder.posterior, (None, 0))(encoder, context)
        z = pearl.sample(key, mu, var)
        return z, jnp.sum(pearl.kl_to_standard_normal(mu, var))

    def draws(self, actor: Actor, params: dict, mu: jax.Array, var: jax.Array, key: jax.Array):
        """The policies of a phase's trajectories, drawn up front: ``DRAWS_PER_PHASE`` latents
        z ~ N(mu, var), their generated parts and (CSP) Bernoulli masks of σ(Ψ(z)), so the
        (hyper)networks that generate a policy run once per trajectory, not at every step."""
        k_z, k_mask = jax.random.split(key)
        n = self.DRAWS_PER_PHASE
        z = mu + jnp.sqrt(var) * jax.random.normal(k_z, (n, mu.shape[-1]))
        parts = jax.vmap(actor.generate, (None, 0))(params, z)
        masks = jax.vmap(lambda k, p: actor.collect_mask(k, actor.policy(params, p)))(
            jax.random.split(k_mask, n), parts
        )
        return parts, masks

    def phase_latents(self, state: TrainState, tasks: jax.Array, key: jax.Array, posterior: bool):
        """(mu, var) [R, L] the phase's z are drawn from: the prior N(0, I), or the posterior of a
        context drawn from each task's (fresh) encoder buffer."""
        n = tasks.shape[0]
        if not posterior:
            return jnp.zeros((n, self.latent_dim)), jnp.ones((n, self.latent_dim))
        context = replay.sample(
            state.encoder_buffer, tasks, jax.random.split(key, n), self.context_batch
        )
        return jax.vmap(self.encoder.posterior, (None, 0))(state.encoder, context)

    def phase(self, actor, state, tasks, key, steps, posterior, to_encoder):
        """One PEARL collection phase on the distinct ``tasks`` [R]: reset, ``steps`` steps with
        a z per trajectory from the prior or (``posterior``) from q(z | fresh context)."""
        env = self.env
        n = tasks.shape[0]
        k_reset, k_context, k_collect = jax.random.split(key, 3)
        task_params = jax.tree.map(lambda x: jnp.asarray(x)[tasks], self.params[0])
        mu, var = self.phase_latents(state, tasks, k_context, posterior)

        def one(p, k_r, k_c, mu_t, var_t):
            r = rollout.reset(env, p, k_r, env.action_dim)
            k_draws = jax.random.fold_in(k_c, POSTERIOR_DRAW)
            parts, masks = self.draws(actor, state.actor, mu_t, var_t, k_draws)

            def draw(i):  # the i-th trajectory's (policy part, mask)
                return take((parts, masks), i % self.DRAWS_PER_PHASE)

            part, mask = draw(0)  # the first step draws it again; this fixes the carry's shape
            return rollout.collect(
                env, actor, self.exploration_correlation,
                r, p, state.actor, part, mask, k_c, steps, draw,
            )  # fmt: skip

        r, transitions, done, finished = jax.vmap(one)(
            task_params, jax.random.split(k_reset, n), jax.random.split(k_collect, n), mu, var
        )
        state = state.replace(buffer=replay.insert(state.buffer, tasks, transitions))
        if to_encoder:
            state = state.replace(
                encoder_buffer=replay.insert(state.encoder_buffer, tasks, transitions)
            )
        return state, r, done, finished

    def collect_tasks(
        self, actor: Actor, state: TrainState, key: jax.Array
    ) -> tuple[TrainState, Metrics]:
        """PEARL's collection for one iteration (module docstring)."""
        k_tasks, k_prior, k_posterior = jax.random.split(key, 3)
        tasks = jax.random.choice(k_tasks, self.num_train, (self.rollout_slots,), replace=False)
        state = state.replace(encoder_buffer=replay.clear(state.encoder_buffer, tasks))
        state, r, done, finished = self.phase(
            actor, state, tasks, k_prior, self.prior_steps, posterior=False, to_encoder=True
        )
        dones, returns = [done], [finished]
        if self.posterior_steps:
            state, r, done, finished = self.phase(
                actor, state, tasks, k_posterior, self.posterior_steps,
                posterior=True, to_encoder=False,
            )  # fmt: skip
            dones.append(done)
            returns.append(finished)
        return _recorded(
            state,
            r,
            jnp.concatenate([d.ravel() for d in dones]),
            jnp.concatenate([f.ravel() for f in returns]),
            self.steps_per_iteration,
        )

    def collect(self, actor: Actor, state: TrainState) -> tuple[TrainState, Metrics, jax.Array]:
        """An iteration's collection: (state, metrics, the key of the iteration's updates)."""
        key, k_collect, k_update = jax.random.split(state.key, 3)
        state, metrics = self.collect_tasks(actor, state.replace(key=key), k_collect)
        return state, metrics, k_update

    def warmup(self, actor: Actor, state: TrainState) -> TrainState:
        """Before the first iteration: ``initial_steps`` prior-z steps on every training task,
        into both buffers (PEARL's ``num_initial_steps``)."""
        if not self.initial_steps:
            return state
        key, k_warmup = jax.random.split(state.key)
        tasks = jnp.arange(self.num_train)
        state, r, done, _ = self.phase(
            actor, state.replace(key=key), tasks, k_warmup, self.initial_steps,
            posterior=False, to_encoder=True,
        )  # fmt: skip
        return state.replace(
            env_steps=state.env_steps + self.num_train * self.initial_steps,
            episodes=state.episodes + jnp.sum(done),
        )

    def l0_ratio(self, actor: Actor, actor_params: dict, batch_l0: jax.Array) -> jax.Array:
        """The iteration's ``l0_ratio``: E||m||_0 / N of σ(Ψ(z)), over the updates' tasks."""
        return batch_l0


TaskSet = SingleTask | MetaTasks


def task_set(config: Config, env: Any, family: Any) -> TaskSet:
    """The task set of a run: ``family``'s (a meta-RL run), else the single task of ``env``.
    The one place the config's collection keys are read."""
    rho = config.exploration_correlation
    if family is None:
        steps = config.steps_per_iteration
        wanted = min(config.buffer_size, config.iterations * steps)
        return SingleTask(env, steps, replay.capacity_for(wanted, steps), rho)
    encoder = pearl.Encoder(
        config.encoder_hidden,
        config.latent_dim,
        family.use_next_obs_in_context,
        config.posterior_var_floor,
    )
    return MetaTasks(
        family=family,
        task_seed=config.task_seed,
        encoder=encoder,
        tasks_per_iteration=config.tasks_per_iteration,
        prior_steps=config.prior_steps,
        posterior_steps=config.posterior_steps,
        initial_steps=config.initial_steps,
        meta_batch=config.meta_batch,
        context_batch=config.context_batch,
        task_buffer_size=config.task_buffer_size,
        exploration_correlation=rho,
    )
