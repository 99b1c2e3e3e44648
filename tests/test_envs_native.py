"""The native MuJoCo backend (``envs/native.py``) against gymnasium, CPU MuJoCo and MJX.

- Every MuJoCo env against its gymnasium v5 class, step by step in float64 (the host core,
  ``NativeEnv.host_step64``), free-running and re-synced for ``STEPS`` steps of random actions:
  obs and reward within 1e-6, and the physics state bit for bit (the state vector holds
  everything ``mj_step`` reads, so restoring it continues exactly).
- The same through the jitted env (``reset``/``step`` under ``jit``, float32 outputs).
- A family's task params: native equals CPU MuJoCo on the task's model; different tasks give
  different trajectories; native agrees with MJX within MJX's float32 tolerance (slow: MJX
  compiles for minutes).
- A native run killed with SIGKILL and resumed ends with the same state as an uninterrupted one.
"""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from espl_jax import envs
from espl_jax.envs.native import (
    HOOK_FIELDS,
    LANES_PER_WORKER,
    NativeEnv,
    float64_words,
    from_words,
    to_words,
)

REPO = Path(__file__).resolve().parent.parent
STEPS = 100
TOL = 1e-6
GYMNASIUM_IDS = {
    "hopper": "Hopper-v5",
    "walker2d": "Walker2d-v5",
    "halfcheetah": "HalfCheetah-v5",
    "inverted_double_pendulum": "InvertedDoublePendulum-v5",
}


def test_float64_words_equal_numpys_conversion():
    rng = np.random.default_rng(0)
    x = np.concatenate(
        [
            (rng.standard_normal(2000) * 10.0 ** rng.integers(-40, 38, 2000)).astype(np.float32),
            np.array([0.0, -0.0, 1e-45, -3e-44, 1.1e-38, 3.4e38, np.inf, -np.inf], np.float32),
        ]
    )
    words = np.asarray(jax.jit(float64_words)(jnp.asarray(x)))
    np.testing.assert_array_equal(words, to_words(x.astype(np.float64)))
    np.testing.assert_array_equal(from_words(words), x.astype(np.float64))
    assert np.isnan(from_words(np.asarray(float64_words(jnp.asarray(np.nan))))).all()


def _view(data: mujoco.MjData) -> SimpleNamespace:
    """One MjData as the batch of one the task hooks read."""
    return SimpleNamespace(**{k: getattr(data, k)[None] for k in HOOK_FIELDS})


def _state_of(env: NativeEnv, data: mujoco.MjData) -> np.ndarray:
    state = np.empty(env.state_size)
    env._save(data, state)
    return state


@pytest.mark.parametrize("name", sorted(GYMNASIUM_IDS))
def test_native_matches_gymnasium_step_by_step(name):
    """float64, free-running and re-synced: obs/reward within 1e-6, the state exactly."""
    pytest.importorskip("imageio", reason="gymnasium.envs.mujoco imports imageio")
    import gymnasium

    env = envs.make(name, physics="native")
    assert isinstance(env, NativeEnv)
    ref = gymnasium.make(GYMNASIUM_IDS[name]).unwrapped
    ref.reset(seed=3)
    row = np.asarray(env.flat_params(env.default_params))[None]
    state = _state_of(env, ref.data)[None]
    np.testing.assert_allclose(
        env.task._obs(_view(ref.data), np)[0], ref._get_obs(), atol=TOL, err_msg="reset obs"
    )
    actions = np.random.default_rng(4).uniform(-1, 1, (STEPS, env.action_dim))
    for resync in (False, True):
        ref.reset(seed=3)
        state = _state_of(env, ref.data)[None]
        for t, action in enumerate(actions):
            if resync:
                state = _state_of(env, ref.data)[None]
            state, values = env.host_step64(state, action[None], row)
            obs, reward, terminated, _, _ = ref.step(action)
            what = f"{name}, step {t}, {'re-synced' if resync else 'free-running'}"
            np.testing.assert_array_equal(state[0], _state_of(env, ref.data), err_msg=what)
            np.testing.assert_allclose(values[0, : env.obs_dim], obs, atol=TOL, err_msg=what)
            np.testing.assert_allclose(values[0, env.obs_dim], reward, atol=TOL, err_msg=what)
            assert bool(values[0, env.obs_dim + 1]) == terminated, what
            if terminated:
                break
    ref.close()


