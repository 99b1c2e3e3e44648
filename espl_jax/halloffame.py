"""The formula hall of fame: every chunk's exported formula, its length and selection return.

After each chunk the host evaluates each seed's exported formula (deterministic mask p > 0.5,
|w| > 1e-3) on ``progress_eval_episodes`` *selection* episodes; this module appends one row per
seed to ``formulas.jsonl``::

    {"iteration", "env_steps", "seed", "selection_return", "length", "formula", "protected",
     "eligible", "stability", "spectral_radius"}

``protected`` is the list of sympy ``srepr`` strings of the protected expressions (exact: the
formula can be rebuilt and exported later), null for an unpruned network (too long to keep).
``eligible`` marks the rows from the end of the schedule (t ≥ t_s) on, when the structure is
pruned; among those the best selection return (the latest on ties) is the run's *anchor*, kept
in the TrainState (``anchor``, ``anchor_return``, ``anchor_iteration``) so a resumed run has it
too. With ``keep_best_formula`` the anchor is what the run exports; its reported return is
measured afresh on other episodes (``run.finish``).

``stability`` and ``spectral_radius`` are ``python -m espl_jax.analyze``'s local-stability verdict
("stable", "marginal" or "unstable") and the largest |λ| of the closed loop's per-step Jacobian
at the env's equilibrium (``stability.closed_loop``): a formula can score a full episode and still
be unstable (a slow mode with |λ| = 1.0002 is invisible in 1000 steps). Both are null for envs
without an equilibrium (``stability.EQUILIBRIA``), for formulas not kept, and where the closed-loop
Jacobian is not finite; rows written before they were recorded lack them.

``pick`` chooses a row for ``python -m espl_jax.export RUN --pick best|shortest-within PCT|
stable-within PCT`` (PySR's ``model_selection``, for symbolic policies).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp

from espl_jax import envs, rundir
from espl_jax import expression as ex
from espl_jax import stability as analysis
from espl_jax.config import UserError
from espl_jax.seeds import one_seed

FORMULAS_FILE = "formulas.jsonl"
PLOT_FILE = "hall_of_fame.png"
# How export's --pick and the API's Run.pick choose (``pick``); the last two take a percentage.
PICKS = ("best", "shortest-within", "stable-within")
NOT_ANALYSED = {"stability": None, "spectral_radius": None}


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


def row(
    expressions: list, selection_return: float, env: str | None = None, **fields: Any
) -> dict[str, Any]:
    """One formulas.jsonl row for one seed's exported expressions; ``env`` (the env's name)
    adds the formula's local stability (``stability``), null for a formula not kept."""
    length = ex.mean_complexity([ex.readable(e) for e in expressions])
    printable = all(ex.complexity(e) <= ex.READABLE_MAX_LENGTH for e in expressions)
    analysed = stability(env, expressions) if printable and env is not None else NOT_ANALYSED
    return {
        **fields,
        "selection_return": float(selection_return),
        "length": length,
        "formula": ex.to_text(expressions) if printable else None,
        "protected": [sp.srepr(e) for e in expressions] if printable else None,
        **analysed,
    }


def stability(env: str, expressions: list) -> dict[str, Any]:
    """``analyze``'s verdict on a formula, as a hall-of-fame row records it.

    Returns:
        ``{"stability": "stable" | "marginal" | "unstable", "spectral_radius": max |λ|}`` of
        ``stability.closed_loop`` at the env's default params and tolerance; both None for an env
        without an equilibrium, or where the closed-loop Jacobian is not finite.
    """
    if not analysis.has_equilibrium(env):
        return dict(NOT_ANALYSED)
    try:
        result = analysis.closed_loop(_analysis_env(env), expressions)
    except ValueError:  # a formula whose closed-loop Jacobian is not finite at x*
        return dict(NOT_ANALYSED)
    return {"stability": result["verdict"], "spectral_radius": result["spectral_radius"]}


@functools.lru_cache(maxsize=4)
def _analysis_env(name: str):
    """One env instance per name, so ``analyze`` compiles its linearisation once per process."""
    return envs.make(name)


def require_stability(env: str | None) -> None:
    """Raises a UserError unless ``env`` has the equilibrium that ``stable-within`` needs."""

    if env is None or not analysis.has_equilibrium(env):
        raise UserError(
            f"stable-within needs the local-stability analysis, and {env} has no equilibrium "
            f"analysis (python -m espl_jax.analyze knows {', '.join(analysis.EQUILIBRIA)}); use "
            "'best' or 'shortest-within PCT'"
        )


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


