"""The Python API: a trained run as an object, ``run = espl_jax.load("runs/...")``.

PySR users read a fitted model with ``model.sympy()``, ``model.latex()``, ``model.jax()`` and
the table ``model.equations_``; sbx/SB3 users call ``model.predict(obs)`` on a model loaded in
one call. :class:`Run` gives the same over a run directory, and :func:`train` trains one (the
command line's config resolution: defaults < configs/ENV.yaml < ``config`` file < keywords).

Thin by design: every value is read from the run directory's files or computed by the functions
the command-line tools use (the hall of fame's exact rows, ``halloffame.pick``; ``run.restore``,
``run.exported_actors`` and ``ex.export_expressions`` as at the end of training;
``meta_report.task_expressions``), so the formula of :meth:`Run.policy` is the one the run's
``policy.py`` evaluates, and :meth:`Run.pick` chooses as ``python -m espl_jax.export --pick``.
Nothing here writes to the run directory. NOT jittable, except what :meth:`Formula.to_jax` returns.
"""

from __future__ import annotations

import json
import os
import types
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp

from espl_jax import config as config_lib
from espl_jax import envs, rundir
from espl_jax import expression as ex
from espl_jax import halloffame as hof
from espl_jax import run as run_lib
from espl_jax.cli import check_path, use_compilation_cache
from espl_jax.config import Config, UserError
from espl_jax.envs.base import action_center_half_range, to_env_units
from espl_jax.learner import Trainer
from espl_jax.seeds import gather, one_seed

# The hall-of-fame table's columns, in formulas.jsonl's names (``halloffame``'s module docstring):
# ``stability`` and ``spectral_radius`` are analyze's verdict at the env's equilibrium (None for
# envs without one).
HALL_OF_FAME_COLUMNS = (
    "iteration",
    "env_steps",
    "seed",
    "length",
    "selection_return",
    "eligible",
    "stability",
    "spectral_radius",
    "formula",
)
# How the table prints a column's floats (default: two decimals): radii next to 1 need six.
FLOAT_FORMATS = {"spectral_radius": "{:.6f}"}


@dataclass(frozen=True, eq=False)
class Formula:
    """One exported symbolic policy: a formula per action dimension and the env's action bounds.

    ``expressions`` are exact: the protected operators of training (``PMul``, ``PDiv``, …, §3.1
    and App. A of the paper) with the trained float constants, pre-tanh. The deployed policy is
    ``center + tanh(f(obs)) · half_range`` (``envs.base.to_env_units``), as in ``policy.py``.

    Attributes:
        expressions: ``action_dim`` protected sympy expressions in x0 … x{obs_dim−1}.
        obs_dim: observation size.
        action_low, action_high: the env's action bounds, one per action dimension.
        info: where the formula comes from (seed, hall-of-fame row, test task, …).
    """

    expressions: tuple[sp.Expr, ...]
    obs_dim: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    info: dict[str, Any] = field(default_factory=dict)

    def sympy(self) -> list[sp.Expr]:
        """The readable formulas (plain operators, simplified, constants unrounded), one per
        action: equal to the policy wherever no protection is active (``expression.readable``)."""
        return [ex.readable(e) for e in self.expressions]

    def latex(self) -> str:
        """One LaTeX equation line per action dimension, constants rounded for reading."""
        return ex.to_latex(self.expressions)

    @property
    def length(self) -> float:
        """The paper's length metric, averaged over action dimensions."""
        return ex.mean_complexity(self.sympy())

    def python(self) -> str:
        """Source of a standalone policy.py (``act``, ``act_batch``) for this formula."""
        return ex.to_python(self.expressions, self.obs_dim, self.action_low, self.action_high)

    @cached_property
    def _module(self) -> types.ModuleType:
        # The policy.py source itself, run once: act and act_batch are policy.py's functions.
        module = types.ModuleType("espl_policy")
        exec(compile(self.python(), "<espl-jax policy.py>", "exec"), module.__dict__)
        return module

    def act(self, obs: Sequence[float] | np.ndarray) -> np.ndarray:
        """The action for one observation (obs_dim,), in the env's own units (float64)."""
        return self._module.act(obs)

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        """Actions for a batch of observations [N, obs_dim] -> [N, action_dim], numpy."""
        return self._module.act_batch(obs)

    def to_jax(self) -> Callable[[jax.Array], jax.Array]:
        """A jittable, differentiable ``act(obs) -> action`` in the env's units, obs (...,
        obs_dim) -> (..., action_dim); the operators are :mod:`espl_jax.operators`' own."""
        pre_tanh = ex.to_jax(self.expressions)
        center, half_range = action_center_half_range(self.action_low, self.action_high)

        def act(obs: jax.Array) -> jax.Array:
            u = jnp.tanh(pre_tanh(obs))
            return to_env_units(u, center.astype(u.dtype), half_range.astype(u.dtype), jnp.clip)

        return act

    def __str__(self) -> str:
        return ex.to_text(self.expressions)

    def __repr__(self) -> str:
        where = ", ".join(f"{k}={v!r}" for k, v in self.info.items() if not isinstance(v, dict))
        return f"<Formula {where}>\n{self}" if where else f"<Formula>\n{self}"


