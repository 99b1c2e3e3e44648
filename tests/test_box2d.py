"""Box2D envs (gymnasium, stepped on the host behind the ``Environment`` interface) through the
one rollout path: env descriptions, collection (transitions, truncation, resets, one host call per
step), states that outlive their host envs, evaluation, PEARL's protocol on lunarlander_params, and
lunarlander training runs (resume, divergence, and every artifact of a symbolic run).

Collection and run-loop checks use the MLP actor (conftest's TINY_MLP), which compiles in seconds;
the symbolic run uses conftest's TINY config and is marked slow (see below).
"""

import json
import math
import shutil

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import TINY, TINY_MLP

from espl_jax import checkpoint, envs, reference_eval, rollout, run, rundir
from espl_jax import config as config_lib
from espl_jax.envs.reference import reference_env
from espl_jax.learner import Trainer
from espl_jax.policies import MLPActor, PolicyConfig

pytestmark = pytest.mark.usefixtures("jax_cache")
GYMNASIUM = {
    "lunarlander": ("LunarLander-v3", {"continuous": True}),
    "bipedalwalker": ("BipedalWalker-v3", {}),
}


def tiny(**overrides) -> config_lib.Config:
    return config_lib.from_mapping({**TINY, "env": "lunarlander", **overrides})


# Env descriptions ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, env_id, obs_dim, action_dim, horizon",
    [("lunarlander", "LunarLander", 8, 2, 1000), ("bipedalwalker", "BipedalWalker", 24, 4, 1600)],
)
def test_box2d_envs_are_registered_host_envs(name, env_id, obs_dim, action_dim, horizon):
    env = envs.make(name)
    assert name in envs.KNOWN_ENVS and isinstance(env, envs.HostEnv)
    assert isinstance(env, envs.Environment) and env.simulator == "gymnasium"
    assert (env.obs_dim, env.action_dim, env.horizon) == (obs_dim, action_dim, horizon)
    np.testing.assert_array_equal(env.action_low, -np.ones(action_dim))
    np.testing.assert_array_equal(env.action_high, np.ones(action_dim))
    reference = reference_env(name)
    assert reference.spec.name == env_id and reference.spec.max_episode_steps == horizon
    assert reference.observation_space.shape == (obs_dim,)
    if name == "lunarlander":
        assert reference.unwrapped.continuous
    reference.close()
    assert envs.make(name, horizon=7).horizon == 7
    assert envs.make("cartpole").simulator == "jax"


def test_unknown_env_lists_the_box2d_envs():
    with pytest.raises(ValueError, match="lunarlander") as err:
        envs.make("lunarlandr")
    assert "bipedalwalker" in str(err.value) and "cartpole" in str(err.value)


def test_to_env_action_clips_and_zeroes_non_finite():
    env = envs.make("lunarlander")
    got = env.to_env_action(np.array([[0.5, -2.0], [np.nan, np.inf]]))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, [[0.5, -1.0], [0.0, 1.0]])


# Collection through the one rollout path ------------------------------------------------------


