"""The host loop of a training run. NOT jittable: I/O and logging only.

Between compiled chunks the host logs metrics, draws the progress bar, evaluates the deterministic
policy for the learning curve, and checkpoints. At the end it exports each seed's formula, picks
the best seed by evaluating the exported formula, and writes the run directory (its files and how
they are written: :mod:`espl_jax.rundir`). Every env, host-stepped ones included (MuJoCo's C
engine, gymnasium's Box2D), runs through the same compiled chunks and evaluations.
"""

from __future__ import annotations

import itertools
import tempfile
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from espl_jax import checkpoint, faults, meta_report, reference_eval, replay, rundir, runlock
from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax.config import Config, UserError
from espl_jax.keys import PROGRESS_EVAL, REFERENCE_FIRST_EPISODE, REPORT, SELECTION, salted
from espl_jax.learner import Trainer
from espl_jax.sac import TrainState
from espl_jax.seeds import gather, one_seed

# Metrics whose non-finite value means the run has diverged.
LOSS_KEYS = ("critic_loss", "actor_loss", "penalty", "q")


class TrainingDiverged(UserError):
    """A loss became non-finite; the last good checkpoint is kept."""


def new_run_dir(config: Config, root: str | Path = "runs") -> Path:
    """A new, empty run directory ``runs/ENV-ACTOR-TIME[-N]``, created here.

    ``mkdir`` is atomic, so two runs started in the same second get different directories
    (the second one gets a ``-2`` suffix, and so on).
    """
    stem = f"{config.env}-{config.actor}-{time.strftime('%Y%m%d-%H%M%S')}"
    Path(root).mkdir(parents=True, exist_ok=True)
    for n in itertools.count(1):
        path = Path(root) / (stem if n == 1 else f"{stem}-{n}")
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue
    raise AssertionError("unreachable")


def saved_config(run_dir: str | Path) -> Config:
    """The config a run directory was trained with (its config.yaml).

    Raises:
        UserError: not a run directory, or an unreadable config.yaml.
    """
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise UserError(f"{run_dir} is not a run directory (no config.yaml)")
    values = config_lib.load_yaml(path)
    # Runs saved before the physics key existed stepped MuJoCo in MJX: their checkpoints hold
    # MJX states, so they resume on MJX.
    values.setdefault("physics", "mjx")
    return config_lib.from_mapping(values)


