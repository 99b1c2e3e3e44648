"""What the adapted formulas' constant offsets cost: each test task's formula of a meta-RL run,
as exported and with its offsets set to 0, on fresh episodes of that task's reference env.

    python benchmarks/meta_offsets.py RUN_DIR [RUN_DIR ...] [--episodes 20]

For each ``test_tasks/<i>/expression.txt`` (task params from ``tasks.json``) it plays three
variants of the formula with deterministic actions (tanh, scaled to the action bounds, as
``policy.py`` does): as exported; with the additive constant inside every sin/cos set to 0; and
with the top-level additive constant set to 0 as well. It prints the mean return over the test
tasks per run. The formulas are read from ``expression.txt`` (constants rounded to 4 digits) and
evaluated with plain math, without the protected operators, so use it for formulas of sums,
products, sin and cos (CSP's cartpole_fl_ood formulas). Used for the CSP diagnosis in the README
(Meta-RL, cartpole_fl_ood). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import sympy as sp

from espl_jax import meta_report, reference_eval, run, rundir
from espl_jax.envs.base import action_center_half_range, to_env_units


def zero_offsets(expr: sp.Expr) -> dict[str, sp.Expr]:
    """The formula, without the constants inside sin/cos, and without those and its own."""
    inner = expr.replace(
        lambda e: isinstance(e, (sp.sin, sp.cos)),
        lambda e: e.func(e.args[0] - e.args[0].as_coeff_Add()[0]),
    )
    return {
        "as exported": expr,
        "inner offsets 0": inner,
        "all offsets 0": inner - inner.as_coeff_Add()[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", help="meta-RL run directories")
    parser.add_argument("--episodes", type=int, default=20)
    args = parser.parse_args()
    for run_dir in map(Path, args.run_dirs):
        config = run.saved_config(run_dir)
        tasks = json.loads((run_dir / meta_report.TASKS_FILE).read_text())["test"]
        means: dict[str, list[float]] = {}
        for i, task in enumerate(tasks):
            task_dir = run_dir / meta_report.TEST_TASKS_DIR / str(i)
            policy = reference_eval.load_policy(task_dir / rundir.POLICY_FILE)
            center, half_range = action_center_half_range(policy.ACTION_LOW, policy.ACTION_HIGH)
            xs = sp.symbols(f"x0:{policy.OBS_DIM}")
            lines = (task_dir / rundir.EXPRESSION_FILE).read_text().splitlines()
            exprs = [sp.sympify(line.split("=", 1)[1], {str(x): x for x in xs}) for line in lines]
            variants = [zero_offsets(e) for e in exprs]
            for name in variants[0]:
                fns = [sp.lambdify(xs, v[name], "math") for v in variants]

                def act(obs, fns=fns, center=center, half_range=half_range):
                    u = np.tanh([f(*obs) for f in fns])
                    return to_env_units(u, center, half_range)

                returns = reference_eval.rollout_returns(
                    act, config.env, args.episodes, 1000, **task
                )
                means.setdefault(name, []).append(float(returns.mean()))
        cells = ", ".join(f"{k} {np.mean(v):.2f}" for k, v in means.items())
        print(f"{run_dir}: mean over {len(tasks)} test tasks × {args.episodes} episodes: {cells}")


if __name__ == "__main__":
    main()