def _collect(name: str, steps: int, horizon: int, seeds: int = 2):
    """``steps`` collection steps (``rollout.collect``, jitted, vmapped over seeds) of an MLP
    actor in ``name`` with a time limit of ``horizon``; also the gymnasium seed of every reset
    (drawn, as the env does, from each step's reset key)."""
    cfg = config_lib.from_mapping({**TINY_MLP, "env": name})
    env = envs.make(name, horizon=horizon)
    actor = MLPActor(config_lib.view(PolicyConfig, cfg), env.obs_dim, env.action_dim)
    params = actor.init(jax.random.PRNGKey(0))
    start_keys = jax.random.split(jax.random.PRNGKey(2), seeds)
    keys = jax.random.split(jax.random.PRNGKey(1), seeds)
    start = jax.jit(jax.vmap(lambda k: rollout.reset(env, env.default_params, k, env.action_dim)))(
        start_keys
    )

    def one(r, key):
        return rollout.collect(
            env, actor, 0.0, r, env.default_params, params, jnp.zeros((0,)), None, key, steps
        )

    calls = env.episodes.calls
    end, transitions, done, finished = jax.block_until_ready(jax.jit(jax.vmap(one))(start, keys))
    calls = env.episodes.calls - calls
    # rollout.collect's key schedule: split(key, steps), then (act, env, reset) per step
    reset_keys = jax.vmap(lambda k: jax.vmap(lambda k_t: jax.random.split(k_t, 3)[2])(
        jax.random.split(k, steps)))(keys)  # fmt: skip
    reset_seeds = np.asarray(jax.vmap(jax.vmap(env._seed))(reset_keys))
    first_seeds = np.asarray(start.env_state.seed)
    return env, start, end, transitions, np.asarray(done), np.asarray(finished), (
        first_seeds, reset_seeds, calls)  # fmt: skip


@pytest.mark.parametrize("name, horizon", [("lunarlander", 80), ("bipedalwalker", 60)])
def test_collected_transitions_replay_in_gymnasium(name, horizon):
    """Every stored (obs, action, reward, next_obs, terminated) is what gymnasium gives for that
    action; ``terminated`` excludes truncation and next_obs at an episode end is the true final
    observation, not the reset one; every episode is reset with the seed of its reset key. The
    whole seed batch steps in one host call per env step."""
    steps = 300
    env, start, end, tr, done, finished_returns, (first, reset_seeds, calls) = _collect(
        name, steps, horizon
    )
    assert calls == steps  # one host call per env step for both seeds
    obs, action, reward, next_obs, terminated = (
        np.asarray(x) for x in (tr.obs, tr.action, tr.reward, tr.next_obs, tr.terminated)
    )
    assert obs.shape == (2, steps, env.obs_dim)
    assert action.shape == (2, steps, env.action_dim)
    truncations = terminations = 0
    for s in range(2):
        env_id, kwargs = GYMNASIUM[name]
        gym_env = gymnasium.make(env_id, max_episode_steps=horizon, **kwargs)
        current, _ = gym_env.reset(seed=int(first[s]))
        np.testing.assert_array_equal(np.asarray(start.obs[s]), current)
        episode_return = 0.0
        for t in range(steps):
            np.testing.assert_array_equal(obs[s, t], current)
            o, r, term, trunc, _ = gym_env.step(env.to_env_action(action[s, t]))
            np.testing.assert_array_equal(next_obs[s, t], o)
            assert reward[s, t] == np.float32(r)
            assert terminated[s, t] == term and done[s, t] == (term or trunc)
            episode_return += float(r)
            assert finished_returns[s, t] == pytest.approx(
                episode_return if term or trunc else 0.0, rel=1e-5, abs=1e-3
            )
            current = o
            if term or trunc:
                truncations += trunc and not term  # TimeLimit may flag both at once
                terminations += term
                current, _ = gym_env.reset(seed=int(reset_seeds[s, t]))
                episode_return = 0.0
                if t + 1 < steps:  # the next stored obs is the reset one, not next_obs
                    assert not np.array_equal(obs[s, t + 1], next_obs[s, t])
        gym_env.close()
        np.testing.assert_array_equal(np.asarray(end.obs[s]), current)
    assert truncations > 0
    if name == "lunarlander":
        assert terminations > 0  # random actions crash the lander within 80 steps sometimes
    assert done.sum() == truncations + terminations


