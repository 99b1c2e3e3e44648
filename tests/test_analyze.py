"""Closed-loop stability of exported formulas (espl_jax.analyze), against known answers."""

import json

import numpy as np
import pytest
import sympy as sp

from espl_jax import analyze, envs, stability
from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax.cli import run_main
from espl_jax.config import UserError

X = ex.observation_symbols(9)
# Table 3's CartPole law, pre-tanh as our exports are: a = 17.17 θ + 1.2 θ̇ (obs x2 = θ, x3 = θ̇).
PAPER_CARTPOLE = [17.17 * X[2] + 1.2 * X[3]]
# Issue 35's formula: 1000.00 in a 20-second episode, yet a slow mode in x grows (|λ| = 1.000187).
SLOW_DRIFT_CARTPOLE = [0.5417 * X[0] + 26.56 * X[2] + 1.837 * X[3] - 0.1759]
# With cart-velocity feedback every mode decays.
STABLE_CARTPOLE = [X[0] + 2.0 * X[1] + 20.0 * X[2] + 2.0 * X[3]]


def _continuous(result):
    return np.array([complex(*m["continuous"]) for m in result["modes"]])


def _assert_same_spectrum(got, expected, atol):
    """Equal as multisets of complex numbers (greedy nearest match)."""
    remaining = list(expected)
    for value in got:
        i = int(np.argmin([abs(value - e) for e in remaining]))
        assert abs(value - remaining[i]) < atol, (got, expected)
        remaining.pop(i)


def test_paper_cartpole_law_matches_the_papers_eigenvalues():
    """App. "Theoretical Analysis for Cartpole": 0, 0, −26.34 ± 6.65j for force_mag 30, τ 0.02."""
    result = stability.closed_loop(envs.make("cartpole"), PAPER_CARTPOLE)
    _assert_same_spectrum(_continuous(result), [0, 0, -26.34 + 6.65j, -26.34 - 6.65j], atol=0.01)
    assert result["continuous_time"].startswith("(λ − 1)/Δt: exact")
    assert result["dt"] == pytest.approx(0.02)
    assert result["fixed_point_residual"] == 0.0
    # the pole is stabilised; the cart's position and velocity are not regulated
    assert result["verdict"] == "marginal"
    marginal = [m for m in result["modes"] if m["kind"] == "marginal"]
    assert len(marginal) == 2 and {m["dominant_state"] for m in marginal} == {"x"}
    assert all(m["jordan_block"] for m in marginal)
    assert all(m["abs"] < 1 for m in result["modes"] if m["kind"] == "stable")
    json.dumps(result)  # recordable in eval.json as is


def test_unforced_cartpole_is_unstable():
    """a = 0: the paper's ±3.97 (our exact linearisation gives ±3.9719)."""
    result = stability.closed_loop(envs.make("cartpole"), [sp.Float(0.0)])
    _assert_same_spectrum(_continuous(result), [0, 0, 3.97, -3.97], atol=0.01)
    assert result["verdict"] == "unstable"
    unstable = [m for m in result["modes"] if m["kind"] == "unstable"]
    assert len(unstable) == 1 and unstable[0]["dominant_state"].startswith("theta")
    assert result["summary"].startswith("unstable")


def test_pendulum_semi_implicit_euler_known_answer():
    """Unforced upright Pendulum-v1: θ̇' = θ̇ + Δt·15 sin θ, θ' = θ + Δt θ̇', so the per-step map
    has trace 2 + 15 Δt² and determinant 1; the paper's formula stabilises it."""
    env = envs.make("pendulum")
    dt = 0.05
    trace = 2 + 15 * dt**2
    root = np.sqrt(trace**2 - 4)
    expected = [(trace + root) / 2, (trace - root) / 2]
    result = stability.closed_loop(env, [sp.Float(0.0)])
    got = [complex(*m["discrete"]) for m in result["modes"]]
    _assert_same_spectrum(got, expected, atol=1e-5)
    assert result["verdict"] == "unstable"
    assert result["continuous_time"].startswith("log(λ)/Δt")
    mu = _continuous(result)
    np.testing.assert_allclose(sorted(mu.real), sorted(np.log(expected) / dt), atol=1e-3)

    paper = [-ex.PMul(4.27 * X[0] + 0.62, 1.9 * X[1] + 0.42 * X[2])]  # Table 3, Pendulum
    stable = stability.closed_loop(env, paper)
    assert stable["verdict"] == "stable" and stable["summary"] == "locally stable: every |λ| < 1"
    assert max(m["abs"] for m in stable["modes"]) < 0.9
    assert stable["fixed_point_residual"] == 0.0


def test_constant_offset_is_reported_as_no_fixed_point():
    env = envs.make("cartpole")
    result = stability.closed_loop(env, [PAPER_CARTPOLE[0] + 0.3])
    # one Euler step from rest under force 30·tanh(0.3): only the velocities change
    offset = np.array(result["fixed_point_offset"])
    assert offset[0] == 0 and offset[2] == 0 and offset[1] > 0 and offset[3] < 0
    assert result["fixed_point_residual"] == pytest.approx(np.linalg.norm(offset))
    assert result["fixed_point_residual"] > 0.1
    assert "not a fixed point" in result["summary"]
    assert result["pre_tanh_at_equilibrium"] == pytest.approx([0.3])
    assert result["action_at_equilibrium"] == pytest.approx([np.tanh(0.3)])


