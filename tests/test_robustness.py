"""ESPL's robustness options: the fine-tune phase trains exactly the exported mask, the anchor
keeps each seed's best formula, and the hall of fame's pick rules (stable-within included)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp
from conftest import TINY
from flax import struct

from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax import selector
from espl_jax.config import UserError
from espl_jax.learner import Trainer


@pytest.mark.usefixtures("jax_cache")
def test_finetune_freezes_p_at_the_exported_mask_and_keeps_it_there():
    cfg = config_lib.from_mapping(
        {
            **TINY,
            "seeds": 1,
            "iterations": 3,
            "chunk_iterations": 3,
            "updates_per_iteration": 5,
            "schedule_iterations": 1,
            "finetune": True,
        }  # fmt: skip
    )
    trainer = Trainer(cfg)
    trainer.env  # noqa: B018
    state = trainer.init_seeds()
    before = jax.tree.map(lambda x: x[0], state.actor)
    # Before t_s the params are untouched; from t_s on p is the 0/1 exported mask.
    untouched = trainer.iteration.freeze_mask(before, jnp.asarray(0))
    for got, want in zip(jax.tree.leaves(untouched), jax.tree.leaves(before), strict=True):
        np.testing.assert_array_equal(got, want)
    frozen = trainer.iteration.freeze_mask(before, jnp.asarray(1))
    expected = selector.deterministic_mask(before["probs"], before["mean"]["w"])
    for got, want in zip(jax.tree.leaves(frozen["probs"]), jax.tree.leaves(expected), strict=True):
        np.testing.assert_array_equal(got, want)
        assert set(np.unique(np.asarray(got))) <= {0.0, 1.0}

    state, _ = trainer.compiled_chunk(3)(state)
    after = jax.tree.map(lambda x: x[0], state.actor)
    # Two iterations past t_s: p is still exactly a 0/1 mask (the updates did not move it) and it
    # is the exported mask of the final params, up to paths whose weight the last updates took
    # below the export's |w| > 1e-3 (they contribute < 1e-3 to the trained formula).
    again = selector.deterministic_mask(after["probs"], after["mean"]["w"])
    leaves = zip(jax.tree.leaves(after["probs"]), jax.tree.leaves(again),
                 jax.tree.leaves(after["mean"]["w"]), strict=True)  # fmt: skip
    for got, want, w in leaves:
        got, want, w = np.asarray(got), np.asarray(want), np.asarray(w)
        assert set(np.unique(got)) <= {0.0, 1.0}
        assert np.all(got >= want)  # every exported path is trained
        assert np.all(np.abs(w[got != want]) <= 1e-3)
    # ... while the constants were trained.
    w0, w1 = jax.tree.leaves(before["mean"]), jax.tree.leaves(after["mean"])
    assert any(not np.array_equal(a, b) for a, b in zip(w0, w1, strict=True))


@struct.dataclass
class _Anchored:
    actor: dict
    anchor: dict
    anchor_return: jax.Array
    anchor_iteration: jax.Array
    iteration: jax.Array


def test_anchor_keeps_each_seeds_best_formula_from_the_schedules_end_on():
    state = _Anchored(
        actor={"w": jnp.asarray([[1.0, 1.0], [2.0, 2.0]])},
        anchor={"w": jnp.zeros((2, 2))},
        anchor_return=jnp.asarray([-jnp.inf, -jnp.inf]),
        anchor_iteration=jnp.asarray([0, 0]),
        iteration=jnp.asarray([10, 10]),
    )
    assert hof.update_anchor(state, jnp.asarray([5.0, 7.0]), eligible=False) is state
    state = hof.update_anchor(state, jnp.asarray([5.0, 7.0]), eligible=True)
    np.testing.assert_array_equal(state.anchor["w"], [[1.0, 1.0], [2.0, 2.0]])
    # Seed 0 improves, seed 1 gets worse: only seed 0's anchor moves.
    state = state.replace(
        actor={"w": jnp.asarray([[3.0, 3.0], [4.0, 4.0]])}, iteration=jnp.asarray([20, 20])
    )
    state = hof.update_anchor(state, jnp.asarray([6.0, 1.0]), eligible=True)
    np.testing.assert_array_equal(state.anchor["w"], [[3.0, 3.0], [2.0, 2.0]])
    np.testing.assert_array_equal(state.anchor_return, [6.0, 7.0])
    np.testing.assert_array_equal(state.anchor_iteration, [20, 10])


def _row(iteration, selection_return, length):
    return {"iteration": iteration, "seed": 0, "selection_return": selection_return,
            "length": length, "formula": f"a0 = f{iteration}", "protected": ["x"]}  # fmt: skip


def test_pick_best_and_shortest_within():
    rows = [_row(1, 900.0, 40), _row(2, 1000.0, 30), _row(3, 960.0, 8), _row(4, 1000.0, 25),
            {**_row(5, 2000.0, 1e6), "formula": None, "protected": None}]  # fmt: skip
    assert hof.pick(rows, "best")["iteration"] == 4  # ties: the shorter; unpruned rows never
    assert hof.pick(rows, "shortest-within", 5.0)["iteration"] == 3  # 960 is within 5 % of 1000
    assert hof.pick(rows, "shortest-within", 1.0)["iteration"] == 4
    with pytest.raises(UserError):
        hof.pick([rows[-1]], "best")


def test_pick_stable_within_takes_the_shortest_locally_stable_formula():
    rows = [{**_row(1, 1000.0, 30), "stability": "unstable", "spectral_radius": 1.0002},
            {**_row(2, 990.0, 20), "stability": "marginal", "spectral_radius": 1.0},
            {**_row(3, 960.0, 25), "stability": "stable", "spectral_radius": 0.99},
            {**_row(4, 980.0, 10), "stability": "unstable", "spectral_radius": 1.1},
            {**_row(5, 900.0, 8), "stability": "stable", "spectral_radius": 0.98}]  # fmt: skip
    assert hof.pick(rows, "stable-within", 5.0, env="cartpole")["iteration"] == 3
    assert hof.pick(rows, "stable-within", 10.0, env="cartpole")["iteration"] == 5
    assert hof.pick(rows, "shortest-within", 5.0)["iteration"] == 4  # unstable, but shortest
    with pytest.raises(UserError, match=r"no locally stable .* 1 marginal, 1 unstable"):
        hof.pick(rows, "stable-within", 1.0, env="cartpole")
    unstable = [r for r in rows if r["stability"] != "stable"]
    with pytest.raises(UserError, match=r"no formula .* is locally stable \(1 marginal, 2 unst"):
        hof.pick(unstable, "stable-within", 100.0, env="cartpole")
    for env in ("mountaincar", "hopper", None):
        with pytest.raises(UserError, match=f"{env} has no equilibrium analysis"):
            hof.pick(rows, "stable-within", 5.0, env=env)
    with pytest.raises(UserError, match=r"stable-within needs a percentage in \[0, 100\]"):
        hof.pick(rows, "stable-within", 101.0, env="cartpole")


def test_pick_stable_within_analyses_rows_written_before_stability_was_recorded():
    """formulas.jsonl from before the hall of fame recorded stability: the rows within the
    percentage are analysed when picked (a cart-velocity feedback law is stable, issue 35's
    formula drifts)."""
    x = ex.observation_symbols(4)
    laws = {1: 0.5417 * x[0] + 26.56 * x[2] + 1.837 * x[3] - 0.1759,
            2: x[0] + 2.0 * x[1] + 20.0 * x[2] + 2.0 * x[3]}  # fmt: skip
    rows = [{**_row(i, 1000.0, 10 + i), "protected": [sp.srepr(law)]} for i, law in laws.items()]
    chosen = hof.pick(rows, "stable-within", 1.0, env="cartpole")
    assert chosen["iteration"] == 2 and chosen["stability"] == "stable"
    assert chosen["spectral_radius"] < 1 and "stability" not in rows[1]  # rows are not changed


def test_bias_l1_is_weight_times_mean_abs_bias_and_pulls_every_bias_to_zero():
    """``bias_l1_scale`` (the authors' ``bl0_scale``): extra = scale · mean |b| over all biases,
    so each bias, the never-masked output bias included, feels a pull of scale / N towards 0."""
    from espl_jax.policies import make_actor

    scale = 1.0
    actor = make_actor(config_lib.from_mapping({**TINY, "bias_l1_scale": scale}), 4, 1, 0)
    assert actor.has_extra_loss
    params = actor.init(jax.random.PRNGKey(0))
    # Random non-zero biases of both signs (init may set them to 0, where |b| has no slope).
    keys = jax.random.split(jax.random.PRNGKey(1), len(params["mean"]["b"]))
    biases = [jax.random.normal(k, b.shape) for k, b in zip(keys, params["mean"]["b"], strict=True)]
    params = {**params, "mean": {**params["mean"], "b": biases}}
    flat = np.concatenate([np.asarray(b).ravel() for b in biases])
    _, extra = actor.regularizers(params, jnp.asarray(0.01))
    np.testing.assert_allclose(extra, scale * np.mean(np.abs(flat)), rtol=1e-6)

    def loss(b):
        return actor.regularizers({**params, "mean": {**params["mean"], "b": b}}, 0.01)[1]

    grads = jax.grad(loss)(biases)
    for g, b in zip(grads, biases, strict=True):
        assert np.all(np.asarray(b) != 0)
        np.testing.assert_allclose(g, scale * np.sign(b) / flat.size, rtol=1e-6)
    assert flat.size == actor.symbolic.num_biases
    # Off by default: the paper's loss has no such term.
    plain = make_actor(config_lib.from_mapping(dict(TINY)), 4, 1, 0)
    assert not plain.has_extra_loss
    assert float(plain.regularizers(params, jnp.asarray(0.01))[1]) == 0.0
