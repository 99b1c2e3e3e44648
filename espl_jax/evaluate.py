"""python -m espl_jax.evaluate RUN_DIR: returns of the exported policy.py in the reference env."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from espl_jax import envs, reference_eval, run, rundir, runlock
from espl_jax.cli import check_path, run_main
from espl_jax.config import UserError
from espl_jax.keys import EVALUATE_FIRST_EPISODE


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m espl_jax.evaluate",
        description="Run a run directory's exported policy.py in the reference environment "
        "(gymnasium, or DSO's CartPole in numpy) and report its mean return; the result is "
        "recorded in eval.json under 'reference_eval'.",
    )
    p.add_argument("run_dir", help="a run directory written by espl_jax.train")
    p.add_argument("--episodes", type=int, default=1000, help="episodes (default: 1000)")
    p.add_argument("--seed", type=int, default=EVALUATE_FIRST_EPISODE, help="first episode seed")
    args = p.parse_args(argv)
    if args.episodes <= 0:
        raise UserError("--episodes must be positive")
    if args.seed < 0:  # gymnasium refuses negative seeds with a traceback
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    check_path(args.run_dir, "RUN_DIR")
    run_dir = Path(args.run_dir)
    config = run.saved_config(run_dir)
    if envs.is_family(config.env):
        raise UserError(
            f"{config.env} is a meta-RL task family: its run was evaluated by PEARL's protocol "
            "(eval.json), and each test task's adapted policy.py is in test_tasks/<i>/"
        )
    if not reference_eval.has_reference(config.env):
        raise UserError(
            f"{config.env} has no reference environment to evaluate policy.py in "
            f"(known: {', '.join(reference_eval.REFERENCE_ENVS)}); its eval.json holds the JAX "
            "evaluation of the same formula"
        )
    with runlock.hold(run_dir):  # eval.json is read here and rewritten below
        record = rundir.read_eval(run_dir) or {}  # first: a corrupt eval.json is never overwritten
        policy = reference_eval.load_policy(run_dir / rundir.POLICY_FILE)
        returns = reference_eval.rollout_returns(policy.act, config.env, args.episodes, args.seed)
        summary = rundir.return_summary(returns)
        record["reference_eval"] = {**summary, "first_seed": args.seed}
        rundir.write_json(run_dir / rundir.EVAL_FILE, record)
    print(
        f"{config.env}: {summary['mean']:.2f} ± {summary['std']:.2f} over "
        f"{summary['episodes']} episodes (min {summary['min']:.2f}, max {summary['max']:.2f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
