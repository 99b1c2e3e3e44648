"""Training throughput of brax's own SAC against ours, on one env, in one process.

    python benchmarks/vs_brax_sac.py                           # defaults below
    python benchmarks/vs_brax_sac.py --env-steps 50 --iterations 2 --sgd-steps 50 --json out.json

What runs:

* **ours, MLP actor** and **ours, symbolic actor** (ESPL): ``Trainer(cfg).compiled_chunk(n)``
  on espl_jax's MJX ``inverted_double_pendulum`` (gymnasium's InvertedDoublePendulum-v5 in MJX,
  ``envs/mjx.py``), one seed: ``n = --iterations`` iterations of ``--env-steps`` env steps on one
  env, then ``--env-steps x G / E`` SAC updates (G = ``--grad-updates-per-step``,
  E = ``--num-envs``), batch ``--batch-size``, twin critic 256x2, MLP actor 256x2.
* **brax SAC**: ``brax.training.agents.sac.train`` on *the same env*: espl_jax's MJX env wrapped
  as a ``brax.envs.Env`` (``EsplEnv`` below, a thin adapter: same model, same solver settings,
  same physics step), ``num_envs`` E, ``grad_updates_per_step`` G, the same batch size,
  ``make_sac_networks`` with hidden layers 256x2 (policy and both Qs). Its training epochs are
  timed by brax itself (``training/sps`` in ``progress_fn``); ``num_evals 3`` gives two epochs of
  ``n x --env-steps`` env steps each, the first of which compiles; the second is reported.
* **SGD step alone**: M = ``--sgd-steps`` updates in one jitted ``lax.scan`` (compile: the
  first call less a steady one).
  Ours: ``trainer.sac.update`` on the state left by the chunk (its replay sampling included).
  Brax: the body of ``train()``'s inner ``sgd_step`` (brax's ``make_losses`` and
  ``gradient_update_fn``: alpha, critic, actor updates, Polyak), rebuilt here because
  ``train()`` does not expose it, on brax's ``_init_training_state`` and a batch drawn each step
  from brax's ``UniformSamplingQueue`` holding random transitions.

Updates per env step are the same in both (G / E); the collection pattern is not: brax steps E
envs once and then runs G updates, every actor step; ours steps one env ``--env-steps`` times,
then runs all of the iteration's updates.

Not identical, and not made so (also printed with the table):

* networks: brax's policy is one 256x2 MLP giving mean and scale (tanh-normal, scale by
  softplus); ours is a 256x2 MLP for the mean plus a separate 64x3 MLP F(s) for log-std (the
  authors' code), and the symbolic actor is ESPL's symbolic network + F(s) + path selector;
  ours clips the policy gradient's global norm (0.5), brax does not;
* brax's AutoResetWrapper restarts an episode from the episode's *first* state (no fresh
  reset noise), ours resets with fresh noise; episodes end at 1000 steps in both (brax's
  EpisodeWrapper, our env's horizon);
* replay: brax's ``UniformSamplingQueue`` (one flat buffer, sampled once per actor step for all
  G updates), ours a per-task ring buffer sampled inside each update;
* brax 0.14.2's ``train()`` calls ``jax.device_put_replicated``, which jax 0.10.2 no longer
  has; this script puts back a one-line equivalent (``_device_put_replicated``) before calling;
* brax normalizes nothing here (``normalize_observations`` False), but updates its
  running-statistics state every step; brax's evaluation runs on a trivial env
  (``_NullEnv``) so its evals cost nothing, and brax's prefill (``min_replay_size`` = batch)
  is outside its timed epochs.

Not part of the test suite. ``--json PATH`` writes the rows and the settings.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs import base as brax_base
from brax.training import gradients, replay_buffers
from brax.training.agents.sac import losses as sac_losses
from brax.training.agents.sac import networks as sac_networks
from brax.training.agents.sac import train as brax_sac
from brax.training.types import Transition

from espl_jax import config, envs
from espl_jax.learner import Trainer

ENV = "inverted_double_pendulum"


def _device_put_replicated(x: Any, devices) -> Any:
    """``jax.device_put_replicated``, removed from jax 0.10 but called by brax 0.14.2's SAC
    ``train()`` (``_init_training_state``): a leading axis of ``len(devices)`` copies, which
    brax's ``pmap`` then splits over the devices."""
    return jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)


