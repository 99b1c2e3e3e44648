"""The end-of-run report of a meta-RL run (CSP, PEARL, Hyper): evaluation by PEARL's protocol
and the adapted formulas. NOT jittable: host I/O, export and plotting; the protocol itself runs in
JAX (``Trainer.adapt``). Written into the run directory beside what every run has:

    tasks.json               {"seed", "train": [...], "test": [...]}: each task's params in the
                             env's own units (``TaskFamily.describe``)
    test_tasks/<i>/          CSP only: expression.txt and policy.py of the formula adapted to
                             test task i (index into tasks.json["test"]) by the protocol
    eval.json                per-test-task and mean returns (protocol), per seed, training budget
    coefficients.png         cartpole_fl_ood + CSP: the adapted formulas' coefficients of θ and θ̇
                             against force magnitude and pole length (the paper's Fig. 5)

Seeds: with several seeds the best is chosen by the protocol on training tasks and reported on
the test tasks (the selection never sees a test task).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import expression as ex
from espl_jax import faults, reference_eval, rollout, rundir
from espl_jax.keys import (
    COEFFICIENTS_OFFSET,
    FRESH_EPISODES_OFFSET,
    REFERENCE_FIRST_EPISODE,
    REPORT,
    SELECTION,
    offset_key,
    salted,
)
from espl_jax.learner import Trainer
from espl_jax.sac import TrainState
from espl_jax.seeds import gather, one_seed
from espl_jax.symbolic import live_paths

TASKS_FILE = "tasks.json"
TEST_TASKS_DIR = "test_tasks"
COEFFICIENTS_FILE = "coefficients.png"
# Fresh episodes of each test task with its adapted formula fixed (the check that the exported
# policy.py scores what the protocol reported).
FRESH_EPISODES = 20


def adapter(trainer: Trainer, task_params: Any):
    """Meta-RL: PEARL's protocol on ``task_params`` [N], (state [S], keys [S, 2]) -> Adapted
    [S, N, runs]."""
    return lambda state, keys: trainer.compiled_adapt(state, task_params, keys)


def write_tasks(trainer: Trainer, run_dir: Path) -> None:
    train, test = trainer.tasks
    family = trainer.family
    record = {
        "family": family.name,
        "seed": trainer.config.task_seed,
        "train": family.describe(train),
        "test": family.describe(test),
    }
    rundir.write_json(run_dir / TASKS_FILE, record)


def finish(
    trainer: Trainer,
    state: TrainState,
    run_dir: Path,
    train_seconds: float,
    warnings: list[str],
) -> dict[str, Any]:
    cfg, family = trainer.config, trainer.family
    train_params, test_params = trainer.tasks
    write_tasks(trainer, run_dir)

    test = gather(adapter(trainer, test_params)(state, salted(state.key, REPORT)))
    faults.kill_point("protocol")  # between the test tasks' protocol and the training tasks'
    # PEARL also evaluates on as many training tasks as there are test tasks.
    n = min(family.n_test, family.n_train)
    subset = jax.tree.map(lambda x: x[:n], train_params)
    train = gather(adapter(trainer, subset)(state, salted(state.key, SELECTION)))
    test_returns = np.asarray(test.final_return)  # [S, tasks, runs]
    train_returns = np.asarray(train.final_return)
    best = int(np.argmax(train_returns.mean(axis=(1, 2)))) if cfg.seeds > 1 else 0

    descriptions = family.describe(test_params)
    per_task = []
    for i in range(family.n_test):
        per_task.append(
            {
                "task": i,
                "params": descriptions[i],
                "return": float(test_returns[best, i].mean()),
                "runs": [float(r) for r in test_returns[best, i]],
                "first_trajectory_return": float(np.mean(test.first_return[best, i])),
                "z": [float(v) for v in test.z[best, i, 0]],
            }
        )
    result: dict[str, Any] = {
        **rundir.result_header(trainer, state, best, train_seconds),
        "protocol": {
            "runs_per_task": cfg.eval_runs,
            "steps_per_run": cfg.eval_steps,
            "posterior_after_trajectories": cfg.eval_exploration_trajectories,
            "reported": "return of the last trajectory, mean over runs and tasks",
        },
        "test": {"mean": float(test_returns[best].mean()), "per_task": per_task},
        "train": {"mean": float(train_returns[best].mean()), "tasks": n},
        "evaluated_in": trainer.env.simulator,
        "per_seed": [
            {
                "seed": s,
                "test_return": float(test_returns[s].mean()),
                "train_return": float(train_returns[s].mean()),
            }
            for s in range(cfg.seeds)
        ],
    }
    if trainer.actor.symbolic is not None:
        policies = _export_test_tasks(trainer, state, best, result, run_dir)
        rundir.write_json(run_dir / rundir.EVAL_FILE, {**result, "warnings": warnings})
        _fresh_episodes(trainer, state, best, result, policies, warnings)
        if cfg.env == "cartpole_fl_ood":
            rundir.warn_on_failure(
                warnings, "coefficient figure", coefficient_figure, trainer, state, best, run_dir
            )
    if warnings:
        result["warnings"] = warnings
    rundir.write_json(run_dir / rundir.EVAL_FILE, result)
    return result


def task_expressions(trainer: Trainer, actor_params: dict, z) -> list:
    """The protected sympy expressions of the CSP formula at latent z."""
    return ex.export_expressions(trainer, trainer.task_policy(actor_params, np.asarray(z)))


def _export_test_tasks(
    trainer: Trainer, state: TrainState, best: int, result: dict, run_dir: Path
) -> list[Path]:
    """test_tasks/<i>/{expression.txt, policy.py}: the formula the protocol adapted to task i.
    Returns the policy.py paths."""
    env, network = trainer.env, trainer.actor.symbolic
    actor = one_seed(state.actor, best)
    lengths, paths, files = [], [], []
    for entry in result["test"]["per_task"]:
        policy = trainer.task_policy(actor, np.asarray(entry["z"]))
        exprs = ex.export_expressions(trainer, policy)
        mask = jax.tree.map(np.asarray, trainer.actor.eval_mask(policy))
        masked = [w * m for w, m in zip(policy["mean"]["w"], mask, strict=True)]
        entry["formula"] = ex.to_text(exprs)
        entry["length"] = ex.mean_complexity([ex.readable(e) for e in exprs])
        entry["selected_paths"] = [int(c) for c in live_paths(network, masked)]
        lengths.append(entry["length"])
        paths.append(entry["selected_paths"])
        directory = run_dir / TEST_TASKS_DIR / str(entry["task"])
        directory.mkdir(parents=True, exist_ok=True)
        rundir.write_atomic(directory / rundir.EXPRESSION_FILE, entry["formula"] + "\n")
        source = ex.to_python(exprs, env.obs_dim, env.action_low, env.action_high)
        rundir.write_atomic(directory / rundir.POLICY_FILE, source)
        files.append(directory / rundir.POLICY_FILE)
        faults.kill_point("test-task-export")  # after the first task's files
    result["length"] = float(np.mean(lengths))
    result["selected_paths_per_action"] = float(np.mean(paths))
    return files


def _fresh_episodes(
    trainer: Trainer,
    state: TrainState,
    best: int,
    result: dict,
    policy_files: list[Path],
    warnings: list[str],
) -> None:
    """Each adapted formula, fixed, on ``FRESH_EPISODES`` new episodes of its task (the training
    env); where the family has a reference env (cartpole_fl_ood: the numpy CartPole;
    lunarlander_params: gymnasium's), also its policy.py there with the task's params."""
    env, actor = trainer.env, trainer.actor
    params = one_seed(state.actor, best)
    zs = jnp.asarray([entry["z"] for entry in result["test"]["per_task"]])

    def one(z, task, key):
        policy = actor.at(params, z)
        mask = actor.eval_mask(policy)
        return rollout.evaluate(env, actor, policy, mask, task, key, FRESH_EPISODES)

    keys = jax.random.split(offset_key(trainer.config.seed, FRESH_EPISODES_OFFSET), zs.shape[0])
    fresh = np.asarray(jax.jit(jax.vmap(one))(zs, trainer.tasks[1], keys))
    for entry, returns in zip(result["test"]["per_task"], fresh, strict=True):
        entry["fresh_return"] = float(returns.mean())
    result["test"]["fresh_mean"] = float(fresh.mean())
    if reference_eval.has_reference(trainer.config.env):
        _fresh_policy_py(trainer, result, policy_files, warnings)


def _fresh_policy_py(
    trainer: Trainer, result: dict, policy_files: list[Path], warnings: list[str]
) -> None:
    """Each test task's policy.py on fresh episodes of the reference env with the task's params
    (numpy CartPole for cartpole_fl_ood; gymnasium's LunarLander for lunarlander_params)."""

    def reference() -> None:
        returns_all = []
        for entry, path in zip(result["test"]["per_task"], policy_files, strict=True):
            kwargs = entry["params"]  # the task's params in the env's units (describe)
            policy = reference_eval.load_policy(path)
            returns = reference_eval.rollout_returns(
                policy.act, trainer.config.env, FRESH_EPISODES, REFERENCE_FIRST_EPISODE, **kwargs
            )
            entry["policy_py_return"] = float(returns.mean())
            returns_all.append(returns.mean())
        result["test"]["policy_py_mean"] = float(np.mean(returns_all))

    rundir.warn_on_failure(warnings, "policy.py in the reference env", reference)


def coefficient_figure(trainer: Trainer, state: TrainState, best: int, run_dir: Path) -> None:
    """The paper's Fig. 5: for a grid of force magnitudes × pole lengths (train and test ranges),
    adapt by the protocol (one run), then read the formula's ∂a/∂θ and ∂a/∂θ̇ at the upright
    state (the coefficients c1, c2 of ``a = c1·θ + c2·θ̇ + b``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    forces = np.linspace(5.0, 15.0, 9)
    lengths = np.linspace(0.2, 0.8, 7)
    grid_f, grid_l = (g.ravel() for g in np.meshgrid(forces, lengths, indexing="ij"))
    default = trainer.env.default_params
    tasks = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), grid_f.shape), default)
    tasks = tasks.replace(force_mag=jnp.asarray(grid_f), length=jnp.asarray(grid_l))
    single = one_seed(state, best)
    adapted = jax.jit(lambda s, p, k: trainer.adapt(s, p, k))(
        single, tasks, offset_key(trainer.config.seed, COEFFICIENTS_OFFSET)
    )
    actor = trainer.actor

    def coefficients(z):
        policy = actor.at(single.actor, z)
        mask = actor.eval_mask(policy)
        grad = jax.grad(lambda o: actor.mean_and_log_std(policy, mask, o)[0][0])
        return grad(jnp.zeros(trainer.env.obs_dim))

    c = np.asarray(jax.jit(jax.vmap(coefficients))(adapted.z[:, 0]))  # [grid, obs]
    c1, c2 = c[:, 2].reshape(len(forces), len(lengths)), c[:, 3].reshape(len(forces), -1)
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for row, (coef, name) in enumerate([(c1, "c1 (θ)"), (c2, "c2 (θ̇)")]):
        for j, length in enumerate(lengths):
            axes[row, 0].plot(forces, coef[:, j], "o-", label=f"length {length:.2f}")
        for i, force in enumerate(forces):
            axes[row, 1].plot(lengths, coef[i], "o-", label=f"force {force:.1f}")
        axes[row, 0].set_ylabel(name)
    axes[1, 0].set_xlabel("force magnitude")
    axes[1, 1].set_xlabel("pole half-length")
    axes[0, 0].legend(fontsize=6)
    axes[0, 1].legend(fontsize=6)
    for ax in axes[:, 0]:
        ax.axvspan(7.5, 12.5, color="grey", alpha=0.1)  # the training range
    for ax in axes[:, 1]:
        ax.axvspan(0.3, 0.7, color="grey", alpha=0.1)
    fig.suptitle(
        "CSP on cartpole_fl_ood: coefficients of the adapted formulas at the upright state"
    )
    fig.tight_layout()
    fig.savefig(run_dir / COEFFICIENTS_FILE, dpi=100)
    plt.close(fig)
    record = {"force_mag": grid_f.tolist(), "length": grid_l.tolist(),
              "c1": c1.ravel().tolist(), "c2": c2.ravel().tolist()}  # fmt: skip
    (run_dir / "coefficients.json").write_text(json.dumps(record) + "\n")
