"""The host loop of a training run and its run directory. NOT jittable: I/O and logging only.

Between compiled chunks the host logs metrics, draws the progress bar, evaluates the deterministic
policy for the learning curve, and checkpoints. At the end it exports each seed's formula, picks
the best seed by evaluating the exported formula, and writes the run directory. For host-stepped
gymnasium envs (Box2D) the chunks and evaluations come from :mod:`espl_jax.host` instead of the
compiled ones (``chunk_runner``, ``evaluator``); the run directory is the same:

    config.yaml         the resolved config
    metrics.jsonl       one row per iteration and seed (+ deterministic eval after each chunk)
    learning_curve.png  return, L0 ratio, penalty and τ against env steps
    checkpoints/        orbax checkpoints of the seed-stacked TrainState
    expression.txt      the best seed's simplified formula, rounded for reading
    policy.py           standalone act(obs) -> action in the env's own units
    eval.json           returns of the exported policy, per seed and for the best one
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from espl_jax import checkpoint, evaluation, host
from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax.config import Config, UserError
from espl_jax.sac import TrainState
from espl_jax.trainer import Trainer

CHECKPOINT_DIR = "checkpoints"
METRICS_FILE = "metrics.jsonl"
EVAL_FILE = "eval.json"
POLICY_FILE = "policy.py"
EXPRESSION_FILE = "expression.txt"
CURVE_FILE = "learning_curve.png"
# Metrics whose non-finite value means the run has diverged.
LOSS_KEYS = ("critic_loss", "actor_loss", "penalty", "q")


class TrainingDiverged(UserError):
    """A loss became non-finite; the last good checkpoint is kept."""


def default_run_dir(config: Config) -> Path:
    return Path("runs") / f"{config.env}-{config.actor}-{time.strftime('%Y%m%d-%H%M%S')}"


def train(
    config: Config,
    run_dir: str | Path,
    resume: bool = False,
    show_progress: bool = True,
    stop_after: int | None = None,
) -> dict[str, Any]:
    """Train (or resume) a run and write its run directory.

    Args:
        config: the resolved config.
        run_dir: where to write; must not hold another run unless ``resume``.
        resume: continue from the newest checkpoint in ``run_dir``.
        show_progress: draw a progress bar.
        stop_after: stop after this many iterations in total without the final export (for
            tests of interrupted runs); None runs to ``config.iterations`` and exports.

    Returns:
        The content of eval.json (empty if stopped early).
    """
    run_dir = Path(run_dir)
    trainer = Trainer(config)
    trainer.env  # noqa: B018  (fail fast on an unknown env, before anything is written)
    state = trainer.init_seeds()
    start = 0
    if resume:
        start, state = checkpoint.restore_latest(run_dir / CHECKPOINT_DIR, state)
        _truncate_metrics(run_dir / METRICS_FILE, start)
    else:
        if (run_dir / CHECKPOINT_DIR).exists():
            raise UserError(f"{run_dir} already holds a run; use --resume {run_dir} or a new --out")
        run_dir.mkdir(parents=True, exist_ok=True)
        config_lib.save(config, run_dir / "config.yaml")
        (run_dir / METRICS_FILE).write_text("")

    end = config.iterations if stop_after is None else min(stop_after, config.iterations)
    started = time.perf_counter()
    run_chunk, close = chunk_runner(trainer)
    progress_eval = evaluator(trainer, config.progress_eval_episodes)
    bar = tqdm(
        total=config.iterations,
        initial=start,
        desc=f"{config.env} ({config.seeds} seed{'s' if config.seeds > 1 else ''})",
        unit="it",
        disable=not show_progress,
    )
    with checkpoint.manager(run_dir / CHECKPOINT_DIR) as mngr, close:
        iteration = start
        while iteration < end:
            length = min(config.chunk_iterations, end - iteration)
            new_state, metrics = run_chunk(state, length)
            metrics = jax.device_get(metrics)
            _check_finite(metrics, iteration, run_dir, mngr.latest_step())
            eval_keys = jax.vmap(jax.random.fold_in, (0, None))(new_state.key, 1)
            eval_returns = np.asarray(progress_eval(new_state.actor, eval_keys))
            _append_metrics(run_dir / METRICS_FILE, metrics, eval_returns)
            state = new_state
            iteration += length
            checkpoint.save(mngr, iteration, state)
            plot_learning_curve(run_dir / METRICS_FILE, run_dir / CURVE_FILE, config.env)
            bar.update(length)
            bar.set_postfix(
                eval_return=f"{eval_returns.mean():.1f}",
                l0=f"{float(np.mean(metrics['l0_ratio'][:, -1])):.3f}",
            )
    bar.close()
    train_seconds = time.perf_counter() - started
    if iteration < config.iterations:
        return {}
    return finish(trainer, state, run_dir, train_seconds)


def chunk_runner(trainer: Trainer) -> tuple[Any, contextlib.AbstractContextManager]:
    """``(run_chunk, closer)``: ``run_chunk(state, length) -> (state, metrics [S, length])``.

    JAX envs: one compiled ``Trainer.compiled_chunk`` per chunk length. Host (Box2D) envs: the
    host collector of :mod:`espl_jax.host`, whose gymnasium envs ``closer`` closes on exit.
    """
    if trainer.on_host:
        collector = host.HostCollector(trainer)
        return collector.chunk, contextlib.closing(collector)
    compiled: dict[int, Any] = {}

    def run_chunk(state: TrainState, length: int):
        if length not in compiled:
            compiled[length] = trainer.compiled_chunk(length)
        return compiled[length](state)

    return run_chunk, contextlib.nullcontext()


def evaluator(trainer: Trainer, episodes: int):
    """(actor params [S, ...], keys [S, 2]) -> returns [S, episodes] of the eval-mask policy.

    In JAX for JAX envs, in gymnasium on the host for host (Box2D) envs.
    """
    if trainer.on_host:
        return host.HostEvaluator(trainer, episodes)
    return trainer.compiled_evaluate(episodes)


def finish(
    trainer: Trainer, state: TrainState, run_dir: Path, train_seconds: float
) -> dict[str, Any]:
    """Export every seed, pick the best by its exported formula's return, write the artifacts."""
    cfg, env = trainer.config, trainer.env
    evaluate = evaluator(trainer, cfg.eval_episodes)
    # Select on one set of episodes, report on a fresh one, so the reported figure is unbiased.
    # A single seed needs no selection (for MJX envs it would double the final evaluation).
    report_keys = jax.vmap(jax.random.fold_in, (0, None))(state.key, 3)
    report = np.asarray(evaluate(state.actor, report_keys))
    best = 0
    if cfg.seeds > 1:
        select_keys = jax.vmap(jax.random.fold_in, (0, None))(state.key, 2)
        selection = np.asarray(evaluate(state.actor, select_keys))
        best = int(np.argmax(selection.mean(axis=1)))

    per_seed = []
    formulas = {}
    for s in range(cfg.seeds):
        actor = jax.tree.map(lambda x, s=s: np.asarray(x[s]), state.actor)
        entry = {"seed": s, "jax_eval": evaluation.summary(report[s])}
        if trainer.sac.actor.symbolic is not None:
            exprs = export_expressions(trainer, actor)
            formulas[s] = exprs
            entry["formula"] = ex.to_text(exprs)
            entry["length"] = ex.mean_complexity([ex.readable(e) for e in exprs])
        per_seed.append(entry)

    result: dict[str, Any] = {
        "env": cfg.env,
        "actor": cfg.actor,
        "best_seed": best,
        "training": {
            "episodes": int(state.episodes[best]),
            "env_steps": int(state.env_steps[best]),
            "iterations": int(state.iteration[best]),
            "wall_seconds_training": round(train_seconds, 1),
        },
        "jax_eval": per_seed[best]["jax_eval"],
        # where "jax_eval" ran: JAX envs in JAX, host (Box2D) envs in gymnasium
        "evaluated_in": "gymnasium" if trainer.on_host else "jax",
        "per_seed": per_seed,
    }
    if best in formulas:
        exprs = formulas[best]
        (run_dir / EXPRESSION_FILE).write_text(ex.to_text(exprs) + "\n")
        source = ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high)
        (run_dir / POLICY_FILE).write_text(source)
        result["formula"] = per_seed[best]["formula"]
        result["length"] = per_seed[best]["length"]
        if cfg.reference_eval_episodes:
            policy = evaluation.load_policy(run_dir / POLICY_FILE)
            returns = evaluation.rollout_returns(policy.act, cfg.env, cfg.reference_eval_episodes)
            result["reference_eval"] = evaluation.summary(returns)
    (run_dir / EVAL_FILE).write_text(json.dumps(result, indent=2) + "\n")
    return result