def test_a_state_continues_alike_without_its_live_envs():
    """The env state determines the episode: with the host's gymnasium envs gone (a restored
    checkpoint), stepping a state replays its actions and continues exactly as before."""
    env, _, end, *_ = _collect("lunarlander", 120, 1000, seeds=3)
    actions = jax.random.uniform(jax.random.PRNGKey(7), (50, 3, 2), minval=-1, maxval=1)

    @jax.jit
    def run(state):
        def step(s, a):
            out = jax.vmap(env.step, (None, 0, 0, None))(
                jax.random.PRNGKey(0), s, a, env.default_params
            )
            return out[1], out[:1] + out[2:5]

        return jax.lax.scan(step, state, actions)

    live = jax.block_until_ready(run(end.env_state))
    env.episodes.close()  # as in a new process
    replays = env.episodes.replays
    again = jax.block_until_ready(run(end.env_state))
    assert env.episodes.replays - replays == 3  # each lane replayed once, then stepped live
    for a, b in zip(jax.tree.leaves(live), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)


def test_steps_after_an_episode_end_leave_it_as_it_ended():
    """``step`` after the end: reward 0, the same observation and flags, no host work."""
    env = envs.make("lunarlander", horizon=3)
    obs, state = env.reset(jax.random.PRNGKey(0), env.default_params)
    step = jax.jit(lambda s: env.step(jax.random.PRNGKey(0), s, jnp.zeros(2), env.default_params))
    for _ in range(3):
        obs, state, reward, terminated, truncated, _ = step(state)
    assert bool(truncated) and not bool(terminated)
    again = step(state)
    np.testing.assert_array_equal(again[0], obs)
    assert float(again[2]) == 0.0 and bool(again[4]) and not bool(again[3])
    assert int(again[1].t) == 3 and not env.episodes.live  # the ended episode was released


# Meta-RL on a Box2D family -------------------------------------------------------------------

LUNAR_META = {
    "env": "lunarlander_params", "actor": "pearl", "seeds": 2, "iterations": 1,
    "updates_per_iteration": 2, "meta_batch": 3, "batch_size": 8, "context_batch": 6,
    "initial_steps": 30, "tasks_per_iteration": 3, "prior_steps": 20, "posterior_steps": 25,
    "task_buffer_size": 200, "critic_hidden": [16], "encoder_hidden": [16],
    "pearl_hidden": [16], "eval_steps": 40, "eval_runs": 2,
}  # fmt: skip


def test_meta_collection_and_protocol_on_lunarlander_params_step_the_batch_together():
    """PEARL's warm-up, collection phases and test-task protocol on the Box2D family run through
    the one rollout path (``Trainer.warmup``, ``MetaTasks.collect_tasks``, ``adapt``): one host
    call per env step for all seeds × tasks (× runs), the tasks' gravity in each env."""
    trainer = Trainer(config_lib.from_mapping(LUNAR_META))
    env, n = trainer.env, trainer.task_set.num_train
    state = trainer.init_seeds()

    def calls(fn, *args):
        before = env.episodes.calls
        out = jax.block_until_ready(fn(*args))
        return out, env.episodes.calls - before

    state, warm_calls = calls(trainer.compiled_warmup(), state)
    assert warm_calls == 30  # 2 seeds × 40 tasks per call
    np.testing.assert_array_equal(state.buffer.size, np.full((2, n), 30))
    (state, metrics), phase_calls = calls(
        trainer.seed_axis.over_seeds(
            lambda s: trainer.task_set.collect_tasks(trainer.actor, s, s.key)
        ),
        state,
    )
    assert phase_calls == 20 + 25  # prior and posterior phase, 2 seeds × 3 tasks per call
    assert np.asarray(state.buffer.size).sum() == 2 * (n * 30 + 3 * 45)
    # Every training task was stepped with its own gravity: one gymnasium env per task's params.
    gravities = {k[1] for k in env.episodes.live} | set(env.episodes.free)
    assert len(gravities) == n

    test = trainer.tasks[1]
    keys = jax.vmap(jax.random.fold_in, (0, None))(state.key, 3)
    out, protocol_calls = calls(trainer.compiled_adapt, state, test, keys)
    assert protocol_calls == 40 + env.horizon  # 2 seeds × 10 tasks × 2 runs per call
    assert out.final_return.shape == (2, 10, 2) and np.all(np.isfinite(out.final_return))
    assert np.all(np.asarray(out.trajectories) >= 1)
    again = trainer.compiled_adapt(state, test, keys)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)  # seeded: repeatable