def test_jitted_native_env_matches_the_host_core():
    """reset/step under jit and vmap: float32 rounding of the float64 host core, and the state
    words exactly the host core's; the auto-reset path of collection needs no host call."""
    env = envs.make("hopper", physics="native")
    params = env.default_params
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    obs, state = jax.jit(jax.vmap(env.reset, (0, None)))(keys, params)
    qpos = from_words(np.asarray(state.physics))[:, env._slices["qpos"]]
    np.testing.assert_array_equal(np.asarray(obs)[:, :5], qpos[:, 1:].astype(np.float32))
    actions = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (3, 3)), jnp.float32)
    step = jax.jit(jax.vmap(env.step, (0, 0, 0, None)))
    obs2, state2, reward, terminated, truncated, info = step(keys, state, actions, params)
    row = np.asarray(env.flat_params(params))
    host_state, values = env.host_step64(
        from_words(np.asarray(state.physics)),
        np.asarray(env.scale_action(actions), np.float64),
        np.broadcast_to(row, (3, row.size)),
    )
    np.testing.assert_array_equal(from_words(np.asarray(state2.physics)), host_state)
    np.testing.assert_array_equal(np.asarray(obs2), values[:, : env.obs_dim].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(reward), values[:, env.obs_dim].astype(np.float32))
    assert np.asarray(state2.t).tolist() == [1, 1, 1]
    assert set(info) == {"x_position", "x_velocity", "reward_forward", "reward_ctrl"} | {
        "reward_survive"
    }
    assert not np.asarray(truncated).any() and not np.asarray(terminated).any()


def _family_rollout(env, params, actions):
    """Open-loop native qpos [T, nq] of one task from the model's reset pose."""
    obs, state = jax.jit(env.reset)(jax.random.PRNGKey(7), params)

    def body(s, a):
        _, s, _, _, _, _ = env.step(jax.random.PRNGKey(0), s, a, params)
        return s, s.physics[env._slices["qpos"]]  # words: compared exactly on the host

    _, qpos_words = jax.jit(lambda s: jax.lax.scan(body, s, actions))(state)
    return state, from_words(np.asarray(qpos_words))


def test_family_tasks_are_their_models_and_differ():
    """hopper_params: a task's native trajectory is ``mj_step`` on the task's model (the model
    fields written in), bit for bit; two tasks give different trajectories."""
    family = envs.make_family("hopper_params", physics="native")
    env = family.env
    train, _ = family.tasks(0)
    actions = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (40, 3)), jnp.float32)
    runs = []
    for i in (0, 1):
        params = jax.tree.map(lambda x, i=i: x[i], train)
        state, qpos = _family_rollout(env, params, actions)
        # the reference: CPU MuJoCo on a copy of the model with the task's values (float64 of
        # the float32 params, the model's own value where the params hold its float32 rounding)
        model = copy.copy(env.model)
        for field in ("body_mass", "body_inertia", "dof_damping", "geom_friction"):
            given = np.asarray(getattr(params, field))
            own = getattr(env.model, field)
            getattr(model, field)[:] = np.where(given == own.astype(np.float32), own, given)
        data = mujoco.MjData(model)
        env._load(data, from_words(np.asarray(state.physics)))
        want = []
        for a in np.asarray(env.scale_action(actions), np.float64):
            data.ctrl[:] = a
            mujoco.mj_step(model, data, nstep=env.task.frame_skip)
            want.append(data.qpos.copy())
        np.testing.assert_array_equal(qpos, np.array(want))
        runs.append(qpos)
    assert np.abs(runs[0] - runs[1]).max() > 1e-3


@pytest.mark.slow
def test_family_task_native_agrees_with_mjx():
    """The same task and actions in both backends, open loop: within MJX's float32 tolerance
    (1e-4, tests/test_envs_mjx.py) for the first 20 steps."""
    native = envs.make_family("hopper_params", physics="native")
    mjx_family = envs.make_family("hopper_params", physics="mjx")
    train, _ = native.tasks(0)
    params = jax.tree.map(lambda x: x[3], train)
    actions = jnp.asarray(np.random.default_rng(2).uniform(-1, 1, (20, 3)), jnp.float32)

    def qpos_of(env):
        obs, state = env.reset(jax.random.PRNGKey(5), params)

        def body(s, a):
            obs, s, *_ = env.step(jax.random.PRNGKey(0), s, a, params)
            return s, obs[:5]  # qpos[1:]

        return np.asarray(jax.jit(lambda s: jax.lax.scan(body, s, actions)[1])(state))

    np.testing.assert_allclose(qpos_of(native.env), qpos_of(mjx_family.env), atol=1e-4, rtol=0)


# Kill and resume ------------------------------------------------------------------------------