try:
    jax.device_put_replicated  # noqa: B018
except AttributeError:
    jax.device_put_replicated = _device_put_replicated

NOT_IDENTICAL = (
    "brax's policy is one 256x2 MLP for mean and scale; ours a 256x2 mean MLP + 64x3 log-std "
    "MLP (symbolic: ESPL's network + 64x3 log-std MLP + selector); ours clips the policy "
    "gradient (norm 0.5)",
    "brax's auto-reset restarts from the episode's first state; ours resets with fresh noise",
    "collection: brax steps E envs then runs G updates per actor step; ours steps one env "
    "--env-steps times, then runs the iteration's updates (same updates per env step)",
    "replay: brax samples G batches at once per actor step from one flat queue; ours samples "
    "inside each update from a per-task ring buffer",
)


class EsplEnv(brax_base.Env):
    """An espl_jax env (default physics params) as a ``brax.envs.Env``.

    ``done`` is the env's termination; the time limit is left to brax's EpisodeWrapper
    (``episode_length`` = the env's horizon), which marks it as truncation.
    """

    def __init__(self, env):
        self._env = env
        self._params = env.default_params

    def reset(self, rng: jax.Array) -> brax_base.State:
        obs, state = self._env.reset(rng, self._params)
        zero = jnp.zeros(())
        return brax_base.State(pipeline_state=state, obs=obs, reward=zero, done=zero)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        key = jax.random.key_data(jax.random.key(0))  # the MJX envs are deterministic
        obs, inner, reward, terminated, _, _ = self._env.step(
            key, state.pipeline_state, action, self._params
        )
        return state.replace(
            pipeline_state=inner, obs=obs, reward=reward, done=terminated.astype(jnp.float32)
        )

    @property
    def observation_size(self) -> int:
        return self._env.obs_dim

    @property
    def action_size(self) -> int:
        return self._env.action_dim

    @property
    def backend(self) -> str:
        return "mjx"


class _NullEnv(brax_base.Env):
    """Same sizes, no physics: brax's evaluator runs on it so that evals cost ~nothing."""

    def __init__(self, obs_size: int, action_size: int):
        self._obs, self._act = obs_size, action_size

    def reset(self, rng: jax.Array) -> brax_base.State:
        zero = jnp.zeros(())
        return brax_base.State(None, jnp.zeros(self._obs), zero, zero)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        return state

    @property
    def observation_size(self) -> int:
        return self._obs

    @property
    def action_size(self) -> int:
        return self._act

    @property
    def backend(self) -> str:
        return "none"


def our_config(args: argparse.Namespace, actor: str) -> config.Config:
    updates = args.env_steps * args.grad_updates_per_step // args.num_envs
    return config.resolve(
        ENV,
        actor=actor,
        seeds=1,
        steps_per_iteration=args.env_steps,
        updates_per_iteration=updates,
        chunk_iterations=args.iterations,
        iterations=max(args.iterations * 3, 10),
        batch_size=args.batch_size,
        critic_hidden=(256, 256),
        mlp_actor_hidden=(256, 256),
    )