class Table:
    """Rows of named columns with a readable repr: the hall of fame when pandas is missing.

    ``len(t)`` rows; ``t[i]`` is row i (a dict), ``t["length"]`` a column (a list); iterating
    gives the rows. ``to_pandas()`` makes the DataFrame PySR users know as ``equations_``.
    """

    def __init__(
        self,
        rows: list[dict[str, Any]],
        columns: Sequence[str],
        float_formats: dict[str, str] | None = None,
    ):
        self.columns = tuple(columns)
        self.rows = [{c: r.get(c) for c in self.columns} for r in rows]
        self.float_formats = dict(float_formats or {})

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        return iter(self.rows)

    def __getitem__(self, key: int | str) -> Any:
        if isinstance(key, str):
            if key not in self.columns:
                raise KeyError(key)
            return [r[key] for r in self.rows]
        return self.rows[key]

    def to_pandas(self):
        import pandas as pd

        return pd.DataFrame(self.rows, columns=list(self.columns))

    def __repr__(self) -> str:
        def cell(v: Any, column: str) -> str:
            if isinstance(v, float):
                text = self.float_formats.get(column, "{:.2f}").format(v)
            else:
                text = str(v)
            text = text.replace("\n", "; ")
            return text if len(text) <= 60 else text[:57] + "..."

        cells = [[cell(r[c], c) for c in self.columns] for r in self.rows]
        widths = [
            max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(self.columns)
        ]
        lines = ["  ".join(c.ljust(w) for c, w in zip(self.columns, widths, strict=True))]
        lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
        return "\n".join(line.rstrip() for line in lines)


