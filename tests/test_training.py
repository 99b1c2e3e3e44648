"""Training runs end to end (tiny budgets), resume, divergence, and SAC / replay unit checks.

The tiny config keeps compile and run time small. It still needs ~1000 updates per iteration:
the path selector moves p by about the learning rate per update, and an unpruned symbolic network
has a formula far too large for sympy to print. With it, the formulas keep ~10–30 paths.
Compiled executables go to a persistent cache shared by the runs of this session, so runs with
the same config compile once.
"""

import copy
import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import TINY, TINY_MLP, committed_checkpoints

from espl_jax import checkpoint, envs, faults, reference_eval, replay, rollout, run, rundir
from espl_jax import config as config_lib
from espl_jax.policies import MLPActor, PolicyConfig, tanh_gaussian_log_prob
from espl_jax.sac import SAC, SACConfig, TrainState
from espl_jax.task_sets import SingleTask

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.usefixtures("jax_cache")

METRIC_KEYS = {
    "iteration", "seed", "env_steps", "train_return", "l0_ratio", "penalty", "tau", "critic_loss",
}  # fmt: skip


def tiny(**overrides) -> config_lib.Config:
    return config_lib.from_mapping({**TINY, **overrides})


def load_params(run_dir):
    _, state, step = run.load_run(run_dir)
    return step, state


def assert_trees_equal(a, b):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# A full run, shared ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("full") / "run"
    result = run.train(tiny(), run_dir, show_progress=False)
    return run_dir, result


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory):
    """The same config stopped after 2 of 4 iterations (as if interrupted); copy before use."""
    run_dir = tmp_path_factory.mktemp("stopped") / "run"
    assert run.train(tiny(), run_dir, show_progress=False, stop_after=2) == {}
    return run_dir


def test_full_run_writes_every_artifact(full_run):
    run_dir, result = full_run
    cfg = tiny()
    assert config_lib.load(run_dir / "config.yaml") == cfg

    rows = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    assert len(rows) == cfg.iterations * cfg.seeds
    assert {(r["iteration"], r["seed"]) for r in rows} == {
        (i, s) for i in range(1, cfg.iterations + 1) for s in range(cfg.seeds)
    }
    for r in rows:
        assert set(r) >= METRIC_KEYS, set(r)
        assert r["env_steps"] == r["iteration"] * cfg.steps_per_iteration
        assert 0.0 <= r["l0_ratio"] <= 1.0
        chunk_end = r["iteration"] % cfg.chunk_iterations == 0
        assert ("eval_return" in r) == chunk_end
        assert all(math.isfinite(r[k]) for k in ("critic_loss", "penalty", "tau"))

    png = (run_dir / rundir.CURVE_FILE).read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 1000

    steps = sorted(int(p.name) for p in (run_dir / rundir.CHECKPOINT_DIR).iterdir())
    assert steps[-1] == cfg.iterations

    expression = (run_dir / rundir.EXPRESSION_FILE).read_text()
    assert expression.startswith("a0 = ") and "x" in expression

    record = json.loads((run_dir / rundir.EVAL_FILE).read_text())
    assert record == result
    assert record["env"] == "cartpole" and record["actor"] == "symbolic"
    best = record["best_seed"]
    assert best in range(cfg.seeds)
    assert record["jax_eval"]["episodes"] == cfg.eval_episodes
    assert record["evaluated_in"] == "jax"
    assert record["devices"] == {"count": 1, "platform": "cpu"}
    assert {"mean", "std", "min", "max"} <= set(record["jax_eval"])
    assert record["training"]["env_steps"] == cfg.total_env_steps
    assert record["training"]["iterations"] == cfg.iterations
    assert record["training"]["episodes"] > 0
    assert [e["seed"] for e in record["per_seed"]] == list(range(cfg.seeds))
    assert record["jax_eval"] == record["per_seed"][best]["jax_eval"]
    assert record["formula"] == record["per_seed"][best]["formula"] == expression.strip()
    assert record["length"] > 0
    assert record["reference_eval"]["episodes"] == cfg.reference_eval_episodes
    for summary in (record["jax_eval"], record["reference_eval"]):
        assert all(math.isfinite(summary[k]) for k in ("mean", "std", "min", "max"))
        assert summary["min"] >= 1.0  # cartpole pays 1 per step


