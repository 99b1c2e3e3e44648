"""python -m espl_jax.export RUN_DIR --format text|latex|python|c: print a run's formula."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np

from espl_jax import expression as ex
from espl_jax import run
from espl_jax.cli import run_main
from espl_jax.config import UserError

FORMATS = ("text", "latex", "python", "c")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m espl_jax.export",
        description="Export the symbolic policy of a run from its newest checkpoint.",
    )
    p.add_argument("run_dir", help="a run directory written by espl_jax.train")
    p.add_argument("--format", choices=FORMATS, default="text")
    p.add_argument("--seed", type=int, help="which seed (default: the best one in eval.json)")
    p.add_argument("--output", "-o", help="write to this file instead of standard output")
    args = p.parse_args(argv)
    trainer, state, _ = run.load_run(args.run_dir)
    if trainer.sac.actor.symbolic is None:
        raise UserError(f"{args.run_dir} trained an MLP actor: there is no formula to export")
    seed = args.seed
    if seed is None:
        eval_path = Path(args.run_dir) / run.EVAL_FILE
        seed = json.loads(eval_path.read_text())["best_seed"] if eval_path.is_file() else 0
    if not 0 <= seed < trainer.config.seeds:
        raise UserError(f"--seed must be in [0, {trainer.config.seeds - 1}]")
    actor = jax.tree.map(lambda x: np.asarray(x[seed]), state.actor)
    exprs = run.export_expressions(trainer, actor)
    env = trainer.env
    text = {
        "text": lambda: ex.to_text(exprs),
        "latex": lambda: ex.to_latex(exprs),
        "python": lambda: ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high),
        "c": lambda: ex.to_c(exprs, env.obs_dim, env.action_low, env.action_high),
    }[args.format]()
    if args.output:
        Path(args.output).write_text(text if text.endswith("\n") else text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