def time_ours(args: argparse.Namespace, actor: str) -> dict[str, Any]:
    cfg = our_config(args, actor)
    trainer = Trainer(cfg)
    # Build the env outside any trace, as run.train does: an MJX env first built inside
    # init_seeds' jit would keep tracers of its model (cached_property).
    trainer.env  # noqa: B018
    state = trainer.init_seeds()
    chunk = trainer.compiled_chunk(args.iterations)
    # (AOT ``lower().compile()`` of an MJX chunk fails on its call here: "compiled for N inputs
    # but called with M", the captured model arrays; so compile = first call less a steady one.)
    started = time.perf_counter()
    state, _ = jax.block_until_ready(chunk(state))  # compiles; fills the buffer
    first_s = time.perf_counter() - started
    started = time.perf_counter()
    state, _ = jax.block_until_ready(chunk(state))
    run_s = time.perf_counter() - started
    compile_s = first_s - run_s
    env_steps = args.iterations * cfg.steps_per_iteration
    updates = args.iterations * cfg.updates_per_iteration
    row = dict(
        impl=f"ours ({actor} actor)",
        compile_s=compile_s,
        run_s=run_s,
        env_steps_per_s=env_steps / run_s,
        updates_per_s=updates / run_s,
    )
    row.update(time_our_sgd(trainer, jax.tree.map(lambda x: x[0], state), args.sgd_steps))
    return row


def time_our_sgd(trainer: Trainer, state, steps: int) -> dict[str, Any]:
    tau, l_min = trainer.iteration.schedules(state.iteration)
    frozen = trainer.iteration.frozen(state.iteration)

    def loop(state, key):
        def body(s, k):
            return trainer.sac.update(s, k, tau, l_min, frozen)[0], None

        return jax.lax.scan(body, state, jax.random.split(key, steps))[0]

    key = jax.random.PRNGKey(1)
    return _time_loop(loop, state, key, steps)


def _time_loop(loop, state, key, steps: int) -> dict[str, Any]:
    compiled = jax.jit(loop)
    started = time.perf_counter()
    state = jax.block_until_ready(compiled(state, key))
    first_s = time.perf_counter() - started
    started = time.perf_counter()
    jax.block_until_ready(compiled(state, jax.random.fold_in(key, 1)))
    run_s = time.perf_counter() - started
    compile_s = first_s - run_s
    return dict(sgd_compile_s=compile_s, sgd_steps_per_s=steps / run_s)


def brax_networks(obs_size: int, action_size: int):
    factory = functools.partial(sac_networks.make_sac_networks, hidden_layer_sizes=(256, 256))
    return factory(observation_size=obs_size, action_size=action_size)


def time_brax(args: argparse.Namespace, env) -> dict[str, Any]:
    per_epoch = args.iterations * args.env_steps
    progress: list[dict[str, float]] = []

    def progress_fn(step: int, metrics) -> None:
        if "training/sps" in metrics:
            progress.append({k: float(v) for k, v in metrics.items() if k.startswith("training")})

    started = time.perf_counter()
    brax_sac.train(
        environment=EsplEnv(env),
        num_timesteps=args.batch_size + 2 * per_epoch,
        episode_length=env.horizon,
        num_envs=args.num_envs,
        num_eval_envs=1,
        batch_size=args.batch_size,
        num_evals=3,
        min_replay_size=args.batch_size,
        max_replay_size=max(100_000, args.batch_size + 2 * per_epoch),
        grad_updates_per_step=args.grad_updates_per_step,
        network_factory=functools.partial(
            sac_networks.make_sac_networks, hidden_layer_sizes=(256, 256)
        ),
        progress_fn=progress_fn,
        eval_env=_NullEnv(env.obs_dim, env.action_dim),
        seed=0,
    )
    wall = time.perf_counter() - started
    if len(progress) < 2:
        raise RuntimeError(f"brax reported {len(progress)} timed epochs, expected 2")
    first, steady = progress[0], progress[-1]
    sps = steady["training/sps"]
    epoch_s = per_epoch / sps
    row = dict(
        impl="brax SAC",
        # brax's first epoch compiles and runs; the compile is its time less a steady epoch
        compile_s=per_epoch / first["training/sps"] - epoch_s,
        run_s=epoch_s,
        env_steps_per_s=sps,
        updates_per_s=sps * args.grad_updates_per_step / args.num_envs,
        brax_train_wall_s=wall,
    )
    row.update(time_brax_sgd(env.obs_dim, env.action_dim, args.batch_size, args.sgd_steps))
    return row