def test_seeds_are_independent(full_run):
    run_dir, result = full_run
    _, state = load_params(run_dir)
    assert len(result["per_seed"]) == 2
    rows = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    assert {r["seed"] for r in rows} == {0, 1}
    for leaf in jax.tree.leaves((state.actor, state.critic)):
        assert leaf.shape[0] == 2
    assert not np.array_equal(state.actor["mean"]["w"][-1][0], state.actor["mean"]["w"][-1][1])
    assert not np.array_equal(
        jax.tree.leaves(state.critic)[0][0], jax.tree.leaves(state.critic)[0][1]
    )


def test_policy_py_is_the_network_under_the_eval_mask(full_run):
    run_dir, result = full_run
    trainer, state, step = run.load_run(run_dir)
    assert step == trainer.config.iterations
    np.testing.assert_array_equal(state.iteration, [trainer.config.iterations] * 2)
    best = result["best_seed"]
    actor_params = jax.tree.map(lambda x: np.asarray(x[best]), state.actor)
    actor, env = trainer.sac.actor, trainer.env
    mask = actor.eval_mask(actor_params)

    rng = np.random.default_rng(0)
    obs = rng.normal(scale=[0.5, 0.5, 0.1, 0.5], size=(16, 4)).astype(np.float32)
    tanh = jax.jit(jax.vmap(actor.deterministic, (None, None, 0)))(actor_params, mask, obs)
    expected = env.action_low + (np.asarray(tanh, np.float64) + 1.0) / 2 * (
        env.action_high - env.action_low
    )

    policy = reference_eval.load_policy(run_dir / rundir.POLICY_FILE)
    got = np.array([policy.act(o) for o in obs])
    assert got.shape == (16, 1)
    assert np.all(got >= env.action_low) and np.all(got <= env.action_high)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert len(np.unique(np.round(got, 4))) > 1, "the formula should depend on the observation"


def test_export_cli_writes_the_same_policy(full_run, tmp_path, jax_cache):
    run_dir, _ = full_run
    out = tmp_path / "policy.py"
    cmd = [sys.executable, "-m", "espl_jax.export", str(run_dir), "--format", "python"]
    proc = subprocess.run(
        [*cmd, "--output", str(out)],
        cwd=REPO, env={**os.environ, **jax_cache}, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert out.read_text() == (run_dir / rundir.POLICY_FILE).read_text()


# Resume ---------------------------------------------------------------------------------------


@pytest.mark.slow  # the extension test below resumes too, and compares with an unbroken run
def test_resume_is_bitwise_deterministic(full_run, stopped_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_run, run_dir)
    assert load_params(run_dir)[0] == 2
    before_resume = rundir.training_seconds_before(run_dir, 2)
    assert before_resume is not None and before_resume > 0
    result = run.train(tiny(), run_dir, resume=True, show_progress=False)
    # The reported time is both parts' (the first part's and the resumed one's), not the last.
    assert result["training"]["wall_seconds_training"] > before_resume
    assert sorted(json.loads((run_dir / rundir.TIMING_FILE).read_text())) == ["2", "4"]
    records = []

    full_dir, full_result = full_run
    step_a, state_a = load_params(full_dir)
    step_b, state_b = load_params(run_dir)
    assert step_a == step_b == 4
    for name in ("actor", "critic", "log_alpha"):
        assert_trees_equal(getattr(state_a, name), getattr(state_b, name))
    assert_trees_equal(state_a, state_b)  # optimizers, targets, buffer, env state and key too
    # The resumed run's records are those of the uninterrupted one.
    assert rundir.read_metrics(run_dir / rundir.METRICS_FILE) == rundir.read_metrics(
        full_dir / rundir.METRICS_FILE
    )
    for record in (result, full_result):
        record = copy.deepcopy(record)
        del record["training"]["wall_seconds_training"]
        records.append(record)
    assert records[0] == records[1]
    assert (run_dir / rundir.EXPRESSION_FILE).read_text() == (
        full_dir / rundir.EXPRESSION_FILE
    ).read_text()


def test_timing_file_keeps_the_time_of_each_checkpoint_a_resume_can_start_from(tmp_path):
    for iteration, seconds in ((2, 10.0), (4, 20.0), (6, 30.0)):
        rundir.record_training_seconds(tmp_path, iteration, seconds)
    assert rundir.training_seconds_before(tmp_path, 4) == 20.0
    # Resumed from 4: the part that had reached 6 is discarded with its time.
    rundir.record_training_seconds(tmp_path, 6, 25.0)
    rundir.record_training_seconds(tmp_path, 8, 35.0)
    assert json.loads((tmp_path / rundir.TIMING_FILE).read_text()) == {
        "2": 10.0, "4": 20.0, "6": 25.0, "8": 35.0,
    }  # fmt: skip
    assert rundir.training_seconds_before(tmp_path, 3) is None
    (tmp_path / rundir.TIMING_FILE).write_text('{"2": 1')  # cut short: unknown, not an error
    assert rundir.training_seconds_before(tmp_path, 2) is None


@pytest.mark.slow  # recompiles the chunk for the new reward scale
def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(stopped_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_run, run_dir)
    path = run_dir / "config.yaml"
    values = yaml.safe_load(path.read_text())
    values["reward_scale"] = 1.0e38
    path.write_text(yaml.safe_dump(values))
    cfg = config_lib.load(path)
    assert cfg.reward_scale == 1e38  # Q targets of ~1e38 square to inf in float32
    with pytest.raises(run.TrainingDiverged) as err:
        run.train(cfg, run_dir, resume=True, show_progress=False)
    message = str(err.value)
    assert "non-finite at iteration 3" in message
    assert "last good checkpoint (iteration 2) is kept" in message
    assert isinstance(err.value, config_lib.UserError)  # the CLI prints it without a traceback
    _, state, step = run.load_run(run_dir)
    assert step == 2
    np.testing.assert_array_equal(state.iteration, [2, 2])
    assert all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(state.critic))
    # The failing chunk's rows are kept, so the user can see what diverged.
    rows = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    assert max(r["iteration"] for r in rows) == 4
    assert any(not math.isfinite(r["critic_loss"]) for r in rows if r["iteration"] == 3)
    assert "critic_loss" in message or "q became" in message
    assert not (run_dir / rundir.EVAL_FILE).exists()


