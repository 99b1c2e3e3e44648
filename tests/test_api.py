"""The Python API (``espl_jax.load``, ``espl_jax.train``) on one tiny training run, the console
scripts, and the README's Python example, executed as written.

The module's run is the README example's own: one ~1-minute cartpole training (2 cores) serves
every test here. The meta-RL part (``tasks``, ``adapted``) trains a tiny CSP run and is slow.
"""

import importlib
import importlib.util
import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import jax
import numpy as np
import pytest
import sympy as sp
import yaml

import espl_jax
from espl_jax import analyze, api, envs, export, rundir, stability
from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax import run as run_lib
from espl_jax.config import UserError

REPO = Path(__file__).resolve().parent.parent

# The README's Python example: it is pasted there as it stands, so it must read well.
README_EXAMPLE = """\
import jax

import espl_jax

# A one-minute budget: leave out the last four keywords for configs/cartpole.yaml's full one.
run = espl_jax.train(env="cartpole", iterations=4, chunk_iterations=2, schedule_iterations=3,
                     eval_episodes=10)
print(run.formula())                    # sympy, one expression per action dimension
print(run.hall_of_fame)                 # every chunk's formula: length, selection return
short = run.pick("shortest-within", 5)  # the shortest formula within 5 % of the best return
action = run.act([0.0, 0.0, 0.05, 0.0])  # the run's policy.py: an action in the env's units
act = jax.jit(run.to_jax())             # the same policy as a JAX function
same = espl_jax.load(run.path)          # later: the run again, from its directory
"""


@pytest.fixture(scope="module")
def example(jax_cache, tmp_path_factory):
    """The README example's namespace after running it in a fresh working directory."""
    namespace: dict = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp_path_factory.mktemp("readme"))
        exec(README_EXAMPLE, namespace)
    return namespace


@pytest.fixture(scope="module")
def trained(example) -> api.Run:
    return example["run"]