def time_brax_sgd(obs_size: int, action_size: int, batch_size: int, steps: int):
    """brax's ``sgd_step`` (``train()``'s inner function, same code) in a jitted scan."""
    network = brax_networks(obs_size, action_size)
    alpha_opt = brax_sac.optax.adam(3e-4)
    policy_opt = brax_sac.optax.adam(1e-4)
    q_opt = brax_sac.optax.adam(1e-4)
    alpha_loss, critic_loss, actor_loss = sac_losses.make_losses(
        sac_network=network, reward_scaling=1.0, discounting=0.99, action_size=action_size
    )
    alpha_update = gradients.gradient_update_fn(alpha_loss, alpha_opt, pmap_axis_name=None)
    critic_update = gradients.gradient_update_fn(critic_loss, q_opt, pmap_axis_name=None)
    actor_update = gradients.gradient_update_fn(actor_loss, policy_opt, pmap_axis_name=None)
    tau = 0.005
    state = brax_sac._init_training_state(
        key=jax.random.PRNGKey(0),
        obs_size=obs_size,
        local_devices_to_use=1,
        sac_network=network,
        alpha_optimizer=alpha_opt,
        policy_optimizer=policy_opt,
        q_optimizer=q_opt,
    )
    state = jax.tree.map(lambda x: x[0], state)  # un-replicate (one device)

    def sgd_step(carry, transitions):  # brax/training/agents/sac/train.py: sgd_step
        training_state, key = carry
        key, key_alpha, key_critic, key_actor = jax.random.split(key, 4)
        _, alpha_params, alpha_optimizer_state = alpha_update(
            training_state.alpha_params,
            training_state.policy_params,
            training_state.normalizer_params,
            transitions,
            key_alpha,
            optimizer_state=training_state.alpha_optimizer_state,
        )
        alpha = jnp.exp(training_state.alpha_params)
        _, q_params, q_optimizer_state = critic_update(
            training_state.q_params,
            training_state.policy_params,
            training_state.normalizer_params,
            training_state.target_q_params,
            alpha,
            transitions,
            key_critic,
            optimizer_state=training_state.q_optimizer_state,
        )
        _, policy_params, policy_optimizer_state = actor_update(
            training_state.policy_params,
            training_state.normalizer_params,
            training_state.q_params,
            alpha,
            transitions,
            key_actor,
            optimizer_state=training_state.policy_optimizer_state,
        )
        target = jax.tree.map(
            lambda x, y: x * (1 - tau) + y * tau, training_state.target_q_params, q_params
        )
        training_state = training_state.replace(
            policy_optimizer_state=policy_optimizer_state,
            policy_params=policy_params,
            q_optimizer_state=q_optimizer_state,
            q_params=q_params,
            target_q_params=target,
            alpha_optimizer_state=alpha_optimizer_state,
            alpha_params=alpha_params,
        )
        return (training_state, key), None

    dummy = Transition(
        observation=jnp.zeros((obs_size,)),
        action=jnp.zeros((action_size,)),
        reward=jnp.zeros(()),
        discount=jnp.zeros(()),
        next_observation=jnp.zeros((obs_size,)),
        extras={"state_extras": {"truncation": jnp.zeros(())}, "policy_extras": {}},
    )
    capacity = 10_000
    queue = replay_buffers.UniformSamplingQueue(
        max_replay_size=capacity, dummy_data_sample=dummy, sample_batch_size=batch_size
    )
    buffer = queue.init(jax.random.PRNGKey(2))
    rng = np.random.default_rng(0)
    fill = jax.tree.map(
        lambda x: jnp.asarray(rng.uniform(-1, 1, (capacity, *x.shape)), jnp.float32), dummy
    )
    buffer = jax.jit(queue.insert)(buffer, fill)

    def loop(carry, key):
        training_state, buffer = carry

        def body(c, _):
            training_state, buffer, key = c
            buffer, transitions = queue.sample(buffer)
            (training_state, key), _ = sgd_step((training_state, key), transitions)
            return (training_state, buffer, key), None

        (training_state, buffer, _), _ = jax.lax.scan(
            body, (training_state, buffer, key), None, length=steps
        )
        return training_state, buffer

    return _time_loop(loop, (state, buffer), jax.random.PRNGKey(1), steps)