class Run:
    """A run directory written by ``espl_jax.train`` (or ``python -m espl_jax.train``).

    Cheap to create: the config is read at once; formulas when first asked for (then kept),
    from the hall of fame, or from the newest checkpoint where it has none. Single-task symbolic
    runs: :meth:`formula`, :meth:`latex`, :meth:`act`, :meth:`act_batch`, :meth:`to_jax` (the
    best seed's exported policy, as ``policy.py``), :attr:`hall_of_fame`, :meth:`pick`. Meta-RL
    runs: :attr:`tasks` and :meth:`adapted` (CSP's formula adapted to a test task). Every run:
    :attr:`config`, :attr:`eval`.

    Raises:
        UserError: ``path`` is not a run directory (no config.yaml), or its config is unreadable.
    """

    def __init__(self, path: str | Path):
        check_path(str(path), "the run directory")
        self.path = Path(path).absolute()  # the run stays found after a change of directory
        self.config: Config = run_lib.saved_config(self.path)
        self._policies: dict[int, Formula] = {}

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r}, env={self.config.env!r}, actor={self.config.actor!r})"

    # Files of the run directory ----------------------------------------------------------------

    @property
    def eval(self) -> dict[str, Any]:
        """eval.json: the run's returns, best seed, budget, devices (read on each access).

        Raises:
            UserError: the run has no eval.json (training has not finished) or it is corrupt.
        """
        record = rundir.read_eval(self.path)
        if record is None:
            raise UserError(
                f"{self.path} has no {rundir.EVAL_FILE}: its training has not finished "
                f"(python -m espl_jax.train --resume {self.path})"
            )
        return record

    @property
    def tasks(self) -> dict[str, Any]:
        """Meta-RL runs: tasks.json, each training and test task's params in the env's units."""
        from espl_jax import meta_report

        self._require_meta()
        path = self.path / meta_report.TASKS_FILE
        if not path.is_file():
            raise UserError(
                f"{self.path} has no {meta_report.TASKS_FILE}: its training has not finished"
            )
        return json.loads(path.read_text())

    @property
    def hall_of_fame(self):
        """Every chunk's exported formula and seed with its length, selection return and local
        stability, in the order they were found (formulas.jsonl): a pandas DataFrame when
        pandas is installed, else a :class:`Table`. ``formula`` is None where the network was
        not pruned yet; ``stability`` ("stable", "marginal", "unstable") and ``spectral_radius``
        (the largest |λ| of the closed loop at the env's equilibrium, ``python -m
        espl_jax.analyze``'s verdict) are None for envs without an equilibrium and for
        formulas not kept."""
        table = Table(hof.read(self._hall_of_fame_file()), HALL_OF_FAME_COLUMNS, FLOAT_FORMATS)
        try:
            return table.to_pandas()
        except ImportError:
            return table

    # Single-task formulas ----------------------------------------------------------------------

    def policy(self, seed: int | None = None) -> Formula:
        """The exported policy of one seed (default: eval.json's best seed): the formula the run
        exports for it (the hall of fame's anchor with ``keep_best_formula``, else the final
        one), the one its policy.py evaluates for the best seed.

        The exact expressions are read from the hall of fame (formulas.jsonl keeps them, in
        sympy's ``srepr``), which needs no JAX; from the newest checkpoint, as at the end of
        training, where the row is missing (a formula too long to keep, a run without
        eval.json).

        Raises:
            UserError: an MLP or meta-RL run, a seed out of range, an unreadable checkpoint.
        """
        self._require_formula()
        if self._is_meta:
            raise UserError(
                f"{self.path} is a meta-RL run: its formula depends on the task; use "
                "run.adapted(i) for the formula adapted to test task i"
            )
        seed = self._best_seed() if seed is None else seed
        self._check_seed(seed)
        if seed not in self._policies:
            found = self._exported_row(seed)
            if found is None:
                self._policies[seed] = self._from_checkpoint(seed)
            else:
                exprs, info = found
                self._policies[seed] = self._formula(exprs, **info)
        return self._policies[seed]

    def formula(self, seed: int | None = None) -> list[sp.Expr]:
        """The readable sympy formula of a seed's exported policy, one per action dimension."""
        return self.policy(seed).sympy()

    def latex(self, seed: int | None = None) -> str:
        """The formula as LaTeX, one equation line per action dimension."""
        return self.policy(seed).latex()

    def act(self, obs: Sequence[float] | np.ndarray) -> np.ndarray:
        """The best seed's action for one observation, in the env's units: policy.py's ``act``."""
        return self.policy().act(obs)

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        """The best seed's actions for observations [N, obs_dim]: policy.py's ``act_batch``."""
        return self.policy().act_batch(obs)

    def to_jax(self) -> Callable[[jax.Array], jax.Array]:
        """The best seed's policy as a jittable JAX function obs -> action (env units)."""
        return self.policy().to_jax()

    def pick(self, how: str = "best", within: float | None = None, seed: int | None = None):
        """A formula from the hall of fame, as ``python -m espl_jax.export --pick``.

        Args:
            how: ``"best"`` (the highest selection return), ``"shortest-within"`` (the
                shortest formula within ``within`` percent of the best selection return:
                PySR's model selection, for symbolic policies) or ``"stable-within"`` (the
                shortest *locally stable* formula within ``within`` percent of the best: every
                |λ| < 1 at the env's equilibrium, as ``python -m espl_jax.analyze`` decides;
                envs with an equilibrium only).
            within: the percentage, for ``"shortest-within"`` and ``"stable-within"``.
            seed: only this seed's formulas (default: all seeds').

        Returns:
            A :class:`Formula`; its ``info`` is the hall-of-fame row it comes from.

        Raises:
            UserError: a bad ``how``/``within`` or seed; ``"stable-within"`` on an env without
                an equilibrium, or with no locally stable formula within ``within`` percent.
        """
        takes_percentage = how in ("shortest-within", "stable-within")
        if how not in hof.PICKS or takes_percentage != (within is not None):
            raise UserError(
                f"pick takes 'best' alone, or 'shortest-within' or 'stable-within' with a "
                f"percentage, e.g. run.pick('stable-within', 5); got {how!r}, {within!r}"
            )
        if how == "stable-within":
            hof.require_stability(self.config.env)  # before reading the hall of fame
        rows = hof.read(self._hall_of_fame_file())
        if seed is not None:
            self._check_seed(seed)
            rows = [r for r in rows if r["seed"] == seed]
        chosen = hof.pick(rows, how, within, env=self.config.env)
        info = {k: chosen.get(k) for k in HALL_OF_FAME_COLUMNS if k != "formula"}
        return self._formula(hof.expressions(chosen), **info)

    # Meta-RL ------------------------------------------------------------------------------------

    def adapted(self, task: int) -> Formula:
        """CSP: the formula the run adapted to test task ``task`` by PEARL's protocol (its
        test_tasks/<task>/policy.py), rebuilt exactly from the checkpoint and eval.json's z.

        Raises:
            UserError: not a CSP run, no eval.json, a task index out of range.
        """
        from espl_jax import meta_report

        self._require_meta()
        self._require_formula()
        record = self.eval
        tasks = record.get("test", {}).get("per_task", [])
        if not (isinstance(task, int) and 0 <= task < len(tasks)):
            raise UserError(f"task must be a test task of eval.json: 0 … {len(tasks) - 1}")
        best = record["best_seed"]
        actor = one_seed(self._state.actor, best)
        entry = tasks[task]
        exprs = meta_report.task_expressions(self._trainer, actor, entry["z"])
        return self._formula(exprs, task=task, seed=best, params=entry["params"])

    # Internals ----------------------------------------------------------------------------------

    @cached_property
    def _trainer(self) -> Trainer:
        return Trainer(self.config)

    @cached_property
    def _state(self):
        """The newest checkpoint's state on the host, without its replay buffers."""
        _, state = run_lib.restore(self.path, self._trainer)
        return gather(state.replace(buffer=None, encoder_buffer=None))

    @property
    def _is_meta(self) -> bool:
        return envs.is_family(self.config.env)

    def _exported_row(self, seed: int) -> tuple[list[sp.Expr], dict[str, Any]] | None:
        """The hall-of-fame row of the formula eval.json says the run exported for ``seed``:
        its expressions and where it comes from; None without eval.json or a kept row."""
        record = rundir.read_eval(self.path)
        path = self.path / hof.FORMULAS_FILE
        if record is None or not path.is_file():
            return None
        entry = record["per_seed"][seed]
        if entry.get("exported") not in ("best", "final"):
            return None  # eval.json from before the hall of fame
        iteration = entry.get("exported_iteration", record["training"]["iterations"])
        rows = [
            r
            for r in hof.read(path)
            if r["seed"] == seed and r["iteration"] == iteration and r["protected"] is not None
        ]
        if not rows:
            return None
        info = {"seed": seed, "exported": entry["exported"], "iteration": iteration}
        return hof.expressions(rows[-1]), info

    def _from_checkpoint(self, seed: int) -> Formula:
        """``seed``'s exported formula rebuilt from the newest checkpoint (``run.finish``'s way)."""
        actors, sources = run_lib.exported_actors(self._trainer, self._state)
        actor = one_seed(actors, seed)
        exprs = ex.export_expressions(self._trainer, actor)
        return self._formula(exprs, seed=seed, exported=sources[seed])

    def _formula(self, exprs: Sequence[sp.Expr], **info: Any) -> Formula:
        env = self._trainer.env
        low, high = (tuple(float(v) for v in b) for b in (env.action_low, env.action_high))
        return Formula(tuple(exprs), env.obs_dim, low, high, info)

    def _best_seed(self) -> int:
        """eval.json's best seed; 0 for a run without eval.json, as the command line does."""
        record = rundir.read_eval(self.path)
        return record.get("best_seed", 0) if record else 0

    def _check_seed(self, seed: int) -> None:
        if not (isinstance(seed, int) and 0 <= seed < self.config.seeds):
            raise UserError(f"seed must be in [0, {self.config.seeds - 1}], got {seed!r}")

    def _require_formula(self) -> None:
        if self.config.actor != "symbolic":
            raise UserError(
                f"{self.path} trained a {self.config.actor.upper()} actor: it has no formula"
            )

    def _require_meta(self) -> None:
        if not self._is_meta:
            raise UserError(f"{self.path} is a single-task run ({self.config.env}): no tasks")

    def _hall_of_fame_file(self) -> Path:
        path = self.path / hof.FORMULAS_FILE
        if not path.is_file():
            raise UserError(
                f"{self.path} has no hall of fame ({hof.FORMULAS_FILE}): single-task symbolic "
                "runs keep one"
            )
        return path