def policy_py(path: Path):
    spec = importlib.util.spec_from_file_location(f"policy_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def observations(n: int = 400) -> np.ndarray:
    return np.random.default_rng(0).normal(scale=[1.0, 1.0, 0.2, 1.0], size=(n, 4))


def test_readme_example_gives_a_formula_an_act_and_a_table(example):
    trained = example["run"]
    assert isinstance(trained, api.Run) and trained.path.parent.name == "runs"
    assert all(isinstance(e, sp.Expr) for e in trained.formula())
    reference = policy_py(trained.path / rundir.POLICY_FILE)
    np.testing.assert_array_equal(example["action"], reference.act([0.0, 0.0, 0.05, 0.0]))
    assert len(trained.hall_of_fame) == 2  # one row per chunk (one seed)
    assert isinstance(example["short"], api.Formula)
    assert example["same"].formula() == trained.formula()


def test_formula_is_sympy_in_the_observation_symbols(trained):
    exprs = trained.formula()
    assert len(exprs) == 1  # cartpole: one action
    assert exprs[0].free_symbols <= {sp.Symbol(f"x{i}", real=True) for i in range(4)}
    assert trained.policy().info["seed"] == trained.eval["best_seed"]
    assert str(trained.policy()) == (trained.path / rundir.EXPRESSION_FILE).read_text().strip()
    assert trained.latex().startswith("a_{0} = ")


def test_act_is_the_runs_policy_py(trained):
    reference = policy_py(trained.path / rundir.POLICY_FILE)
    obs = observations()
    got = np.array([trained.act(o) for o in obs])
    np.testing.assert_array_equal(got, np.array([reference.act(o) for o in obs]))
    np.testing.assert_array_equal(trained.act_batch(obs), reference.act_batch(obs))
    assert len(np.unique(np.round(got, 6))) > 1  # not a constant policy: the test means something


def test_to_jax_agrees_with_act(trained):
    obs = observations()
    got = np.asarray(jax.jit(trained.to_jax())(obs.astype(np.float32)))
    np.testing.assert_allclose(got, trained.act_batch(obs), atol=1e-5)  # float32 against float64


def test_hall_of_fame_and_checkpoint_give_the_same_formula(trained):
    """The API reads a seed's exact formula from formulas.jsonl; the checkpoint (its fallback,
    the way training exported it) must give the same expressions."""
    for seed in range(trained.config.seeds):
        assert trained.policy(seed).info["iteration"] == trained.config.iterations
        from_checkpoint = trained._from_checkpoint(seed)
        assert from_checkpoint.expressions == trained.policy(seed).expressions


def test_hall_of_fame_table(trained):
    table = trained.hall_of_fame
    rows = hof.read(trained.path / hof.FORMULAS_FILE)
    assert len(table) == len(rows) == 2
    assert list(table["length"]) == [r["length"] for r in rows]
    assert list(table["selection_return"]) == [r["selection_return"] for r in rows]
    assert list(table["formula"])[-1] == str(trained.policy())  # the anchor is the last one
    if isinstance(table, api.Table):  # pandas not installed: the table prints itself
        assert repr(table).splitlines()[0].split() == list(api.HALL_OF_FAME_COLUMNS)


def test_pick_is_exports_pick(trained, tmp_path):
    picked = trained.pick("shortest-within", 5)
    assert (
        export.main([str(trained.path), "--pick", "shortest-within", "5", "-o", str(tmp_path)]) == 0
    )
    assert str(picked) == (tmp_path / rundir.EXPRESSION_FILE).read_text().strip()
    reference = policy_py(tmp_path / rundir.POLICY_FILE)
    obs = observations(50)
    np.testing.assert_array_equal(picked.act_batch(obs), reference.act_batch(obs))
    kept = [r for r in hof.read(trained.path / hof.FORMULAS_FILE) if r["protected"] is not None]
    best = max(r["selection_return"] for r in kept)
    assert picked.info["selection_return"] >= best - abs(best) * 0.05
    assert str(trained.pick("best")) == str(trained.pick("best", seed=0))


def test_hall_of_fame_records_each_formulas_local_stability(trained, tmp_path):
    """Each kept formula's row holds analyze's verdict and spectral radius (cartpole has an
    equilibrium); the table shows them and the plot draws them."""
    rows = hof.read(trained.path / hof.FORMULAS_FILE)
    kept = [r for r in rows if r["protected"] is not None]
    assert kept, "the tiny run kept no formula: the test would mean nothing"
    for r in rows:
        if r["protected"] is None:
            assert r["stability"] is None and r["spectral_radius"] is None
            continue
        result = stability.closed_loop(envs.make("cartpole"), hof.expressions(r))
        assert r["stability"] == result["verdict"] in ("stable", "marginal", "unstable")
        assert r["spectral_radius"] == pytest.approx(result["spectral_radius"], abs=1e-9)
    table = trained.hall_of_fame
    assert list(table["stability"]) == [r["stability"] for r in rows]
    assert list(table["spectral_radius"]) == [r["spectral_radius"] for r in rows]
    if isinstance(table, api.Table):
        radius = f"{kept[-1]['spectral_radius']:.6f}"  # six decimals: 1.000187 is not 1.00
        assert radius in repr(table).splitlines()[-1]
    assert not any("hall-of-fame plot" in w for w in trained.eval.get("warnings", []))
    hof.plot(trained.path / hof.FORMULAS_FILE, tmp_path / "hof.png", "cartpole")
    assert (tmp_path / "hof.png").stat().st_size > 0


def test_pick_stable_within_in_the_api_and_the_cli(trained, tmp_path, capsys):
    """A copy of the run's hall of fame gets a locally stable formula (cart-velocity feedback)
    in a row written without stability, as before it was recorded: stable-within finds a stable
    formula there; the API and ``export --pick`` agree."""
    run_dir = tmp_path / "run"
    shutil.copytree(trained.path, run_dir, ignore=shutil.ignore_patterns("checkpoints"))
    rows = hof.read(run_dir / hof.FORMULAS_FILE)
    x = ex.observation_symbols(4)
    law = x[0] + 2.0 * x[1] + 20.0 * x[2] + 2.0 * x[3]
    best = max(r["selection_return"] for r in rows if r["protected"] is not None)
    old_row = {k: v for k, v in hof.row([law], best, iteration=99, seed=0).items()
               if k not in ("stability", "spectral_radius")}  # fmt: skip
    hof.append(run_dir / hof.FORMULAS_FILE, [{**old_row, "eligible": True, "env_steps": 0}])
    picked = espl_jax.load(run_dir).pick("stable-within", 5)
    assert picked.info["stability"] == "stable" and picked.info["spectral_radius"] < 1
    assert picked.length <= ex.mean_complexity([law])
    assert stability.closed_loop(envs.make("cartpole"), picked.expressions)["verdict"] == "stable"
    out = tmp_path / "picked"
    assert export.main([str(run_dir), "--pick", "stable-within", "5", "-o", str(out)]) == 0
    assert str(picked) == (out / rundir.EXPRESSION_FILE).read_text().strip()
    assert "stable at the equilibrium (spectral radius 0." in capsys.readouterr().out


def test_export_and_analyze_read_the_exported_anchor_not_the_final_actor(
    trained, monkeypatch, capsys
):
    """With keep_best_formula the run exports the hall of fame's anchor; export (default) and
    analyze must rebuild that formula, not the checkpoint's newest actor (which differs here: its
    constants are scaled)."""
    assert trained.config.keep_best_formula
    trainer, state, step = run_lib.load_run(trained.path)
    assert np.isfinite(np.asarray(state.anchor_return)).all()
    final = {**state.actor, "mean": jax.tree.map(lambda w: 1.5 * w, state.actor["mean"])}
    moved = state.replace(actor=final)
    monkeypatch.setattr(run_lib, "load_run", lambda run_dir: (trainer, moved, step))
    exported = (trained.path / rundir.EXPRESSION_FILE).read_text().strip()
    final_text = ex.to_text(
        ex.export_expressions(trainer, jax.tree.map(lambda v: np.asarray(v[0]), final))
    )
    assert final_text != exported  # the test means something
    assert ex.to_text(analyze.exported_expressions(trained.path)) == exported
    capsys.readouterr()
    assert export.main([str(trained.path)]) == 0
    assert capsys.readouterr().out.strip() == exported


@pytest.mark.parametrize("how, within", [("worst", None), ("best", 5), ("shortest-within", None),
                                         ("stable-within", None)])  # fmt: skip
def test_pick_refuses_what_export_refuses(trained, how, within):
    with pytest.raises(UserError, match="pick takes"):
        trained.pick(how, within)


def test_eval_is_eval_json(trained):
    assert trained.eval == json.loads((trained.path / rundir.EVAL_FILE).read_text())
    assert trained.config == config_lib.load(trained.path / "config.yaml")


def test_train_refuses_a_used_directory_and_unknown_keys(trained, tmp_path):
    with pytest.raises(UserError, match="already holds a run"):
        espl_jax.train(env="cartpole", out=trained.path, iterations=4)
    with pytest.raises(UserError, match="unknown key"):
        espl_jax.train(env="cartpole", out=tmp_path / "new", iteration=4)


def test_load_refuses_what_is_not_a_run(tmp_path):
    for path in (tmp_path, tmp_path / "missing", ""):
        with pytest.raises(UserError):
            espl_jax.load(path)


@pytest.mark.parametrize(
    "values, call, message",
    [
        ({"actor": "mlp"}, lambda r: r.formula(), "MLP actor: it has no formula"),
        ({"actor": "mlp"}, lambda r: r.hall_of_fame, "no hall of fame"),
        ({"env": "cartpole_fl_ood"}, lambda r: r.act([0, 0, 0, 0]), "run.adapted"),
        ({"env": "cartpole_fl_ood", "actor": "pearl"}, lambda r: r.adapted(0), "PEARL actor"),
        ({}, lambda r: r.tasks, "single-task run"),
        ({}, lambda r: r.eval, "has not finished"),
        (
            {"env": "mountaincar"},
            lambda r: r.pick("stable-within", 5),
            "mountaincar has no equilibrium analysis",
        ),
    ],
)
def test_runs_without_what_is_asked_say_so(tmp_path, values, call, message):
    config_lib.save(config_lib.from_mapping(values), tmp_path / "config.yaml")
    with pytest.raises(UserError, match=message):
        call(espl_jax.load(tmp_path))


def test_console_scripts_are_the_modules_behind_run_main(tmp_path, monkeypatch, capsys):
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert sorted(scripts) == ["espl-analyze", "espl-evaluate", "espl-export", "espl-train"]
    for name, target in scripts.items():
        module, function = target.split(":")
        entry = getattr(importlib.import_module(module), function)
        args = ["--env", "nosuch"] if name == "espl-train" else [str(tmp_path)]
        monkeypatch.setattr(sys, "argv", [name, *args])
        assert entry() == 2, name  # a user error: one line, exit status 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), (name, err)


def test_import_is_cheap_and_train_is_module_and_function():
    code = "import sys, espl_jax; assert 'jax' not in sys.modules, 'import espl_jax loads jax'"
    subprocess.run([sys.executable, "-c", code], check=True)
    from espl_jax import train

    assert callable(train) and callable(train.main)  # python -m espl_jax.train's module


def test_citation_and_license_name_this_version():
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert citation["version"] == project["version"] == espl_jax.__version__
    assert citation["license"] == project["license"] == "MIT"
    assert (REPO / "LICENSE").read_text().startswith("MIT License")
    paper = citation["preferred-citation"]
    assert paper["title"].startswith("Efficient Symbolic Policy Learning")


# Meta-RL (slow: a CSP run compiles its own programs) -------------------------------------------

TINY_CSP = {
    "seeds": 1, "iterations": 2, "chunk_iterations": 1, "schedule_iterations": 1,
    "updates_per_iteration": 4, "meta_batch": 3, "batch_size": 8, "context_batch": 6,
    "initial_steps": 30, "tasks_per_iteration": 2, "prior_steps": 20, "posterior_steps": 20,
    "task_buffer_size": 200, "critic_hidden": [16], "std_hidden": [8], "encoder_hidden": [16],
    "generator_hidden": [8], "latent_dim": 2, "eval_steps": 40, "eval_runs": 1,
}  # fmt: skip


@pytest.mark.slow
def test_meta_run_tasks_and_adapted_formulas(jax_cache, tmp_path):
    csp = espl_jax.train(env="cartpole_fl_ood", out=tmp_path / "csp", **TINY_CSP)
    tasks = csp.tasks
    assert tasks == json.loads((csp.path / "tasks.json").read_text())
    per_task = csp.eval["test"]["per_task"]
    assert len(tasks["test"]) == len(per_task) > 1
    obs = observations(50)
    for i in (0, len(per_task) - 1):
        adapted = csp.adapted(i)
        directory = csp.path / "test_tasks" / str(i)
        assert str(adapted) == (directory / rundir.EXPRESSION_FILE).read_text().strip()
        reference = policy_py(directory / rundir.POLICY_FILE)
        np.testing.assert_array_equal(adapted.act_batch(obs), reference.act_batch(obs))
    with pytest.raises(UserError, match="test task"):
        csp.adapted(len(per_task))