TINY_HOPPER = {
    "env": "hopper",
    "actor": "mlp",
    "physics": "native",
    "seeds": 1,
    "iterations": 4,
    "steps_per_iteration": 64,
    "updates_per_iteration": 4,
    "chunk_iterations": 2,
    "batch_size": 8,
    "critic_hidden": [16],
    "std_hidden": [8],
    "mlp_actor_hidden": [16],
    "progress_eval_episodes": 1,
    "eval_episodes": 1,
    "reference_eval_episodes": 1,
    "buffer_size": 1024,
}


def _train_cli(args, env_vars=None):
    env = {**os.environ, **(env_vars or {})}
    return subprocess.run(
        [sys.executable, "-m", "espl_jax.train", "--no-progress", *args],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=1200,
    )  # fmt: skip


@pytest.mark.slow  # ~2 min: three CLI runs of a tiny hopper config
def test_native_run_killed_mid_chunk_resumes_bit_for_bit(tmp_path, jax_cache):
    """SIGKILL while the second chunk runs, then ``--resume``: the physics state is in the
    checkpoint, so the run ends exactly where an uninterrupted one does."""
    from espl_jax import config as config_lib
    from espl_jax import faults, run, rundir

    config_file = tmp_path / "tiny_hopper.yaml"
    config_lib.save(config_lib.from_mapping(TINY_HOPPER), config_file)
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    done = _train_cli(["--config", str(config_file), "--out", str(whole)], jax_cache)
    assert done.returncode == 0, done.stderr
    proc = _train_cli(
        ["--config", str(config_file), "--out", str(killed)],
        {**jax_cache, faults.ENV_VAR: "chunk:4"},
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    resumed = _train_cli(["--resume", str(killed)], jax_cache)
    assert resumed.returncode == 0, resumed.stderr
    _, state_a, step_a = run.load_run(whole)
    _, state_b, step_b = run.load_run(killed)
    assert step_a == step_b == 4
    for x, y in zip(jax.tree.leaves(state_a), jax.tree.leaves(state_b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert rundir.read_metrics(whole / rundir.METRICS_FILE) == rundir.read_metrics(
        killed / rundir.METRICS_FILE
    )
    import json

    record = json.loads((killed / rundir.EVAL_FILE).read_text())
    assert record["physics"] == "native"


def test_physics_is_chosen_per_platform_and_refused_where_it_does_not_apply():
    from espl_jax import config as config_lib
    from espl_jax.config import UserError
    from espl_jax.learner import Trainer

    assert jax.default_backend() == "cpu"
    auto = Trainer(config_lib.resolve("hopper_params"))
    assert auto.physics == "native" and isinstance(auto.env, NativeEnv)
    mjx = Trainer(config_lib.resolve("hopper", physics="mjx"))
    assert mjx.physics == "mjx" and not isinstance(mjx.env, NativeEnv)
    assert Trainer(config_lib.resolve("cartpole")).physics is None
    with pytest.raises(UserError, match="MuJoCo tasks only"):
        _ = Trainer(config_lib.resolve("cartpole", physics="native")).env


def test_threads_step_the_same_lanes_bit_for_bit():
    """A batch split over host threads (each with its own MjData) equals one thread's result."""
    family = envs.make_family("walker2d_params", physics="native")
    train, _ = family.tasks(0)
    one, two = NativeEnv(family.env.task, threads=1), NativeEnv(family.env.task, threads=2)
    assert two.threads == 2
    lanes = 2 * LANES_PER_WORKER  # enough lanes for two workers
    tasks = jax.tree.map(lambda x: x[np.arange(lanes) % len(x)], train)
    rows = np.stack(
        [
            np.asarray(one.flat_params(jax.tree.map(lambda x, i=i: x[i], tasks)))
            for i in range(lanes)
        ]
    )
    keys = jax.random.split(jax.random.PRNGKey(3), lanes)
    _, state = jax.vmap(one.reset)(keys, tasks)
    states = from_words(np.asarray(state.physics))
    ctrl = np.random.default_rng(5).uniform(-1, 1, (lanes, one.action_dim))
    submit, used = two._pool.submit, []
    two._pool.submit = lambda fn, worker, lanes: used.append(worker) or submit(fn, worker, lanes)
    for _ in range(20):
        new_one, values_one = one.host_step64(states, ctrl, rows)
        new_two, values_two = two.host_step64(states, ctrl, rows)
        np.testing.assert_array_equal(new_one, new_two)
        np.testing.assert_array_equal(values_one, values_two)
        states = new_one
    assert used == [1] * 20  # the pool stepped the second worker's lanes, every step