def test_envs_without_equilibrium_and_wrong_sizes_are_errors():
    with pytest.raises(UserError, match="no equilibrium defined for mountaincar"):
        stability.closed_loop(envs.make("mountaincar"), [X[1]])
    with pytest.raises(ValueError, match="1 actions, got 2"):
        stability.closed_loop(envs.make("cartpole"), PAPER_CARTPOLE * 2)


def test_spectral_radius_verdicts_and_one_compile_per_env():
    """The hall of fame's two numbers (``halloffame.stability``) are closed_loop's, and each
    formula after the first reuses the env's compiled linearisation."""
    env = envs.make("cartpole")
    drift = stability.closed_loop(env, SLOW_DRIFT_CARTPOLE)
    assert drift["verdict"] == "unstable"
    assert drift["spectral_radius"] == max(m["abs"] for m in drift["modes"])
    assert drift["spectral_radius"] == pytest.approx(1.000187, abs=2e-6)
    compiled = stability._linearisation.cache_info().misses
    stable = stability.closed_loop(env, STABLE_CARTPOLE)
    assert stability._linearisation.cache_info().misses == compiled  # no new compile
    assert stable["verdict"] == "stable" and stable["spectral_radius"] < 1 - stable["tolerance"]
    assert hof.stability("cartpole", STABLE_CARTPOLE) == {
        "stability": "stable",
        "spectral_radius": pytest.approx(stable["spectral_radius"], abs=1e-9),
    }
    assert hof.stability("cartpole", SLOW_DRIFT_CARTPOLE)["stability"] == "unstable"
    assert hof.stability("mountaincar", [X[1]]) == hof.NOT_ANALYSED  # no equilibrium
    assert "spectral radius max |λ| = 1.000187" in stability.format_report(drift)


def test_report_names_modes_and_verdict():
    result = stability.closed_loop(envs.make("cartpole"), PAPER_CARTPOLE)
    report = stability.format_report(result, ex.to_text(PAPER_CARTPOLE))
    assert "a0 = 17.17*x2 + 1.2*x3" in report
    assert "-26.34" in report and "marginal" in report and "verdict: marginal" in report


# CLI -----------------------------------------------------------------------------------------


def _fake_run(tmp_path, env="cartpole", seeds=2):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    config_lib.save(config_lib.Config(env=env, seeds=seeds), run_dir / "config.yaml")
    (run_dir / "eval.json").write_text(json.dumps({"best_seed": 1, "jax_eval": {"mean": 1000}}))
    return run_dir


def test_cli_prints_and_records_the_analysis(tmp_path, monkeypatch, capsys):
    """The CLI on a run directory; the checkpoint read is the one function re-pointed here."""
    run_dir = _fake_run(tmp_path)
    calls = []

    def fake_expressions(path, seed=None):
        calls.append((str(path), seed))
        return PAPER_CARTPOLE

    monkeypatch.setattr(analyze, "exported_expressions", fake_expressions)
    assert run_main(analyze.main, [str(run_dir)]) == 0
    assert calls == [(str(run_dir), 1)]  # the best seed of eval.json
    out = capsys.readouterr().out
    assert "verdict: marginal" in out and "a0 = 17.17*x2 + 1.2*x3" in out
    record = json.loads((run_dir / "eval.json").read_text())
    assert record["jax_eval"] == {"mean": 1000} and record["best_seed"] == 1  # kept
    stability = record["stability"]
    assert stability["verdict"] == "marginal" and stability["seed"] == 1
    assert stability["formula"] == "a0 = 17.17*x2 + 1.2*x3"
    _assert_same_spectrum(
        [complex(*m["continuous"]) for m in stability["modes"]],
        [0, 0, -26.34 + 6.65j, -26.34 - 6.65j],
        atol=0.01,
    )


@pytest.mark.parametrize(
    "env, args, message",
    [
        ("mountaincar", [], "error: no equilibrium defined for mountaincar"),
        ("cartpole", ["--seed", "5"], "error: --seed must be in [0, 1]"),
        ("cartpole", ["--tol", "0"], "error: --tol must be positive"),
    ],
)
def test_cli_user_errors(tmp_path, monkeypatch, capsys, env, args, message):
    run_dir = _fake_run(tmp_path, env=env)
    monkeypatch.setattr(analyze, "exported_expressions", pytest.fail)  # must not be reached
    assert run_main(analyze.main, [str(run_dir), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(message), err
    assert "stability" not in json.loads((run_dir / "eval.json").read_text())


def test_cli_rejects_a_directory_that_is_not_a_run(tmp_path, capsys):
    assert run_main(analyze.main, [str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "is not a run directory (no config.yaml)" in err


# MJX pendula (compiling MJX's step with its Jacobian takes ~1 min each on 2 cores) -----------


@pytest.mark.slow
def test_unforced_mjx_pendula_are_unstable_and_the_swingup_nudges_past_sqrt_at_zero():
    results = {}
    for name, n in (("inverted_pendulum_swingup", 4), ("inverted_double_pendulum", 6)):
        result = results[name] = stability.closed_loop(envs.make(name), [sp.Float(0.0)])
        assert len(result["modes"]) == n and result["verdict"] == "unstable"
        assert np.all(np.isfinite(result["jacobian"]))
        unstable = [m for m in result["modes"] if m["kind"] == "unstable"]
        assert unstable and all("hinge" in m["dominant_state"] for m in unstable)
    # the swing-up's Bullet link damping has |v| = sqrt(v·v), whose autodiff at v = 0 is 0·inf
    assert results["inverted_pendulum_swingup"]["jacobian_at"].startswith("mean of x* ±")
    assert results["inverted_double_pendulum"]["jacobian_at"] == "equilibrium"
