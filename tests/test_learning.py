"""Slow: ESPL really learns CartPole on a small budget (run with ``pytest -m slow``)."""

import json

import pytest

from espl_jax import config, reference_eval, run, rundir


@pytest.mark.slow
def test_cartpole_learns_a_formula_on_a_small_budget(tmp_path):
    cfg = config.resolve(
        "cartpole",
        iterations=14,
        updates_per_iteration=500,
        chunk_iterations=7,
        schedule_iterations=10,
        target_l0_ratio=0.02,
        eval_episodes=100,
        reference_eval_episodes=20,
    )
    result = run.train(cfg, tmp_path, show_progress=False)
    # A random policy balances for ~20 steps; a learned formula for hundreds.
    assert result["jax_eval"]["mean"] >= 150, result
    assert result["length"] <= 60
    # The written policy.py, run in the numpy reference CartPole, agrees with the JAX evaluation.
    policy = reference_eval.load_policy(tmp_path / rundir.POLICY_FILE)
    returns = reference_eval.rollout_returns(policy.act, "cartpole", 20)
    assert returns.mean() >= 150
    assert json.loads((tmp_path / rundir.EVAL_FILE).read_text())["reference_eval"]["mean"] >= 150
