"""The formula hall of fame: every chunk's exported formula, its length and selection return.

After each chunk the host evaluates each seed's exported formula (deterministic mask p > 0.5,
|w| > 1e-3) on ``progress_eval_episodes`` *selection* episodes; this module appends one row per
seed to ``formulas.jsonl``::

    {"iteration", "env_steps", "seed", "selection_return", "length", "formula", "protected",
     "eligible"}

``protected`` is the list of sympy ``srepr`` strings of the protected expressions (exact: the
formula can be rebuilt and exported later), null for an unpruned network (too long to keep).
``eligible`` marks the rows from the end of the schedule (t ≥ t_s) on, when the structure is
pruned; among those the best selection return (the latest on ties) is the run's *anchor*, kept
in the TrainState (``anchor``, ``anchor_return``, ``anchor_iteration``) so a resumed run has it
too. With ``keep_best_formula`` the anchor is what the run exports; its reported return is
measured afresh on other episodes (``run.finish``).

``pick`` chooses a row for ``python -m espl_jax.export RUN --pick best|shortest-within PCT``
(PySR's ``model_selection``, for symbolic policies).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp

from espl_jax import expression as ex
from espl_jax import rundir
from espl_jax.config import UserError
from espl_jax.seeds import one_seed

FORMULAS_FILE = "formulas.jsonl"
PLOT_FILE = "hall_of_fame.png"


def update_anchor(state, returns: jax.Array, eligible: bool):
    """Keep each seed's actor as its anchor if its selection return is the best so far.

    Args:
        state: the seed-stacked TrainState after a chunk.
        returns: [S] mean selection return of each seed's exported formula.
        eligible: whether this chunk ended at or after the end of the schedule.
    """
    if not eligible:
        return state
    better = returns >= state.anchor_return

    def pick(new, old):
        return jnp.where(better.reshape(-1, *([1] * (new.ndim - 1))), new, old)

    return state.replace(
        anchor=jax.tree.map(pick, state.actor, state.anchor),
        anchor_return=jnp.where(better, returns, state.anchor_return),
        anchor_iteration=jnp.where(better, state.iteration, state.anchor_iteration),
    )


def row(expressions: list, selection_return: float, **fields: Any) -> dict[str, Any]:
    """One formulas.jsonl row for one seed's exported expressions."""
    length = ex.mean_complexity([ex.readable(e) for e in expressions])
    printable = all(ex.complexity(e) <= ex.READABLE_MAX_LENGTH for e in expressions)
    return {
        **fields,
        "selection_return": float(selection_return),
        "length": length,
        "formula": ex.to_text(expressions) if printable else None,
        "protected": [sp.srepr(e) for e in expressions] if printable else None,
    }


def append(path: Path, rows: list[dict[str, Any]]) -> None:
    with path.open("a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")


def read(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a formulas.jsonl; a last line cut short by a kill is skipped."""
    return rundir.read_metrics(path)  # the same tolerant JSONL reader


def expressions(row: dict[str, Any]) -> list[sp.Expr]:
    """The protected sympy expressions of a row (exact constants)."""
    if row.get("protected") is None:
        raise UserError(
            f"the formula of iteration {row['iteration']} (seed {row['seed']}) was not kept: "
            f"the network was not pruned yet (length {row['length']:.0f})"
        )
    names = {"PMul": ex.PMul, "PDiv": ex.PDiv, "PLog": ex.PLog, "PExp": ex.PExp, "PCond": ex.PCond}
    return [sp.sympify(text, locals=names) for text in row["protected"]]


def pick(rows: list[dict[str, Any]], how: str, within: float | None = None) -> dict[str, Any]:
    """``best``: the highest selection return (the shorter formula on ties); ``shortest-within``:
    the shortest formula whose selection return is within ``within`` percent of the best.

    Only rows with a kept formula count.
    """
    kept = [r for r in rows if r.get("protected") is not None]
    if not kept:
        raise UserError("no formula in the hall of fame was kept (none was pruned yet)")
    best = max(kept, key=lambda r: (r["selection_return"], -r["length"], r["iteration"]))
    if how == "best":
        return best
    if within is None or not 0 <= within <= 100:
        raise UserError("--pick shortest-within needs a percentage in [0, 100]")
    # Returns can be negative (pendulum): the tolerance is a fraction of the best's magnitude.
    floor = best["selection_return"] - abs(best["selection_return"]) * within / 100
    close = [r for r in kept if r["selection_return"] >= floor]
    return min(close, key=lambda r: (r["length"], -r["selection_return"]))


def plot(path: Path, out: Path, title: str) -> None:
    """Selection return against length, one colour per seed, the anchors circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in read(path) if math.isfinite(r["length"])]
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7, 5))
    for s in sorted({r["seed"] for r in rows}):
        mine = [r for r in rows if r["seed"] == s]
        ax.scatter(
            [r["length"] for r in mine],
            [r["selection_return"] for r in mine],
            s=[30 if r["eligible"] else 10 for r in mine],
            alpha=0.7,
            label=f"seed {s}",
        )
    ax.set_xscale("log")
    ax.set_xlabel("formula length (operators + constants + variables, mean over actions)")
    ax.set_ylabel("selection return")
    ax.set_title(f"{title}: the hall of fame (large dots: after the schedule)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def seed_rows(trainer, actors: Any, returns: np.ndarray, **fields: Any) -> list[dict[str, Any]]:
    """One row per seed of seed-stacked actor params (numpy)."""
    rows = []
    for s in range(returns.shape[0]):
        actor = one_seed(actors, s)
        rows.append(row(ex.export_expressions(trainer, actor), returns[s], seed=s, **fields))
    return rows
