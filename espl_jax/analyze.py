"""python -m espl_jax.analyze RUN_DIR: local stability of a run's exported formula in closed loop.

Reads the run's exported formula and hands it to ``espl_jax.stability`` (the linearisation at the
env's equilibrium and its eigenvalues; see there for the method), prints the report and records
it in eval.json under ``stability``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import sympy as sp

from espl_jax import config as config_lib
from espl_jax import envs, run, rundir, runlock
from espl_jax import expression as ex
from espl_jax.cli import check_path, run_main
from espl_jax.config import UserError
from espl_jax.seeds import one_seed
from espl_jax.stability import (
    DEFAULT_TOLERANCE,
    EQUILIBRIA,
    check_has_equilibrium,
    closed_loop,
    format_report,
)

# --------------------------------------------------------------------------------------------
# The one place that reads a trained run's formula (re-point it when the trainer API changes).


def best_seed(run_dir: str | Path) -> int:
    """The seed eval.json names as best (0 when the run has no eval.json yet)."""
    path = Path(run_dir) / rundir.EVAL_FILE
    return int(json.loads(path.read_text()).get("best_seed", 0)) if path.is_file() else 0


def exported_expressions(run_dir: str | Path, seed: int | None = None) -> list[sp.Expr]:
    """The protected sympy expressions of a run's exported policy (one per action dimension).

    Args:
        run_dir: a run directory written by ``espl_jax.train``.
        seed: which vmapped seed; default the best one in eval.json.

    Returns:
        The expressions ``expression.network_expressions`` gives for that seed's deterministic
        policy (pre-tanh, symbols x0 … x{obs_dim−1}).
    """
    trainer, state, _ = run.load_run(run_dir)
    if trainer.actor.symbolic is None:
        raise UserError(f"{run_dir} trained an MLP actor: there is no formula to analyse")
    seed = best_seed(run_dir) if seed is None else seed
    if not 0 <= seed < trainer.config.seeds:
        raise UserError(f"--seed must be in [0, {trainer.config.seeds - 1}]")
    # The actor the run exported (the hall of fame's anchor with keep_best_formula), not
    # necessarily the newest one: the formula of expression.txt and policy.py.
    actors, _ = run.exported_actors(trainer, state)
    actor = one_seed(actors, seed)
    return ex.export_expressions(trainer, actor)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m espl_jax.analyze",
        description="Local stability of a run's exported formula: linearise the closed loop "
        "(the JAX env's step with the deterministic policy tanh(formula(obs))) at the env's "
        "equilibrium, print the eigenvalues of the per-step Jacobian (discrete time) and their "
        "continuous-time equivalents, and a verdict: stable (all |λ| < 1), marginal (|λ| = 1 "
        "within --tol, named by the dominant state) or unstable. Also reports whether the "
        f"equilibrium is a fixed point under the policy. Envs: {', '.join(EQUILIBRIA)}. "
        "The result is recorded in eval.json under 'stability'.",
    )
    p.add_argument("run_dir", help="a run directory written by espl_jax.train")
    p.add_argument("--seed", type=int, help="which seed (default: the best one in eval.json)")
    p.add_argument(
        "--tol",
        type=float,
        default=DEFAULT_TOLERANCE,
        help=f"|λ| within this of 1 is marginal (default: {DEFAULT_TOLERANCE:g})",
    )
    args = p.parse_args(argv)
    if not args.tol > 0:
        raise UserError("--tol must be positive")
    check_path(args.run_dir, "RUN_DIR")
    run_dir = Path(args.run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise UserError(f"{run_dir} is not a run directory (no config.yaml)")
    config = config_lib.load(run_dir / "config.yaml")
    check_has_equilibrium(config.env)  # before the (slow) checkpoint restore
    if config.actor != "symbolic":
        raise UserError(f"{run_dir} trained an MLP actor: there is no formula to analyse")
    seed = best_seed(run_dir) if args.seed is None else args.seed
    if not 0 <= seed < config.seeds:
        raise UserError(f"--seed must be in [0, {config.seeds - 1}]")
    exprs = exported_expressions(run_dir, seed)
    result = closed_loop(envs.make(config.env), exprs, tolerance=args.tol)
    formula = ex.to_text(exprs)
    print(format_report(result, formula))
    eval_path = run_dir / rundir.EVAL_FILE
    with runlock.hold(run_dir):  # eval.json is read and rewritten
        record = json.loads(eval_path.read_text()) if eval_path.is_file() else {}
        record["stability"] = {**result, "seed": seed, "formula": formula}
        rundir.write_json(eval_path, record)
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