@pytest.mark.slow
def test_resume_after_kill_9(tmp_path, jax_cache):
    """A real SIGKILL mid-run, then ``--resume``: the same final state as an uninterrupted run."""
    cfg = tiny(iterations=8, chunk_iterations=1)
    config_file = tmp_path / "tiny.yaml"
    config_lib.save(cfg, config_file)
    killed = tmp_path / "killed"
    cmd = [sys.executable, "-m", "espl_jax.train", "--no-progress"]
    env = {**os.environ, **jax_cache}
    proc = subprocess.Popen(
        [*cmd, "--config", str(config_file), "--out", str(killed)],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 900
        while not committed_checkpoints(killed / rundir.CHECKPOINT_DIR) & {2, 3, 4, 5, 6}:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "no checkpoint >= 2 in time"
            time.sleep(0.2)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (killed / rundir.EVAL_FILE).exists()

    resumed = subprocess.run(
        [*cmd, "--resume", str(killed)], cwd=REPO, env=env, capture_output=True, text=True,
        timeout=1200,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    reference = tmp_path / "uninterrupted"
    run.train(cfg, reference, show_progress=False)

    step_a, state_a = load_params(reference)
    step_b, state_b = load_params(killed)
    assert step_a == step_b == 8
    for name in ("actor", "critic", "log_alpha"):
        assert_trees_equal(getattr(state_a, name), getattr(state_b, name))
    assert rundir.read_metrics(killed / rundir.METRICS_FILE) == rundir.read_metrics(
        reference / rundir.METRICS_FILE
    )


def _killed_at(point: str, tmp_path: Path, jax_cache: dict) -> Path:
    """A CLI run of the tiny config SIGKILLed at a named kill point (espl_jax.faults)."""
    config_file = tmp_path / "tiny.yaml"
    config_lib.save(tiny(), config_file)
    killed = tmp_path / "killed"
    env = {**os.environ, **jax_cache, faults.ENV_VAR: point}
    proc = subprocess.run(
        [sys.executable, "-m", "espl_jax.train", "--no-progress", "--config", str(config_file),
         "--out", str(killed)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    return killed


def _resume_cli(run_dir: Path, jax_cache: dict) -> None:
    resumed = subprocess.run(
        [sys.executable, "-m", "espl_jax.train", "--no-progress", "--resume", str(run_dir)],
        cwd=REPO, env={**os.environ, **jax_cache}, capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr


def _assert_same_finished_run(a: Path, b: Path) -> None:
    step_a, state_a = load_params(a)
    step_b, state_b = load_params(b)
    assert step_a == step_b
    assert_trees_equal(state_a, state_b)
    assert rundir.read_metrics(a / rundir.METRICS_FILE) == rundir.read_metrics(
        b / rundir.METRICS_FILE
    )
    for name in (rundir.EXPRESSION_FILE, rundir.POLICY_FILE):  # absent for the MLP actor
        assert (a / name).is_file() == (b / name).is_file()
        if (a / name).is_file():
            assert (a / name).read_text() == (b / name).read_text()
    records = [json.loads((d / rundir.EVAL_FILE).read_text()) for d in (a, b)]
    for record in records:
        del record["training"]["wall_seconds_training"]
    assert records[0] == records[1]


@pytest.mark.slow
def test_kill_during_a_checkpoint_write_then_resume(full_run, tmp_path, jax_cache):
    """SIGKILL while the checkpoint of iteration 4 is written: it is never committed, the
    resume restarts from iteration 2 and ends where the uninterrupted run ends."""
    killed = _killed_at("checkpoint-write:4", tmp_path, jax_cache)
    assert committed_checkpoints(killed / rundir.CHECKPOINT_DIR) == {0, 2}  # the initial state, 2
    assert not (killed / rundir.EVAL_FILE).exists()
    _resume_cli(killed, jax_cache)
    _assert_same_finished_run(full_run[0], killed)


def test_kill_during_the_final_export_then_resume(full_run, tmp_path, jax_cache):
    """SIGKILL after eval.json, expression.txt and policy.py are written but before the reference
    evaluation: the formula is already saved, and the resume completes the export."""
    killed = _killed_at("export", tmp_path, jax_cache)
    record = json.loads((killed / rundir.EVAL_FILE).read_text())
    assert "formula" in record and "reference_eval" not in record
    assert (killed / rundir.POLICY_FILE).is_file()
    _resume_cli(killed, jax_cache)
    _assert_same_finished_run(full_run[0], killed)


def _extended_equals_planned(config: config_lib.Config, finished: Path, tmp_path: Path) -> None:
    """``--resume RUN --iterations N+2`` on a finished N-iteration run: the replay buffer (sized
    by the run's total steps) grows, and the result is the (N+2)-iteration run's, bit for bit."""
    longer = config.iterations + 2
    extended = tmp_path / "extended"
    shutil.copytree(finished, extended)
    resumed = run.resume_config(extended, iterations=longer)
    assert resumed == dataclasses.replace(config, iterations=longer)
    run.train(resumed, extended, resume=True, show_progress=False)
    assert config_lib.load(extended / "config.yaml") == resumed
    planned = tmp_path / "planned"
    run.train(resumed, planned, show_progress=False)
    _assert_same_finished_run(planned, extended)


def test_extending_a_finished_run_equals_a_run_planned_that_long(tmp_path):
    """The extension on the MLP actor, which compiles in seconds: the buffer resize and the
    resumed schedule are the trainer's, the same for every actor kind (the symbolic run is the
    slow test below)."""
    config = config_lib.from_mapping(TINY_MLP)
    finished = tmp_path / "finished"
    run.train(config, finished, show_progress=False)
    _extended_equals_planned(config, finished, tmp_path)


@pytest.mark.slow  # two more symbolic iterations and a 6-iteration run: 2–5 min
def test_extending_a_finished_symbolic_run_equals_a_run_planned_that_long(full_run, tmp_path):
    _extended_equals_planned(tiny(), full_run[0], tmp_path)


def test_failing_reference_evaluation_is_a_warning_and_loses_nothing(
    full_run, tmp_path, monkeypatch
):
    run_dir = tmp_path / "run"
    shutil.copytree(full_run[0], run_dir)

    def broken(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'imageio'")

    monkeypatch.setattr(reference_eval, "rollout_returns", broken)
    result = run.train(tiny(), run_dir, resume=True, show_progress=False)
    assert "reference_eval" not in result
    assert result["warnings"] == [
        "reference evaluation of policy.py failed: ModuleNotFoundError: No module named 'imageio'"
    ]
    assert json.loads((run_dir / rundir.EVAL_FILE).read_text()) == result
    assert (run_dir / rundir.POLICY_FILE).read_text() == (
        full_run[0] / rundir.POLICY_FILE
    ).read_text()


# The neural baseline -----------------------------------------------------------------------------


@pytest.mark.slow
def test_mlp_actor_run_has_no_formula(tmp_path):
    cfg = config_lib.from_mapping(TINY_MLP)
    result = run.train(cfg, tmp_path, show_progress=False)
    record = json.loads((tmp_path / rundir.EVAL_FILE).read_text())
    assert record == result
    assert record["actor"] == "mlp"
    assert "formula" not in record and "reference_eval" not in record
    assert all("formula" not in e for e in record["per_seed"])
    assert math.isfinite(record["jax_eval"]["mean"])
    assert not (tmp_path / rundir.POLICY_FILE).exists()
    assert not (tmp_path / rundir.EXPRESSION_FILE).exists()
    rows = rundir.read_metrics(tmp_path / rundir.METRICS_FILE)
    assert len(rows) == cfg.iterations and all(r["l0_ratio"] == 1.0 for r in rows)


# SAC, replay and the policy distribution: unit checks without training -----------------------


# The update's view of a single task (its batches, its (0,) latent): no env needed.
ONE_TASK = SingleTask(env=None, steps_per_iteration=0, buffer_capacity=0, exploration_correlation=0)


def _mlp_sac(**overrides):
    cfg = config_lib.from_mapping(
        {"actor": "mlp", "critic_hidden": [16, 16], "std_hidden": [8], "mlp_actor_hidden": [8],
         **overrides}
    )  # fmt: skip
    actor = MLPActor(config_lib.view(PolicyConfig, cfg), obs_dim=4, action_dim=1)
    return SAC(config_lib.view(SACConfig, cfg), actor, ONE_TASK)


def test_critic_target_bootstraps_unless_terminated():
    gamma, scale = 0.9, 2.0
    sac = _mlp_sac(gamma=gamma, reward_scale=scale)
    learner = sac.init_learner(jax.random.PRNGKey(0))
    z = jnp.zeros((0,))
    # A target critic that differs from the critic, and α ≠ 1, so every term of y matters.
    learner["target_critic"] = sac.critic.init(jax.random.PRNGKey(7), jnp.zeros(4), jnp.zeros(1), z)
    learner["log_alpha"] = jnp.asarray(-0.7)
    state = TrainState(
        **learner, buffer=None, encoder_buffer=None, rollout=None, key=None,
        iteration=None, env_steps=None, episodes=None,
    )  # fmt: skip
    rng = np.random.default_rng(0)
    obs, next_obs = (jnp.asarray(rng.normal(size=(1, 1, 4)), jnp.float32) for _ in range(2))
    action, reward = jnp.asarray([[[0.3]]]), jnp.asarray([[0.7]])  # [tasks, batch, ...]
    key = jax.random.PRNGKey(3)

    @jax.jit
    def loss(terminated):
        batch = replay.Transition(obs, action, reward, next_obs, terminated)
        return sac.critic_loss(state.critic, None, state, batch, None, key)[0]

    bootstrapped = float(loss(jnp.asarray([[False]])))
    terminal = float(loss(jnp.asarray([[True]])))

    # The soft value of s' from the same key: min of the target Qs minus α log π.
    _, k_act = jax.random.split(key)
    a2, log_prob, _ = sac.actor.sample(
        jax.random.split(k_act, 1)[0], state.actor, None, next_obs[0, 0]
    )
    soft_next = float(
        sac.critic.apply(state.target_critic, next_obs[0, 0], a2, z).min() - np.exp(-0.7) * log_prob
    )
    q = np.asarray(sac.critic.apply(state.critic, obs[0, 0], action[0, 0], z), np.float64)
    y_terminal = scale * 0.7
    np.testing.assert_allclose(terminal, np.sum((q - y_terminal) ** 2), rtol=1e-5)
    np.testing.assert_allclose(
        bootstrapped, np.sum((q - y_terminal - gamma * soft_next) ** 2), rtol=1e-5
    )
    assert abs(gamma * soft_next) > 1e-3  # the two cases really differ


def _collect(cfg, env, zero_actor=False):
    """One collection of ``cfg.steps_per_iteration`` steps of a fresh MLP actor in ``env``."""
    actor = MLPActor(config_lib.view(PolicyConfig, cfg), env.obs_dim, env.action_dim)
    params = actor.init(jax.random.PRNGKey(0))
    if zero_actor:
        params = jax.tree.map(jnp.zeros_like, params)
    start = rollout.reset(env, env.default_params, jax.random.PRNGKey(2), env.action_dim)

    @jax.jit
    def run_collect(r, key):
        return rollout.collect(
            env, actor, cfg.exploration_correlation, r, env.default_params, params,
            jnp.zeros((0,)), None, key,
            cfg.steps_per_iteration,
        )  # fmt: skip

    _, transitions, done, _ = run_collect(start, jax.random.PRNGKey(1))
    return transitions, np.asarray(done)


def test_truncation_is_stored_as_not_terminated():
    """Time-limit ends reset the env but are not ``terminated``: the critic bootstraps there."""
    cfg = config_lib.from_mapping(
        {**TINY_MLP, "steps_per_iteration": 12, "buffer_size": 12, "iterations": 1}
    )
    transitions, done = _collect(cfg, envs.make("cartpole", horizon=5))
    assert int(done.sum()) == 2  # truncated after steps 5 and 10
    assert not np.asarray(transitions.terminated).any()
    obs, next_obs = np.asarray(transitions.obs), np.asarray(transitions.next_obs)
    continues = np.all(next_obs[:-1] == obs[1:], axis=1)
    # next_obs at a truncation is the true next state, not the reset observation.
    np.testing.assert_array_equal(np.flatnonzero(~continues), [4, 9])


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_exploration_noise_is_standard_normal_with_lag_one_correlation_rho(rho):
    """Collection's ε (recovered from the actions) is N(0, 1) per step, with autocorrelation ρ."""
    steps = 4000
    cfg = config_lib.from_mapping(
        {**TINY_MLP, "env": "pendulum", "steps_per_iteration": steps, "buffer_size": steps,
         "iterations": 1, "exploration_correlation": rho}
    )  # fmt: skip
    # A zero actor has μ = 0 and σ = exp(0) = 1, so the action is tanh(ε): ε = artanh(a).
    transitions, _ = _collect(cfg, envs.make("pendulum"), zero_actor=True)
    eps = np.arctanh(np.asarray(transitions.action, np.float64)[:, 0])
    assert np.all(np.isfinite(eps))
    assert abs(eps.mean()) < 0.2 and abs(eps.std() - 1.0) < 0.1
    lag1 = np.corrcoef(eps[1:], eps[:-1])[0, 1]
    assert abs(lag1 - rho) < 0.05


def test_checkpoint_round_trip_keeps_zero_size_arrays(tmp_path):
    """MJX env states hold zero-size arrays (``data.act``), which orbax alone refuses to save."""
    state = {"a": jnp.arange(3.0), "empty": jnp.zeros((2, 0)), "none": None}
    with checkpoint.manager(tmp_path / "ckpt") as mngr:
        checkpoint.save(mngr, 1, state)
    step, restored = checkpoint.restore_latest(tmp_path / "ckpt", state)
    assert step == 1 and restored["none"] is None
    assert restored["empty"].shape == (2, 0) and restored["empty"].dtype == jnp.float32
    np.testing.assert_array_equal(restored["a"], state["a"])


def test_replay_insert_wraps_and_size_saturates():
    buffer = replay.init(tasks=1, capacity=6, obs_dim=2, action_dim=1)
    task = jnp.zeros(1, jnp.int32)

    def batch(start):
        r = jnp.arange(start, start + 2, dtype=jnp.float32)
        t = replay.Transition(
            jnp.stack([r, r], 1), r[:, None], r, jnp.stack([r, r], 1) + 1, r > 100
        )
        return jax.tree.map(lambda x: x[None], t)

    insert = jax.jit(lambda b, t: replay.insert(b, task, t))
    sizes, positions = [], []
    for k in range(4):
        buffer = insert(buffer, batch(10 * k))
        sizes.append(int(buffer.size[0]))
        positions.append(int(buffer.position[0]))
    assert sizes == [2, 4, 6, 6]
    assert positions == [2, 4, 0, 2]
    # The fourth batch overwrote the oldest entries (indices 0 and 1), the rest is kept.
    np.testing.assert_array_equal(buffer.data.reward[0], [30, 31, 10, 11, 20, 21])
    np.testing.assert_array_equal(buffer.data.obs[0, :, 0], buffer.data.reward[0])

    sample = jax.jit(lambda b, k, n: replay.sample(b, task, k[None], n), static_argnums=2)
    partial = insert(replay.init(1, 6, 2, 1), batch(50))
    drawn = sample(partial, jax.random.PRNGKey(0), 64)
    assert set(np.asarray(drawn.reward).ravel().tolist()) == {50.0, 51.0}  # only valid entries
    full = sample(buffer, jax.random.PRNGKey(0), 256)
    assert set(np.asarray(full.reward).ravel().tolist()) == {30, 31, 10, 11, 20, 21}
    np.testing.assert_array_equal(full.next_obs[..., 0], full.reward + 1)  # rows stay aligned
    assert replay.capacity_for(10, 4) == 12 and replay.capacity_for(8, 4) == 8


def test_tanh_gaussian_log_prob_matches_numpy():
    rng = np.random.default_rng(0)
    u = rng.uniform(-3, 3, size=(50, 3))
    mean = rng.normal(size=(50, 3))
    log_std = rng.uniform(-2, 1, size=(50, 3))
    std = np.exp(log_std)
    gauss = -0.5 * ((u - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    expected = np.sum(gauss - np.log(1 - np.tanh(u) ** 2), axis=-1)
    got = jax.jit(tanh_gaussian_log_prob)(
        *(jnp.asarray(a, jnp.float32) for a in (u, mean, log_std))
    )
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)


def test_tanh_gaussian_log_prob_squash_epsilon_is_rlkits_and_bounded():
    # rlkit's TanhNormal: log(1 - tanh(u)^2 + eps); at |u| = 40 the exact term is -2|u| per dim,
    # while with eps it floors at log(eps): the entropy bonus stays bounded for saturated means.
    u = np.array([[-40.0, -3.0, 0.5], [0.0, 2.0, 40.0]])
    mean = np.array([[-39.0, -2.5, 0.0], [0.3, 1.0, 41.0]])
    log_std = np.zeros_like(u)
    gauss = -0.5 * (u - mean) ** 2 - 0.5 * np.log(2 * np.pi)
    expected = np.sum(gauss - np.log(1 - np.tanh(u) ** 2 + 1e-6), axis=-1)
    args = (jnp.asarray(a, jnp.float32) for a in (u, mean, log_std))
    got = jax.jit(tanh_gaussian_log_prob, static_argnums=3)(*args, 1e-6)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-3)
    exact = tanh_gaussian_log_prob(*(jnp.asarray(a, jnp.float32) for a in (u, mean, log_std)))
    assert float(exact[1]) > float(got[1]) + 50  # the unbounded term the epsilon removes


def test_eval_json_names_the_seed_that_trains_the_chosen_one_alone(capsys):
    # best_seed indexes the run's seeds; with --seed 3 --seeds 2, index 1 is --seed 4's key.
    from types import SimpleNamespace

    from espl_jax import train
    from espl_jax.learner import Trainer

    trainer = Trainer(config_lib.resolve("cartpole", seed=3, seeds=2))
    ones = np.ones(2, np.int32)
    state = SimpleNamespace(episodes=ones, env_steps=ones, iteration=ones)
    head = rundir.result_header(trainer, state, 1, 0.0)
    assert (head["best_seed"], head["train_seed"]) == (1, 4)
    train.print_single_task({**head, "formula": "a0 = x2", "length": 3, "jax_eval": {
        "episodes": 10, "mean": 1.0, "std": 0.0}, "evaluated_in": "jax"})  # fmt: skip
    assert "formula (seed 4, length 3)" in capsys.readouterr().out