def pick(
    rows: list[dict[str, Any]], how: str, within: float | None = None, env: str | None = None
) -> dict[str, Any]:
    """Choose a row of the hall of fame.

    Args:
        rows: formulas.jsonl rows; only those with a kept formula count.
        how: ``best``: the highest selection return (the shorter formula on ties);
            ``shortest-within``: the shortest formula whose selection return is within
            ``within`` percent of the best; ``stable-within``: the same among the formulas
            ``analyze`` finds locally stable (every |λ| < 1); the best itself need not be stable.
        within: the percentage, in [0, 100].
        env: the run's env; ``stable-within`` needs one with an equilibrium. Rows written before
            the hall of fame recorded stability are analysed here.

    Raises:
        UserError: an unknown ``how`` or bad ``within``; no kept formula; ``stable-within`` on an
            env without an equilibrium, or with no stable formula within ``within`` percent.
    """
    if how not in PICKS:
        raise UserError("--pick takes 'best', 'shortest-within PCT' or 'stable-within PCT'")
    if how != "best" and (within is None or not 0 <= within <= 100):
        raise UserError(f"--pick {how} needs a percentage in [0, 100]")
    if how == "stable-within":
        require_stability(env)
    kept = [r for r in rows if r.get("protected") is not None]
    if not kept:
        raise UserError("no formula in the hall of fame was kept (none was pruned yet)")
    best = max(kept, key=lambda r: (r["selection_return"], -r["length"], r["iteration"]))
    if how == "best":
        return best
    # Returns can be negative (pendulum): the tolerance is a fraction of the best's magnitude.
    floor = best["selection_return"] - abs(best["selection_return"]) * within / 100
    close = [r for r in kept if r["selection_return"] >= floor]
    if how == "stable-within":
        close = [r if "stability" in r else {**r, **stability(env, expressions(r))} for r in close]
        stable = [r for r in close if r["stability"] == "stable"]
        if not stable:
            verdicts = [str(r["stability"]) for r in close]
            counts = ", ".join(f"{verdicts.count(v)} {v}" for v in sorted(set(verdicts)))
            if len(close) == len(kept):
                raise UserError(f"no formula in the hall of fame is locally stable ({counts})")
            raise UserError(
                f"no locally stable formula within {within:g} % of the best selection return "
                f"({best['selection_return']:.2f}); the {len(close)} there: {counts}; try a "
                "larger percentage"
            )
        close = stable
    return min(close, key=lambda r: (r["length"], -r["selection_return"]))


# The hall-of-fame plot's marker for each local-stability verdict (None: not analysed).
MARKERS = {"stable": "o", "marginal": "s", "unstable": "X", None: "^"}
VERDICT_LABELS = {
    "stable": "locally stable",
    "marginal": "marginal",
    "unstable": "unstable",
    None: "not analysed",
}


def plot(path: Path, out: Path, title: str) -> None:
    """Selection return against length, one colour per seed, the marker the formula's local
    stability; beside it, where any row was analysed, the spectral radius against length."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    rows = [r for r in read(path) if math.isfinite(r["length"])]
    if not rows:
        return
    analysed = any(r.get("spectral_radius") is not None for r in rows)
    fig, axes = plt.subplots(1, 2 if analysed else 1, figsize=(13 if analysed else 7, 5))
    axes = list(np.atleast_1d(axes))
    seeds = sorted({r["seed"] for r in rows})
    colours = {s: f"C{i % 10}" for i, s in enumerate(seeds)}
    panels = [(axes[0], "selection_return", "selection return")]
    if analysed:
        panels.append((axes[1], "spectral_radius", "spectral radius max |λ| (per step)"))
    for ax, key, label in panels:
        for verdict, marker in MARKERS.items():
            mine = [r for r in rows if r.get("stability") == verdict and r.get(key) is not None]
            if mine:
                ax.scatter(
                    [r["length"] for r in mine],
                    [r[key] for r in mine],
                    s=[40 if r["eligible"] else 12 for r in mine],
                    c=[colours[r["seed"]] for r in mine],
                    marker=marker,
                    alpha=0.7,
                )
        ax.set_xscale("log")
        ax.set_xlabel("formula length (operators + constants + variables, mean over actions)")
        ax.set_ylabel(label)
    handles = [
        Line2D([], [], ls="", marker="o", color=colours[s], label=f"seed {s}") for s in seeds
    ]
    handles += [
        Line2D([], [], ls="", marker=MARKERS[v], color="grey", label=VERDICT_LABELS[v])
        for v in MARKERS
        if any(r.get("stability") == v for r in rows)
    ]
    axes[0].legend(handles=handles, fontsize=7)
    axes[0].set_title(f"{title}: the hall of fame (large: after the schedule)")
    if analysed:
        axes[1].axhline(1.0, color="black", lw=0.8, ls="--")
        axes[1].set_title("local stability at the equilibrium (stable: every |λ| < 1)")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def seed_rows(trainer, actors: Any, returns: np.ndarray, **fields: Any) -> list[dict[str, Any]]:
    """One row per seed of seed-stacked actor params (numpy), each with its local stability."""
    rows = []
    for s in range(returns.shape[0]):
        actor = one_seed(actors, s)
        exprs = ex.export_expressions(trainer, actor)
        rows.append(row(exprs, returns[s], env=trainer.config.env, seed=s, **fields))
    return rows