# Training runs ---------------------------------------------------------------------------------
# The symbolic TINY run compiles for ~1.5–2.5 min on a busy 2-core CPU (the symbolic network's
# init, Bernoulli masks and update scan), so its artifact checks are marked slow; the host loop,
# checkpoints, resume and divergence are checked with the MLP actor, which compiles in seconds.


def tiny_mlp(**overrides) -> config_lib.Config:
    return config_lib.from_mapping(
        {**TINY_MLP, "env": "lunarlander", "seeds": 2, "chunk_iterations": 1, **overrides}
    )


@pytest.fixture(scope="module")
def stopped_mlp_run(tmp_path_factory):
    """A 2-iteration MLP run on lunarlander stopped after 1 (as if interrupted); copy before use."""
    run_dir = tmp_path_factory.mktemp("stopped") / "run"
    assert run.train(tiny_mlp(), run_dir, show_progress=False, stop_after=1) == {}
    return run_dir


def test_host_run_resumes_as_if_never_stopped(stopped_mlp_run, tmp_path):
    """The checkpoint holds the Box2D episodes in progress (``envs/box2d.py``): a resumed run
    replays them and ends as the uninterrupted run does, bit for bit."""
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_mlp_run, run_dir)
    cfg = tiny_mlp()
    stopped_rows = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    assert [r["iteration"] for r in stopped_rows] == [1, 1]
    _, stopped, step = run.load_run(run_dir)
    assert step == 1 and np.all(np.asarray(stopped.rollout.env_state.t) > 0)
    np.testing.assert_array_equal(stopped.iteration, [1, 1])

    result = run.train(cfg, run_dir, resume=True, show_progress=False)
    whole = tmp_path / "whole"
    expected = run.train(cfg, whole, show_progress=False)
    for record in (result, expected):
        record["training"].pop("wall_seconds_training")
    assert result == expected
    assert rundir.read_metrics(run_dir / rundir.METRICS_FILE) == rundir.read_metrics(
        whole / rundir.METRICS_FILE
    )
    (_, state, step), (_, ref, _) = run.load_run(run_dir), run.load_run(whole)
    assert step == 2
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(ref), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(state.env_steps, [2 * 64, 2 * 64])

    record = json.loads((run_dir / rundir.EVAL_FILE).read_text())
    assert record["env"] == "lunarlander" and record["actor"] == "mlp"
    assert record["jax_eval"]["episodes"] == cfg.eval_episodes
    assert record["evaluated_in"] == "gymnasium"
    assert record["training"]["env_steps"] == cfg.total_env_steps
    assert "formula" not in record and not (run_dir / rundir.POLICY_FILE).exists()
    assert (run_dir / rundir.CURVE_FILE).read_bytes().startswith(b"\x89PNG\r\n\x1a\n")


def test_a_checkpoint_without_box2d_episodes_resumes_from_fresh_envs(stopped_mlp_run, tmp_path):
    """Checkpoints written before the Box2D envs held their episodes in the state (rollout
    ``env_state`` None) still resume, from freshly reset envs, as they did then."""
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_mlp_run, run_dir)
    trainer, stopped, step = run.load_run(run_dir)
    old = stopped.replace(rollout=stopped.rollout.replace(env_state=None))
    shutil.rmtree(run_dir / rundir.CHECKPOINT_DIR / "1")
    with checkpoint.manager(run_dir / rundir.CHECKPOINT_DIR) as mngr:
        checkpoint.save(mngr, 1, old)  # as the former host driver wrote it
    _, restored, step = run.load_run(run_dir)
    fresh = trainer.init_seeds().rollout
    assert step == 1
    for a, b in zip(jax.tree.leaves(restored.rollout), jax.tree.leaves(fresh), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree.leaves(restored.actor), jax.tree.leaves(stopped.actor), strict=True):
        np.testing.assert_array_equal(a, b)  # the rest is the checkpoint's
    run.train(tiny_mlp(), run_dir, resume=True, show_progress=False)  # and trains on


