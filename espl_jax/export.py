"""python -m espl_jax.export RUN_DIR --format text|latex|python|c: print a run's formula."""

from __future__ import annotations

import argparse
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
    config = run.saved_config(args.run_dir)
    if config.actor != "symbolic":
        raise UserError(f"{args.run_dir} trained an MLP actor: there is no formula to export")
    trainer, state, _ = run.load_run(args.run_dir)
    seed = args.seed
    if seed is None:
        try:
            record = run.read_eval(args.run_dir)
        except UserError as err:
            raise UserError(f"{err}; give --seed to export a seed without it") from None
        seed = record.get("best_seed", 0) if record else 0
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise UserError(
                f"{Path(args.run_dir) / run.EVAL_FILE} has a bad best_seed ({seed!r}); "
                "give --seed to export a seed without it"
            )
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