def export_expressions(trainer: Trainer, actor_params: dict) -> list:
    """Protected sympy expressions of one seed's deterministic symbolic policy."""
    network = trainer.sac.actor.symbolic
    probs = actor_params["probs"] if trainer.sac.actor.uses_selector else None
    return ex.network_expressions(network, actor_params["mean"], probs)


def load_run(run_dir: str | Path) -> tuple[Trainer, TrainState, int]:
    """Config, trainer and newest checkpointed state of a run directory."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise UserError(f"{run_dir} is not a run directory (no config.yaml)")
    trainer = Trainer(config_lib.load(run_dir / "config.yaml"))
    step, state = checkpoint.restore_latest(run_dir / CHECKPOINT_DIR, trainer.init_seeds())
    return trainer, state, step


# Metrics ---------------------------------------------------------------------------------------


def _check_finite(metrics: dict, start: int, run_dir: Path, last_good: int | None) -> None:
    for name in LOSS_KEYS:
        values = np.asarray(metrics[name])  # (seeds, iterations)
        bad = ~np.isfinite(values)
        if bad.any():
            seed, offset = map(int, np.argwhere(bad)[0])
            kept = (
                f"the last good checkpoint (iteration {last_good}) is kept in "
                f"{run_dir / CHECKPOINT_DIR}"
                if last_good is not None
                else "no checkpoint had been written yet"
            )
            raise TrainingDiverged(
                f"training stopped: {name} became non-finite at iteration {start + offset + 1} "
                f"(seed {seed}); {kept}"
            )


def _append_metrics(path: Path, metrics: dict, eval_returns: np.ndarray) -> None:
    seeds, length = np.asarray(metrics["iteration"]).shape
    with path.open("a") as f:
        for i in range(length):
            for s in range(seeds):
                row = {k: _scalar(v[s, i]) for k, v in metrics.items()}
                row["seed"] = s
                if i == length - 1:
                    row["eval_return"] = float(eval_returns[s].mean())
                f.write(json.dumps(row) + "\n")


def _scalar(x: Any) -> float | int:
    x = np.asarray(x)
    return int(x) if np.issubdtype(x.dtype, np.integer) else float(x)


def _truncate_metrics(path: Path, iteration: int) -> None:
    """Drop rows written after the checkpoint a resumed run restarts from."""
    if path.exists():
        rows = [r for r in read_metrics(path) if r["iteration"] <= iteration]
        path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def read_metrics(path: str | Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def plot_learning_curve(metrics_path: Path, out: Path, title: str) -> None:
    """Return (training episodes and deterministic eval), L0 ratio, penalty and τ vs env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_metrics(metrics_path)
    if not rows:
        return
    fig, axes = plt.subplots(2, 2, figsize=(10, 7), sharex=True)
    panels = [
        ("train_return", "return", axes[0, 0]),
        ("l0_ratio", "L0 ratio (E||m||0 / N)", axes[0, 1]),
        ("penalty", "operator penalty", axes[1, 0]),
        ("tau", "temperature τ", axes[1, 1]),
    ]
    seeds = sorted({r["seed"] for r in rows})
    for s in seeds:
        mine = [r for r in rows if r["seed"] == s]
        steps = [r["env_steps"] for r in mine]
        for key, label, ax in panels:
            values = [
                r[key] if r.get("episodes_finished", 1) or key != "train_return" else math.nan
                for r in mine
            ]
            ax.plot(
                steps,
                values,
                lw=1,
                alpha=0.6 if key == "train_return" else 1.0,
                label=f"seed {s} (training)" if key == "train_return" else f"seed {s}",
            )
            ax.set_ylabel(label)
        evals = [(r["env_steps"], r["eval_return"]) for r in mine if "eval_return" in r]
        if evals:
            axes[0, 0].plot(*zip(*evals, strict=True), "o-", lw=2, label=f"seed {s} (formula)")
    axes[0, 1].set_yscale("log")
    for ax in axes[1]:
        ax.set_xlabel("environment steps")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"ESPL on {title}")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