def _load() -> str:
    a = os.getloadavg()
    return f"{a[0]:.2f} {a[1]:.2f} {a[2]:.2f}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env-steps", type=int, default=200, help="env steps per iteration (ours)")
    p.add_argument("--iterations", type=int, default=5, help="iterations per timed chunk")
    p.add_argument("--num-envs", type=int, default=1, help="brax num_envs (E)")
    p.add_argument("--grad-updates-per-step", type=int, default=1, help="brax G")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--sgd-steps", type=int, default=200, help="updates in the SGD-alone loop")
    p.add_argument(
        "--skip",  # each row compiles for a minute or more on a loaded 2-core CPU
        nargs="*",
        default=[],
        choices=["mlp", "symbolic", "brax"],
        help="rows to leave out",
    )
    p.add_argument("--json", default=None, metavar="PATH", help="write rows and settings")
    args = p.parse_args(argv)
    if (args.env_steps * args.grad_updates_per_step) % args.num_envs:
        p.error("--env-steps x --grad-updates-per-step must be a multiple of --num-envs")

    env = envs.make(ENV)
    settings = dict(
        env=ENV,
        backend=jax.default_backend(),
        jax=jax.__version__,
        env_steps_per_iteration=args.env_steps,
        iterations=args.iterations,
        num_envs=args.num_envs,
        grad_updates_per_step=args.grad_updates_per_step,
        updates_per_env_step=args.grad_updates_per_step / args.num_envs,
        batch_size=args.batch_size,
        sgd_steps=args.sgd_steps,
        load_average_before=_load(),
    )
    print(
        f"{ENV} (espl_jax MJX env; brax trains on it through EsplEnv), jax {jax.__version__}, "
        f"backend {jax.default_backend()}, batch {args.batch_size}, "
        f"{args.grad_updates_per_step / args.num_envs:g} updates per env step, "
        f"{args.iterations} x {args.env_steps} env steps timed; load average {_load()}",
        flush=True,
    )
    rows = []
    for name in ("mlp", "symbolic", "brax"):
        if name in args.skip:
            continue
        row = time_brax(args, env) if name == "brax" else time_ours(args, name)
        row["load_average_after"] = _load()
        rows.append(row)
        print(f"  done: {row['impl']} (load average {row['load_average_after']})", flush=True)
    brax_row = next((r for r in rows if r["impl"] == "brax SAC"), None)
    for r in rows:
        if brax_row is not None:
            r["updates_per_s_over_brax"] = r["updates_per_s"] / brax_row["updates_per_s"]
            r["sgd_steps_per_s_over_brax"] = r["sgd_steps_per_s"] / brax_row["sgd_steps_per_s"]
    print()
    print(
        "| impl | compile (s) | env steps/s | SGD updates/s (training) | ratio to brax "
        "| SGD step alone (updates/s) | ratio to brax |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ratio = f"{r['updates_per_s_over_brax']:.2f}" if brax_row else ""
        sgd_ratio = f"{r['sgd_steps_per_s_over_brax']:.2f}" if brax_row else ""
        print(
            f"| {r['impl']} | {r['compile_s']:.1f} | {r['env_steps_per_s']:.0f} "
            f"| {r['updates_per_s']:.0f} | {ratio} | {r['sgd_steps_per_s']:.0f} | {sgd_ratio} |"
        )
    print("\nNot identical between the two:")
    for line in NOT_IDENTICAL:
        print(f"- {line}")
    print(f"\nload average after: {_load()}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {"settings": settings, "not_identical": NOT_IDENTICAL, "rows": rows}, f, indent=2
            )
            f.write("\n")


if __name__ == "__main__":
    main()