def load(path: str | Path) -> Run:
    """The run in directory ``path`` (written by ``espl_jax.train`` or the command line).

    Raises:
        UserError: ``path`` is not a run directory.
    """
    return Run(path)


def train(
    env: str | None = None,
    *,
    config: str | Path | None = None,
    out: str | Path | None = None,
    progress: bool = False,
    **overrides: Any,
) -> Run:
    """Train a run as ``python -m espl_jax.train`` does, and return it.

    Args:
        env: environment or task family (default: the ``config`` file's, else cartpole).
        config: a YAML file over configs/ENV.yaml (the command line's ``--config``).
        out: the run directory (default: a new ``runs/ENV-ACTOR-TIME``).
        progress: draw a progress bar.
        **overrides: any config key (``iterations=20``, ``seeds=4``, ``actor="mlp"``, …);
            highest precedence, as command-line flags.

    Returns:
        The trained :class:`Run`.

    Raises:
        UserError: an unknown env or key, a bad value, ``out`` already holding a run.
    """
    for value, name in ((config, "config"), (out, "out")):
        check_path(None if value is None else str(value), name)
    resolved = config_lib.resolve(env, config, **overrides)
    run_dir = Path(out) if out is not None else run_lib.new_run_dir(resolved)
    # The command line keeps compiled programs on disk (cli.use_compilation_cache); a cache the
    # calling program configured in jax.config itself is left as it is.
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") is not None or (
        jax.config.jax_compilation_cache_dir is None
    ):
        use_compilation_cache()
    run_lib.train(resolved, run_dir, show_progress=progress)
    return Run(run_dir)
