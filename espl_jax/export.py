"""python -m espl_jax.export RUN_DIR: print or write a run's formula in one of four formats.

- default: the formula the run exported (the best seed of eval.json), rebuilt from its newest
  checkpoint: the hall of fame's anchor with ``keep_best_formula``, else the final one;
- ``--pick best|shortest-within PCT|stable-within PCT``: one from the hall of fame
  (formulas.jsonl: every chunk's formula with its selection return and local stability), written
  as expression.txt and policy.py into RUN/picked/ (or ``--output DIR``); ``stable-within`` is the
  shortest formula that ``python -m espl_jax.analyze`` finds locally stable within PCT percent of
  the best selection return (envs with an equilibrium only);
- ``--task I`` (meta-RL runs): the CSP formula adapted to test task I by the protocol.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax import run, rundir
from espl_jax.cli import check_path, run_main
from espl_jax.config import Config, UserError
from espl_jax.seeds import one_seed

FORMATS = ("text", "latex", "python", "c")
PICK_DIR = "picked"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m espl_jax.export",
        description="Export the symbolic policy of a run: the one it exported (rebuilt from its "
        "newest checkpoint: the hall of fame's best with keep_best_formula), one from its hall "
        "of fame (--pick), or the one adapted to a meta-RL test task (--task).",
    )
    p.add_argument("run_dir", help="a run directory written by espl_jax.train")
    p.add_argument("--format", choices=FORMATS, default="text")
    p.add_argument("--seed", type=int, help="which seed (default: the best one in eval.json)")
    p.add_argument(
        "--output", "-o", help="write to this file (with --pick: this directory) instead"
    )
    p.add_argument(
        "--pick",
        nargs="+",
        metavar="HOW",
        help="'best' (highest selection return), 'shortest-within PCT' (the shortest formula "
        "within PCT percent of the best) or 'stable-within PCT' (the same among the formulas "
        "that are locally stable at the env's equilibrium, as python -m espl_jax.analyze "
        "decides; envs with an equilibrium only): writes expression.txt and policy.py",
    )
    p.add_argument("--task", type=int, help="meta-RL: the formula adapted to test task TASK")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    check_path(args.run_dir, "RUN_DIR")
    check_path(args.output, "--output")  # '' would print (or write into RUN/picked/) instead
    config = run.saved_config(args.run_dir)
    if config.actor != "symbolic":
        raise UserError(
            f"{args.run_dir} trained an {config.actor.upper()} actor: there is no formula to export"
        )
    if args.pick:
        return pick(args, config)
    trainer, state, _ = run.load_run(args.run_dir)
    if trainer.meta and args.task is None:
        raise UserError(
            f"{args.run_dir} is a meta-RL run: give --task I for the formula adapted to test "
            f"task I (0 … {trainer.family.n_test - 1})"
        )
    if not trainer.meta and args.task is not None:
        raise UserError("--task applies to meta-RL runs only")
    seed = args.seed
    record = None
    if seed is None or trainer.meta:
        try:
            record = rundir.read_eval(args.run_dir)
        except UserError as err:
            raise UserError(f"{err}; give --seed to export a seed without it") from None
    if seed is None:
        seed = record.get("best_seed", 0) if record else 0
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise UserError(
                f"{Path(args.run_dir) / rundir.EVAL_FILE} has a bad best_seed ({seed!r}); "
                "give --seed to export a seed without it"
            )
    if not 0 <= seed < trainer.config.seeds:
        raise UserError(f"--seed must be in [0, {trainer.config.seeds - 1}]")
    # The actor the run exported (the hall of fame's anchor with keep_best_formula), not
    # necessarily the newest one: the formula of expression.txt and policy.py.
    actors, _ = run.exported_actors(trainer, state)
    actor = one_seed(actors, seed)
    if trainer.meta:
        tasks = (record or {}).get("test", {}).get("per_task", [])
        if not 0 <= args.task < len(tasks):
            raise UserError(
                f"--task must name a test task evaluated in eval.json (0 … {len(tasks) - 1})"
            )
        if seed != record.get("best_seed"):
            raise UserError("eval.json holds the adapted latents of the best seed only")
        actor = trainer.task_policy(actor, np.asarray(tasks[args.task]["z"]))
    exprs = ex.export_expressions(trainer, actor)
    write(exprs, trainer.env, args.format, args.output)
    return 0


def write(exprs: list, env, fmt: str, output: str | None) -> None:
    text = {
        "text": lambda: ex.to_text(exprs),
        "latex": lambda: ex.to_latex(exprs),
        "python": lambda: ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high),
        "c": lambda: ex.to_c(exprs, env.obs_dim, env.action_low, env.action_high),
    }[fmt]()
    if output is not None:
        Path(output).write_text(text if text.endswith("\n") else text + "\n")
    else:
        print(text)


def pick(args: argparse.Namespace, config: Config) -> int:
    how = args.pick[0]
    within = None
    if how in ("shortest-within", "stable-within"):
        if len(args.pick) != 2:
            raise UserError(f"--pick {how} takes a percentage, e.g. 5")
        try:
            within = float(args.pick[1])
        except ValueError:
            raise UserError(f"--pick {how}: {args.pick[1]!r} is not a number") from None
    elif how != "best" or len(args.pick) != 1:
        raise UserError("--pick takes 'best', 'shortest-within PCT' or 'stable-within PCT'")
    if how == "stable-within":
        hof.require_stability(config.env)  # before reading the hall of fame
    path = Path(args.run_dir) / hof.FORMULAS_FILE
    if not path.is_file():
        raise UserError(f"{args.run_dir} has no hall of fame ({hof.FORMULAS_FILE} is missing)")
    rows = hof.read(path)
    if args.seed is not None:
        if not 0 <= args.seed < config.seeds:
            raise UserError(f"--seed must be in [0, {config.seeds - 1}]")
        rows = [r for r in rows if r["seed"] == args.seed]
    chosen = hof.pick(rows, how, within, env=config.env)
    exprs = hof.expressions(chosen)
    env = run.Trainer(config).env
    out = Path(args.output) if args.output is not None else Path(args.run_dir) / PICK_DIR
    out.mkdir(parents=True, exist_ok=True)
    (out / rundir.EXPRESSION_FILE).write_text(ex.to_text(exprs) + "\n")
    source = ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high)
    (out / rundir.POLICY_FILE).write_text(source)
    verdict = chosen.get("stability")
    stability = (
        f", {verdict} at the equilibrium (spectral radius {chosen['spectral_radius']:.6f})"
        if verdict is not None
        else ""
    )
    print(
        f"picked iteration {chosen['iteration']}, seed {chosen['seed']}: selection return "
        f"{chosen['selection_return']:.2f}, length {chosen['length']:.0f}{stability}; wrote "
        f"{out / rundir.EXPRESSION_FILE} and {out / rundir.POLICY_FILE}"
    )
    print(ex.to_text(exprs))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