def resume_config(
    run_dir: str | Path, iterations: int | None = None, devices: int | None = None
) -> Config:
    """The saved config of a run directory, with ``iterations`` changed to extend it (and the
    devices to run on, which do not change the results)."""
    config = saved_config(run_dir)
    changes = {
        k: v for k, v in {"iterations": iterations, "devices": devices}.items() if v is not None
    }
    return config_lib.from_mapping(changes, base=config) if changes else config


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

    Raises:
        UserError: bad input, or another process holds ``run_dir`` (``runlock``).
    """
    run_dir = Path(run_dir)
    trainer = Trainer(config)
    # Fail fast on an unknown env or too many devices, before anything is written.
    trainer.env  # noqa: B018
    trainer.seed_axis.mesh  # noqa: B018
    if jax.process_index() != 0:  # process 0 holds the run directory for the whole group
        return _train(trainer, run_dir, resume, show_progress, stop_after)
    run_dir.mkdir(parents=True, exist_ok=True)  # resume: it exists (config.yaml was read)
    with runlock.hold(run_dir):
        return _train(trainer, run_dir, resume, show_progress, stop_after)


def _train(
    trainer: Trainer, run_dir: Path, resume: bool, show_progress: bool, stop_after: int | None
) -> dict[str, Any]:
    config = trainer.config
    # Multi-process runs (--distributed): every process computes, all write the checkpoints
    # (each its own seeds' shards; orbax coordinates), and only process 0 writes the other files
    # of the run directory; the others write theirs to a scratch directory.
    primary = jax.process_index() == 0
    out = run_dir if primary else Path(tempfile.mkdtemp(prefix=f"espl-{jax.process_index()}-"))
    if resume:
        start, state = restore(run_dir, trainer)
        if start > config.iterations:
            raise UserError(
                f"{run_dir} has already trained {start} iterations; --iterations must be at "
                f"least {start} to resume it"
            )
        rundir.truncate_metrics(out / rundir.METRICS_FILE, start)
        rundir.truncate_metrics(out / hof.FORMULAS_FILE, start)
        # Written after the checkpoint proved readable; a kill in between is harmless (the next
        # resume re-reads the checkpoint and fits its buffer again).
        if primary and config_lib.load(run_dir / "config.yaml") != config:
            rundir.write_atomic(run_dir / "config.yaml", config_lib.dump(config))
    else:
        if (run_dir / rundir.CHECKPOINT_DIR).exists():
            raise UserError(f"{run_dir} already holds a run; use --resume {run_dir} or a new --out")
        _barrier("run directory checked")  # before any process creates checkpoints/
        run_dir.mkdir(parents=True, exist_ok=True)
        rundir.write_atomic(out / "config.yaml", config_lib.dump(config))
        (out / rundir.METRICS_FILE).write_text("")
        if keeps_hall_of_fame(trainer):
            (out / hof.FORMULAS_FILE).write_text("")
        state = trainer.init_seeds()
        start = 0

    end = config.iterations if stop_after is None else min(stop_after, config.iterations)
    warnings: list[str] = []
    # Read from run_dir, which every process shares (the checkpoints are there): only process 0
    # writes timing.json, and the others' ``out`` is a scratch directory without it.
    earlier_seconds = 0.0 if start == 0 else rundir.training_seconds_before(run_dir, start)
    if earlier_seconds is None:
        earlier_seconds = 0.0
        warnings.append(
            f"{rundir.TIMING_FILE} has no time for iteration {start}: wall_seconds_training "
            "counts only the training after this resume"
        )
    started = time.perf_counter() - earlier_seconds
    run_chunk = chunk_runner(trainer)
    progress_eval = progress_evaluator(trainer)
    bar = tqdm(
        total=config.iterations,
        initial=start,
        desc=f"{config.env} ({config.seeds} seed{'s' if config.seeds > 1 else ''})",
        unit="it",
        disable=not show_progress or not primary,
    )
    with checkpoint.manager(run_dir / rundir.CHECKPOINT_DIR) as mngr:
        if not resume:  # a run killed before its first chunk ends resumes from here
            checkpoint.save(mngr, 0, state)
        if start == 0 and trainer.task_set.initial_steps:  # PEARL's initial collection
            state = warmup(trainer, state)
        iteration = start
        while iteration < end:
            length = min(config.chunk_iterations, end - iteration)
            new_state, metrics = run_chunk(state, length)
            # The chunk is still running (dispatch is asynchronous).
            faults.kill_point(f"chunk:{iteration + length}")
            metrics = gather(metrics)
            diverged = _non_finite(metrics, iteration)
            if diverged:
                # Keep the failing chunk's rows, so the user can see what diverged and how.
                rundir.append_metrics(out / rundir.METRICS_FILE, metrics, None)
                raise TrainingDiverged(diverged + "; " + _kept(run_dir, mngr.latest_step()))
            eval_keys = salted(new_state.key, PROGRESS_EVAL)
            eval_returns = gather(progress_eval(new_state, eval_keys))
            rundir.append_metrics(out / rundir.METRICS_FILE, metrics, eval_returns)
            state = new_state
            iteration += length
            if keeps_hall_of_fame(trainer):
                state = record_hall_of_fame(trainer, state, eval_returns, iteration, out)
            # Before the checkpoint: a kill between the two resumes from the older checkpoint,
            # whose time is still in timing.json.
            rundir.record_training_seconds(out, iteration, time.perf_counter() - started)
            checkpoint.save(mngr, iteration, state)
            rundir.warn_on_failure(
                warnings, "learning-curve plot", rundir.plot_learning_curve,
                out / rundir.METRICS_FILE, out / rundir.CURVE_FILE, config.env,
            )  # fmt: skip
            if keeps_hall_of_fame(trainer):
                rundir.warn_on_failure(
                    warnings, "hall-of-fame plot", hof.plot,
                    out / hof.FORMULAS_FILE, out / hof.PLOT_FILE, config.env,
                )  # fmt: skip
            bar.update(length)
            bar.set_postfix(
                eval_return=f"{eval_returns.mean():.1f}",
                l0=f"{float(np.mean(metrics['l0_ratio'][:, -1])):.3f}",
            )
    bar.close()
    train_seconds = time.perf_counter() - started
    if iteration < config.iterations:
        return {}
    return finish(trainer, state, out, train_seconds, warnings)


def _barrier(name: str) -> None:
    """Wait for every process of a multi-process run to get here (no-op in one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def keeps_hall_of_fame(trainer: Trainer) -> bool:
    """Single-task symbolic runs keep every chunk's formula (espl_jax.halloffame)."""
    return trainer.actor.one_formula


def record_hall_of_fame(
    trainer: Trainer, state: TrainState, eval_returns: np.ndarray, iteration: int, run_dir: Path
) -> TrainState:
    """formulas.jsonl rows for this chunk, and the anchor updated from t_s on."""
    returns = eval_returns.mean(axis=1)
    eligible = iteration >= trainer.config.schedule_iterations
    state = jax.jit(hof.update_anchor, static_argnums=2)(state, jnp.asarray(returns), eligible)
    env_steps, actors = gather((state.env_steps, state.actor))
    rows = hof.seed_rows(trainer, actors, returns, iteration=iteration, eligible=eligible)
    for r in rows:
        r["env_steps"] = int(env_steps[r["seed"]])
    hof.append(run_dir / hof.FORMULAS_FILE, rows)
    return state


def restore(run_dir: str | Path, trainer: Trainer) -> tuple[int, TrainState]:
    """The newest checkpoint of a run, fitted to ``trainer``'s config.

    The replay buffer's capacity follows the run's total env steps (capped by ``buffer_size``),
    so a run extended with ``--resume --iterations`` stored a smaller buffer than its new config
    builds: it is restored with the stored capacity and padded (``replay.resize``; such a buffer
    never wrapped), which makes the extended run equal to one planned that long from the start.

    A Box2D checkpoint written before the Box2D envs held their episodes in the state (its
    rollout has no env state) resumes as such runs did then: from freshly reset envs, the
    episodes in progress dropped.
    """
    template = trainer.init_seeds()
    capacity = trainer.task_set.buffer_capacity
    fresh_rollout = False

    def with_capacity(state: TrainState, n: int) -> TrainState:
        if state.buffer.data.reward.shape[-1] == n:  # [seeds, tasks, capacity]
            return state
        return state.replace(buffer=jax.vmap(lambda b: replay.resize(b, n))(state.buffer))

    def like(stored: dict) -> TrainState:
        nonlocal fresh_rollout
        stored_capacity = stored["buffer"]["data"]["reward"].shape[-1]  # [seeds, tasks, cap]
        state = with_capacity(template, stored_capacity)
        if stored["rollout"].get("env_state") is None and state.rollout.env_state is not None:
            fresh_rollout = True
            state = state.replace(rollout=state.rollout.replace(env_state=None))
        return state

    step, state = checkpoint.restore_latest(Path(run_dir) / rundir.CHECKPOINT_DIR, like)
    if fresh_rollout:
        state = state.replace(rollout=template.rollout)
    return step, trainer.seed_axis.place(with_capacity(state, capacity))


def chunk_runner(trainer: Trainer):
    """``run_chunk(state, length) -> (state, metrics [S, length])``: one compiled
    ``Trainer.compiled_chunk`` per chunk length."""
    compiled: dict[int, Any] = {}

    def run_chunk(state: TrainState, length: int):
        if length not in compiled:
            compiled[length] = trainer.compiled_chunk(length)
        return compiled[length](state)

    return run_chunk


def progress_evaluator(trainer: Trainer):
    """(state [S], keys [S, 2]) -> returns [S, n] for the learning curve after each chunk:
    single task, ``progress_eval_episodes`` episodes of the exported formula; meta-RL, PEARL's
    protocol on every test task (the last trajectory's return, averaged over runs)."""
    if trainer.meta:  # the two reports (below, finish): a family's test tasks, a task's formula
        adapt = meta_report.adapter(trainer, trainer.tasks[1])
        return lambda state, keys: gather(adapt(state, keys).final_return).mean(axis=-1)
    evaluate = evaluator(trainer, trainer.config.progress_eval_episodes)
    return lambda state, keys: gather(evaluate(state.actor, keys))


def warmup(trainer: Trainer, state: TrainState) -> TrainState:
    """Meta-RL: PEARL's initial collection."""
    state = trainer.compiled_warmup()(state)
    faults.kill_point("warmup")  # nothing of it is written yet (it may still be running)
    return state


def evaluator(trainer: Trainer, episodes: int):
    """(actor params [S, ...], keys [S, 2]) -> returns [S, episodes] of the eval-mask policy."""
    return trainer.compiled_evaluate(episodes)


def finish(
    trainer: Trainer,
    state: TrainState,
    run_dir: Path,
    train_seconds: float,
    warnings: list[str] | None = None,
) -> dict[str, Any]:
    """Export every seed, pick the best by its exported formula's return, write the artifacts.

    eval.json, expression.txt and policy.py are written before the optional reference
    evaluation (policy.py in gymnasium), so a failure there — or a kill — loses nothing: it
    becomes a warning in the output and in eval.json.
    """
    # Every seed on every process, as numpy (the replay buffers stay behind); the jitted
    # evaluations below take numpy input and shard it over the devices again.
    state = gather(state.replace(buffer=None, encoder_buffer=None))
    if trainer.meta:  # a family's report is per test task (meta_report); a single task's per seed
        return meta_report.finish(trainer, state, run_dir, train_seconds, list(warnings or []))
    cfg, env = trainer.config, trainer.env
    warnings = list(warnings or [])
    evaluate = evaluator(trainer, cfg.eval_episodes)
    actors, source = exported_actors(trainer, state)
    # Select on one set of episodes, report on a fresh one, so the reported figure is unbiased.
    # A single seed needs no selection (for MJX envs it would double the final evaluation).
    report_keys = salted(state.key, REPORT)
    report = gather(evaluate(actors, report_keys))
    best = 0
    if cfg.seeds > 1:
        select_keys = salted(state.key, SELECTION)
        selection = gather(evaluate(actors, select_keys))
        best = int(np.argmax(selection.mean(axis=1)))

    per_seed = []
    formulas = {}
    for s in range(cfg.seeds):
        actor = one_seed(actors, s)
        entry = {"seed": s, "jax_eval": rundir.return_summary(report[s]), "exported": source[s]}
        if source[s] == "best":
            entry["exported_iteration"] = int(state.anchor_iteration[s])
        if trainer.actor.symbolic is not None:
            exprs = ex.export_expressions(trainer, actor)
            formulas[s] = exprs
            entry["formula"] = ex.to_text(exprs)
            entry["length"] = ex.mean_complexity([ex.readable(e) for e in exprs])
        per_seed.append(entry)

    result: dict[str, Any] = {
        **rundir.result_header(trainer, state, best, train_seconds),
        "jax_eval": per_seed[best]["jax_eval"],
        # what simulated "jax_eval": "jax", or "gymnasium" for the Box2D envs
        "evaluated_in": env.simulator,
        "per_seed": per_seed,
    }
    if best in formulas:
        exprs = formulas[best]
        result["formula"] = per_seed[best]["formula"]
        result["length"] = per_seed[best]["length"]
        rundir.write_atomic(run_dir / rundir.EXPRESSION_FILE, ex.to_text(exprs) + "\n")
        source = ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high)
        rundir.write_atomic(run_dir / rundir.POLICY_FILE, source)
    rundir.write_eval(run_dir, result, warnings)
    faults.kill_point("export")
    if best in formulas and cfg.reference_eval_episodes:

        def reference() -> None:
            policy = reference_eval.load_policy(run_dir / rundir.POLICY_FILE)
            returns = reference_eval.rollout_returns(
                policy.act, cfg.env, cfg.reference_eval_episodes, REFERENCE_FIRST_EPISODE
            )
            result["reference_eval"] = rundir.return_summary(returns)

        rundir.warn_on_failure(warnings, "reference evaluation of policy.py", reference)
        rundir.write_eval(run_dir, result, warnings)
    return result


