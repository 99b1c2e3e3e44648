"""python -m espl_jax.train --env NAME: learn a symbolic policy from scratch (ESPL, Algorithm 1)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from espl_jax import config as config_lib
from espl_jax import run
from espl_jax.cli import check_path, run_main, use_compilation_cache
from espl_jax.config import Config, UserError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m espl_jax.train",
        description="Learn a compact symbolic policy with ESPL (SAC + symbolic network + path "
        "selector). Defaults come from configs/ENV.yaml; the run directory receives the config, "
        "metrics, a learning curve, checkpoints, the formula, policy.py and eval.json.",
    )
    p.add_argument(
        "--env",
        help="environment name (default: the --config file's env, else cartpole); "
        "see the README for the list",
    )
    p.add_argument("--seeds", type=int, help="independent runs vmapped together; best is kept")
    p.add_argument("--iterations", type=int, help="training iterations (collect + update)")
    p.add_argument(
        "--config",
        help="YAML file overriding configs/ENV.yaml (precedence: defaults < configs/ENV.yaml < "
        "--config < flags); it may set env",
    )
    p.add_argument(
        "--actor",
        choices=["symbolic", "mlp", "pearl", "hyper"],
        help="symbolic (ESPL; CSP on a task family), mlp (SAC), pearl or hyper (task families)",
    )
    p.add_argument("--seed", type=int, help="base random seed")
    p.add_argument(
        "--physics",
        choices=["auto", "mjx", "native"],
        help="MuJoCo tasks: native (MuJoCo's C engine on the host), mjx (MJX in the compiled "
        "program) or auto (native on a CPU, mjx on an accelerator; the default)",
    )
    p.add_argument("--out", help="run directory (default: runs/ENV-ACTOR-TIMESTAMP)")
    p.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="continue a run from its last checkpoint with its saved config; only --iterations "
        "(to extend it), --devices and --no-progress may be given with it",
    )
    p.add_argument(
        "--devices",
        type=int,
        help="devices to shard the seeds over (default: all of jax.devices() that divide --seeds)",
    )
    p.add_argument(
        "--distributed",
        action="store_true",
        help="run as one process of a multi-host run: call jax.distributed.initialize() first "
        "(see the README); without the three flags below JAX detects them (SLURM, Open MPI, ...)",
    )
    p.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's address (--distributed)")
    p.add_argument("--num-processes", type=int, help="processes in the run (--distributed)")
    p.add_argument("--process-id", type=int, help="this process's index (--distributed)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


# Flags that define a run; on --resume the run's saved config defines it instead.
RUN_DEFINING_FLAGS = ("env", "seeds", "config", "actor", "seed", "physics", "out")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    check_flags(args)
    if args.distributed:
        start_distributed(args)
    config = resolve_config(args)
    resume = args.resume is not None
    if resume:
        run_dir = Path(args.resume)
    elif args.out is not None:
        run_dir = Path(args.out)
    else:
        run_dir = run.new_run_dir(config)
    use_compilation_cache()
    started = time.perf_counter()
    result = run.train(config, run_dir, resume=resume, show_progress=not args.no_progress)
    wall = time.perf_counter() - started
    print(f"\nrun directory: {run_dir}")
    for warning in result.get("warnings", []):
        print(f"warning: {warning}")
    if "test" in result:
        print_meta(result)
    else:
        print_single_task(result)
    t = result["training"]
    print(
        f"trained on {t['episodes']} episodes / {t['env_steps']} env steps; wall time {wall:.0f} s"
    )
    return 0


def check_flags(args: argparse.Namespace) -> None:
    """Refuse flags that cannot be honoured as given, before anything starts.

    An empty path is refused (``cli.check_path``), never read as "not given": ``--out ''``
    would otherwise fall back to a new ``runs/…`` directory, ``--resume ''`` to a new run.
    """
    for flag in ("config", "out", "resume"):
        check_path(getattr(args, flag), f"--{flag}")
    if args.coordinator == "":
        raise UserError("--coordinator is empty: give process 0's HOST:PORT")
    if args.distributed:
        if args.out is None and args.resume is None:
            raise UserError("--distributed needs --out (or --resume): one run directory for all")
    elif any(x is not None for x in (args.coordinator, args.num_processes, args.process_id)):
        raise UserError("--coordinator, --num-processes and --process-id need --distributed")
    if args.resume is not None:
        given = [f"--{name}" for name in RUN_DEFINING_FLAGS if getattr(args, name) is not None]
        if given:
            raise UserError(
                f"--resume continues a run with its saved config; {', '.join(given)} cannot be "
                "changed on resume (only --iterations, --devices and --no-progress can)"
            )


def resolve_config(args: argparse.Namespace) -> Config:
    """The run's config from flags that passed ``check_flags``: the run's saved one on
    ``--resume``, else ``config.resolve``'s. Writes nothing."""
    if args.resume is not None:
        return run.resume_config(args.resume, iterations=args.iterations, devices=args.devices)
    return config_lib.resolve(
        args.env,
        args.config,
        seeds=args.seeds,
        iterations=args.iterations,
        actor=args.actor,
        seed=args.seed,
        physics=args.physics,
        devices=args.devices,
    )


def start_distributed(args: argparse.Namespace) -> None:
    """Join the run's process group (``jax.distributed.initialize``): every process then sees
    every host's devices in ``jax.devices()``, and the seed axis is sharded across all of them."""
    import jax

    given = {
        "coordinator_address": args.coordinator,
        "num_processes": args.num_processes,
        "process_id": args.process_id,
    }
    if any(v is not None for v in given.values()) and any(v is None for v in given.values()):
        raise UserError("--coordinator, --num-processes and --process-id go together")
    try:
        jax.distributed.initialize(**{k: v for k, v in given.items() if v is not None})
    except (ValueError, RuntimeError) as err:
        raise UserError(f"--distributed: could not join the process group ({err})") from None


def print_single_task(result: dict) -> None:
    if "formula" in result:
        print(f"formula (seed {result['train_seed']}, length {result['length']:.0f}):")
        print("  " + result["formula"].replace("\n", "\n  "))
    ev = result["jax_eval"]
    # Host (Box2D) envs are evaluated in gymnasium, JAX envs in JAX; an MLP has no formula.
    where = "in gymnasium" if result["evaluated_in"] == "gymnasium" else "in JAX"
    what = "exported policy" if "formula" in result else "deterministic policy"
    print(f"{what}, {ev['episodes']} episodes {where}: {ev['mean']:.2f} ± {ev['std']:.2f}")
    if "reference_eval" in result:
        ref = result["reference_eval"]
        print(
            f"policy.py in the reference env, {ref['episodes']} episodes: "
            f"{ref['mean']:.2f} ± {ref['std']:.2f}"
        )


def print_meta(result: dict) -> None:
    tasks = result["test"]["per_task"]
    print(
        f"{result['actor']} on {len(tasks)} test tasks (PEARL's protocol, seed "
        f"{result['train_seed']}): mean return {result['test']['mean']:.2f}; "
        f"on {result['train']['tasks']} training tasks {result['train']['mean']:.2f}"
    )
    if "length" in result:
        print(
            f"adapted formulas: mean length {result['length']:.1f}, "
            f"{result['selected_paths_per_action']:.1f} selected paths per action; "
            f"test_tasks/<i>/policy.py for each task, e.g. task 0:"
        )
        print("  " + tasks[0]["formula"].replace("\n", "\n  "))


if __name__ == "__main__":
    sys.exit(run_main(main))