def test_non_finite_loss_stops_a_host_run(stopped_mlp_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_mlp_run, run_dir)
    path = run_dir / "config.yaml"
    values = yaml.safe_load(path.read_text())
    values["reward_scale"] = 1.0e38  # Q targets of ~1e38 square to inf in float32
    path.write_text(yaml.safe_dump(values))
    with pytest.raises(run.TrainingDiverged, match="last good checkpoint \\(iteration 1\\)"):
        run.train(config_lib.load(path), run_dir, resume=True, show_progress=False)
    assert run.load_run(run_dir)[2] == 1
    assert not (run_dir / rundir.EVAL_FILE).exists()


def test_evaluation_plays_distinct_seeded_episodes():
    trainer = Trainer(tiny_mlp())
    state = trainer.init_seeds()
    evaluate = trainer.compiled_evaluate(3)
    keys = jax.vmap(jax.random.fold_in, (0, None))(state.key, 2)
    returns = np.asarray(evaluate(state.actor, keys))
    assert returns.shape == (2, 3) and np.all(np.isfinite(returns))
    np.testing.assert_array_equal(evaluate(state.actor, keys), returns)  # seeded: repeatable
    assert len(np.unique(returns)) == returns.size  # distinct episodes
    other = evaluate(state.actor, jax.vmap(jax.random.fold_in, (0, None))(state.key, 3))
    assert not np.array_equal(other, returns)  # other keys, other episodes


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("lunarlander") / "run"
    return run_dir, run.train(tiny(), run_dir, show_progress=False)


@pytest.mark.slow
def test_run_writes_every_artifact(full_run):
    run_dir, result = full_run
    cfg = tiny()
    assert config_lib.load(run_dir / "config.yaml") == cfg
    rows = rundir.read_metrics(run_dir / rundir.METRICS_FILE)
    assert sorted((r["iteration"], r["seed"]) for r in rows) == [
        (i, s) for i in range(1, cfg.iterations + 1) for s in range(cfg.seeds)
    ]
    for r in rows:
        assert r["env_steps"] == r["iteration"] * cfg.steps_per_iteration
        assert all(math.isfinite(r[k]) for k in ("critic_loss", "actor_loss", "penalty", "q"))
        assert ("eval_return" in r) == (r["iteration"] % cfg.chunk_iterations == 0)
    assert (run_dir / rundir.CURVE_FILE).read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    steps = sorted(int(p.name) for p in (run_dir / rundir.CHECKPOINT_DIR).iterdir())
    assert steps[-1] == cfg.iterations

    record = json.loads((run_dir / rundir.EVAL_FILE).read_text())
    assert record == result and record["env"] == "lunarlander"
    best = record["best_seed"]
    assert record["jax_eval"] == record["per_seed"][best]["jax_eval"]
    assert record["jax_eval"]["episodes"] == cfg.eval_episodes
    assert record["training"]["env_steps"] == cfg.total_env_steps
    assert record["training"]["iterations"] == cfg.iterations
    expression = (run_dir / rundir.EXPRESSION_FILE).read_text()
    assert expression.startswith("a0 = ") and "a1 = " in expression
    assert record["formula"] == expression.strip()
    assert record["reference_eval"]["episodes"] == cfg.reference_eval_episodes
    for summary in (record["jax_eval"], record["reference_eval"]):
        assert all(math.isfinite(summary[k]) for k in ("mean", "std", "min", "max"))