def exported_actors(trainer: Trainer, state: TrainState) -> tuple[Any, list[str]]:
    """Each seed's actor whose formula the run exports, and which one it is ("final" or
    "best": the hall of fame's anchor, with ``keep_best_formula`` once one was eligible).
    ``state`` is the host (numpy) copy that ``finish`` gathered."""
    seeds = trainer.config.seeds
    if not trainer.config.keep_best_formula or state.anchor is None:
        return state.actor, ["final"] * seeds
    has_anchor = np.isfinite(np.asarray(state.anchor_return))

    def pick(anchor, final):
        return np.where(has_anchor.reshape(-1, *([1] * (anchor.ndim - 1))), anchor, final)

    actors = jax.tree.map(pick, state.anchor, state.actor)
    return actors, ["best" if a else "final" for a in has_anchor]


def load_run(run_dir: str | Path) -> tuple[Trainer, TrainState, int]:
    """Config, trainer and newest checkpointed state of a run directory."""
    trainer = Trainer(saved_config(run_dir))
    step, state = restore(run_dir, trainer)
    return trainer, state, step


# Metrics ---------------------------------------------------------------------------------------


def _non_finite(metrics: dict, start: int) -> str | None:
    """What diverged in a chunk (metric, iteration, seed), or None if every loss is finite."""
    for name in LOSS_KEYS:
        values = np.asarray(metrics[name])  # (seeds, iterations)
        bad = ~np.isfinite(values)
        if bad.any():
            seed, offset = map(int, np.argwhere(bad)[0])
            return (
                f"training stopped: {name} became non-finite at iteration {start + offset + 1} "
                f"(seed {seed}); that chunk's metrics are in {rundir.METRICS_FILE}"
            )
    return None


def _kept(run_dir: Path, last_good: int | None) -> str:
    if last_good is None:
        return "no checkpoint had been written yet"
    checkpoints = run_dir / rundir.CHECKPOINT_DIR
    return f"the last good checkpoint (iteration {last_good}) is kept in {checkpoints}"