@pytest.mark.slow
def test_policy_py_is_the_network_and_runs_in_gymnasium(full_run):
    run_dir, result = full_run
    trainer, state, _ = run.load_run(run_dir)
    best = result["best_seed"]
    params = jax.tree.map(lambda x: np.asarray(x[best]), state.actor)
    actor, env = trainer.sac.actor, trainer.env
    reference = reference_env("lunarlander")
    obs = np.stack([reference.reset(seed=i)[0] for i in range(4)])
    for _ in range(20):  # states off the reset distribution as well
        o, *_ = reference.step(reference.action_space.sample())
        obs = np.vstack([obs, o[None]])
    reference.close()
    expected = env.to_env_action(
        np.asarray(jax.vmap(actor.deterministic, (None, None, 0))(
            params, actor.eval_mask(params), obs))
    )  # fmt: skip
    policy = reference_eval.load_policy(run_dir / rundir.POLICY_FILE)
    got = np.array([policy.act(o) for o in obs])
    assert got.shape == (len(obs), 2)
    np.testing.assert_allclose(got, expected, atol=1e-4)
    returns = reference_eval.rollout_returns(policy.act, "lunarlander", 2, seed=123)
    assert returns.shape == (2,) and np.all(np.isfinite(returns))


# --------------------------------------------------------------------------------------------
# known answers: the paper's formulas
# --------------------------------------------------------------------------------------------


def _log(x):
    return np.log(max(abs(x), 0.001))  # protected as the network's log (App. A)


def _div(a, b):
    return a / b if abs(b) >= 0.01 else 0.0  # protected as the network's div (App. A)


def _paper_lunarlander(obs):
    """Table 3, LunarLander (s1..s8 = obs[0..7]); the action is the tanh of the formula."""
    s = [None, *obs]
    a1 = (0.14 - 2.57 * s[4]) * (0.48 - 0.68 * _log(0.5 * s[2])) - 1.44
    inner = -6.5 * s[6] - 2.13 * np.cos(0.78 * np.sin(4.15 * s[1] - 0.05) + 1.98) - 0.98
    a2 = -5.72 * s[3] + 4.42 * np.sin(2.54 * s[5] + 0.03) - 0.4 - _div(inner, 4.71 * s[7] + 0.77)
    return np.tanh([a1, a2])


def _paper_bipedalwalker(obs):
    """Table 3, BipedalWalker (s1..s24 = obs[0..23]); the action is the tanh of the formula."""
    s = [None, *obs]
    a1 = 1.45 - 2.94 * np.cos(
        -0.73 * s[5] + (0.06 - 1.06 * s[3]) * (-1.33 * s[12] - 0.28 * s[6] + 0.41) + 1.32
    )
    a2 = 7.53 * np.exp(0.4 * s[1] - 0.13 * s[6] - 0.52 * np.sin(1.5 * s[7] - 0.24)) - 11.1
    den = 4.56 * s[9] + (0.2 - 3.01 * s[21]) * (-1.8 * s[1] - 0.03 * s[7] - 0.96) - 0.54
    a3 = -_div(1.07 * s[6] + 0.41, den) + 0.55
    a4 = -0.28 + _div(-3.32 * s[12] + 5.64 * s[3] + 0.29 * s[22] - 2.46, 3.26 * s[23] - 1.45)
    return np.tanh([a1, a2, a3, a4])


@pytest.mark.parametrize(
    "name, formula, paper",
    [("lunarlander", _paper_lunarlander, 283.56), ("bipedalwalker", _paper_bipedalwalker, 309.43)],
)
def test_paper_formulas_score_the_papers_returns(name, formula, paper):
    """The paper's Table 3 formulas, played by ``reference_eval.rollout_returns`` (the reference-env
    path that reports every Box2D figure), score what its Table 2 reports: the env, its
    observation order and the action convention are the paper's.

    Observed over env seeds 0..9: lunarlander 282.05, bipedalwalker 309.99.
    """
    returns = reference_eval.rollout_returns(formula, name, episodes=10)
    assert abs(returns.mean() - paper) < 10.0, returns
