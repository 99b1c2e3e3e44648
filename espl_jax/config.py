"""One frozen, typed training config, loaded from YAML and validated once (never mutated).

Defaults hold the paper's common ESPL hyperparameters (Table 5); ``configs/<env>.yaml`` adds the
per-environment ones (Table 6) and a budget that fits a laptop CPU.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import yaml

# The shipped per-env configs. In the source tree ``espl_jax/configs`` is a link to the top-level
# ``configs/``; in a wheel it is a real directory (package data), so ``--env NAME`` loads the same
# files from any install.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"
DEFAULT_ENV = "cartpole"


class UserError(Exception):
    """A problem with the user's input (config, env name, run directory): printed, no traceback."""


@dataclass(frozen=True)
class Config:
    """Everything a run needs. Sizes fix array shapes; the rest are plain hyperparameters."""

    env: str = "cartpole"
    # Single-task envs: "symbolic" (ESPL) or "mlp" (plain SAC, the neural baseline). Meta-RL task
    # families: "symbolic" (CSP), "pearl" (MLP policy on s ⊕ z) or "hyper" (hypernetwork policy).
    actor: str = "symbolic"
    # Symbolic network layout: arranged | dense | plain (ESPL); csp | csp_cond (CSP, App. C.2).
    layout: str = "arranged"
    selector: str = "probabilistic"  # path selector: probabilistic | l1 (ablation)
    seed: int = 0
    seeds: int = 1  # independent runs, vmapped in one computation; the best formula is kept
    # Devices the seed axis is sharded over (jax.sharding, one mesh axis "seeds"): 0 = as many
    # of jax.devices() as divide ``seeds``; N > 0 = N devices, which must divide ``seeds``.
    devices: int = 0
    # How MuJoCo tasks are simulated: "native" steps MuJoCo's C engine on the host (envs/native.py,
    # the fast path on a CPU), "mjx" steps MJX inside the compiled program (the fast path on an
    # accelerator), "auto" picks native when JAX's default backend is the CPU, else mjx.
    # Non-MuJoCo envs ignore it.
    physics: str = "auto"

    # Budget (Algorithm 1): iterations of (collect, update).
    iterations: int = 100
    steps_per_iteration: int = 1000  # K environment steps, one Bernoulli mask each iteration
    updates_per_iteration: int = 250  # gradient steps per iteration
    chunk_iterations: int = 10  # iterations per compiled chunk: log, plot, checkpoint between
    buffer_size: int = 1_000_000

    # SAC (Table 5).
    batch_size: int = 256
    learning_rate: float = 3e-4  # critics and α
    # Actor (w, b, p, θ_F). Adam moves each constant by about this much per update, so a budget
    # with ~10x fewer updates than the paper's needs a larger step for constants to reach
    # magnitudes like 17.17 (Table 2); the paper's value is 3e-4.
    actor_learning_rate: float = 3e-4
    # The selector's probabilities keep the paper's step: with the larger actor step they would
    # cross [0, 1] within one iteration and the sampled masks would thrash.
    probs_learning_rate: float = 3e-4
    gamma: float = 0.99
    # ρ of the AR(1) exploration noise in collection (trainer.collect); 0 is SAC's white noise.
    exploration_correlation: float = 0.0
    # ε in log π's squashing term log(1 − tanh(u)² + ε) (policies.tanh_gaussian_log_prob): 0 is
    # exact and unbounded; rlkit (PEARL, the authors' CSP code) uses 1e-6, which bounds it.
    squash_epsilon: float = 0.0
    polyak: float = 0.005
    reward_scale: float = 1.0
    grad_clip: float = 0.5  # global-norm clip of the policy gradient (authors' code)
    critic_hidden: tuple[int, ...] = (256, 256)
    # The critics (sac.py). "sac": the paper's twin Q with Polyak-averaged target networks.
    # "crossq": CrossQ (Bhatt et al., ICLR 2024): batch renormalisation in the critics, no
    # target network, (s, a) and (s', a') in one joint forward pass, the critics' Adam with
    # β1 0.5. The actor losses, the symbolic actor, the selector and PEARL's encoder are the
    # same for both.
    critic: str = "sac"
    critic_layer_norm: bool = False  # LayerNorm before each hidden ReLU of the critics
    crossq_momentum: float = 0.99  # batch renorm's running statistics (sbx)
    crossq_warmup: int = 100_000  # critic updates with plain batch norm before renorm (sbx)
    std_hidden: tuple[int, ...] = (64, 64, 64)  # F(s), the std network (authors' code)
    mlp_actor_hidden: tuple[int, ...] = (256, 256)  # only for actor == "mlp"

    # ESPL losses and schedules (Table 5 and 6, Algorithm 1).
    penalty_scale: float = 1.0  # α1
    # L1 on the symbolic network's biases, weight × mean |b| (the authors' code: ``bl0_scale``,
    # 0 in their released script). Biases are never masked, so a constant the pruned paths no
    # longer need stays in the formula unless something pulls it back to 0. configs/cartpole.yaml
    # uses 1.0: an offset of 0.05 there drives the cart off the track (README, "Across seeds").
    # CSP applies it to the generated biases Φ_b(z) (configs/cartpole_fl_ood.yaml: 10.0).
    bias_l1_scale: float = 0.0
    select_scale: float = 0.08  # α2
    target_l0_ratio: float = 0.002  # l_t, as a fraction of all weights
    schedule_iterations: int = 80  # t_s
    target_temperature: float = 0.2  # τ_t

    # After the schedule (ESPL; not in the paper; off by default, measured in the README, "Across
    # seeds"):
    # finetune: from iteration t_s on, p is set to the exported mask (p > 0.5, |w| > 1e-3, as
    # 0/1) and frozen, so collection, the critic's target and the actor loss all use exactly the
    # formula that is exported, and the constants (and F, the critics) are fine-tuned on it
    # with the step finetune_learning_rate (EQL-style symbolic regression does the same).
    finetune: bool = False
    finetune_learning_rate: float = 3e-4
    # keep_best_formula: export the formula that scored best on the selection episodes after
    # each chunk from t_s on (the hall of fame's best), not the last one; the reported return is
    # measured afresh on other episodes.
    keep_best_formula: bool = False

    # SAC's entropy temperature: tuned towards −|A| from ``alpha`` (ESPL), or fixed at ``alpha``
    # (the authors' CSP code and PEARL fix it; with reward scale 5, as there).
    auto_alpha: bool = True
    alpha: float = 1.0

    # Meta-RL: CSP, PEARL and Hyper (paper §4, Algorithm 2, App. C.2, D); single-task runs
    # ignore these. Sizes are the paper's and the authors' code's.
    task_seed: int = 0  # the train/test task sets are drawn from this seed (saved in tasks.json)
    latent_dim: int = 5
    encoder_hidden: tuple[int, ...] = (200, 200, 200)
    generator_hidden: tuple[int, ...] = (64, 64)  # Φ and Ψ, one MLP per action dimension
    pearl_hidden: tuple[int, ...] = (300, 300, 300)
    hyper_policy_hidden: int = 256
    kl_weight: float = 0.1  # β: PEARL's and the authors' code (the paper's table says 1)
    # Floor of each context transition's factor variance σ²_n before the product of Gaussians.
    # PEARL's 1e-7 is a numerical guard; a factor at the floor outweighs every other, and the
    # posterior is then that one transition's μ_n (lunarlander_params, docs/notes).
    posterior_var_floor: float = 1e-7
    meta_batch: int = 10  # tasks per gradient step, sampled with replacement
    context_batch: int = 100  # context transitions per task, from its encoder buffer
    # Collection (PEARL's rl_algorithm): before the first iteration every training task gets
    # initial_steps with z from the prior; each iteration visits tasks_per_iteration tasks:
    # their encoder buffers are cleared, prior_steps with prior z go to both buffers, then
    # posterior_steps with z from the posterior of that fresh context go to the RL buffer only.
    initial_steps: int = 2000
    tasks_per_iteration: int = 5
    prior_steps: int = 400
    posterior_steps: int = 600
    task_buffer_size: int = 100_000  # RL buffer capacity per task
    # Evaluation protocol (PEARL): per test task eval_runs runs from the prior, whole
    # trajectories until eval_steps; the posterior of the run's own transitions after
    # eval_exploration_trajectories trajectories; the last trajectory's return is reported.
    eval_runs: int = 2
    eval_steps: int = 600
    eval_exploration_trajectories: int = 2
    # CSP's relaxed mask for the actor loss: "straight_through" (paper, as ESPL) or "soft"
    # (the authors' code). Their two extra terms: a penalty on Ψ's logits outside ±6 and L1 on
    # Φ's weights (``constrain_scale`` 0.001, ``l0_scale`` 0.01 in their script).
    csp_relaxed_mask: str = "straight_through"
    logit_clamp_scale: float = 0.001
    weight_l1_scale: float = 0.01

    # Evaluation.
    progress_eval_episodes: int = 10  # deterministic episodes after each chunk (learning curve)
    eval_episodes: int = 1000  # final evaluation of the exported formula in JAX
    reference_eval_episodes: int = 100  # exported policy.py in the reference (gymnasium) env

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def total_env_steps(self) -> int:
        return self.iterations * self.steps_per_iteration

    def to_dict(self) -> dict[str, Any]:
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


_CHOICES = {
    "actor": ("symbolic", "mlp", "pearl", "hyper"),
    "layout": ("arranged", "dense", "plain", "csp", "csp_cond"),
    "selector": ("probabilistic", "l1"),
    "csp_relaxed_mask": ("straight_through", "soft"),
    "physics": ("auto", "mjx", "native"),
    "critic": ("sac", "crossq"),
}
_POSITIVE_INT = (
    "seeds",
    "iterations",
    "steps_per_iteration",
    "updates_per_iteration",
    "chunk_iterations",
    "buffer_size",
    "batch_size",
    "schedule_iterations",
    "progress_eval_episodes",
    "eval_episodes",
    "latent_dim",
    "hyper_policy_hidden",
    "meta_batch",
    "context_batch",
    "tasks_per_iteration",
    "prior_steps",
    "task_buffer_size",
    "eval_runs",
    "eval_steps",
)
_UNIT_INTERVAL = ("gamma", "polyak", "target_l0_ratio", "target_temperature", "crossq_momentum")
_POSITIVE_FLOAT = (
    "posterior_var_floor",
    "learning_rate",
    "actor_learning_rate",
    "probs_learning_rate",
    "grad_clip",
    "reward_scale",
    "alpha",
    "finetune_learning_rate",
)
_NON_NEGATIVE_FLOAT = (
    "penalty_scale",
    "select_scale",
    "bias_l1_scale",
    "kl_weight",
    "squash_epsilon",
    "logit_clamp_scale",
    "weight_l1_scale",
)
_NON_NEGATIVE_INT = (
    "initial_steps",
    "posterior_steps",
    "eval_exploration_trajectories",
    "devices",
    "crossq_warmup",
)


# JAX's integers are int32 by default: a count, size or seed beyond them cannot be honoured.
_INT_LIMIT = 2**31


def _validate(c: Config) -> None:
    for f in fields(c):
        value = getattr(c, f.name)
        expected = _field_type(f)
        if expected is tuple:
            ok = (
                isinstance(value, tuple)
                and value
                and all(
                    isinstance(v, int) and not isinstance(v, bool) and 0 < v < _INT_LIMIT
                    for v in value
                )
            )
            if not ok:
                raise UserError(
                    f"config: {f.name} must be a list of positive integers below 2**31, "
                    f"got {value!r}"
                )
        elif expected is float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UserError(f"config: {f.name} must be a number, got {value!r}")
            # Every check below is written so that NaN fails it, but say what is wrong.
            if not _finite(value):
                raise UserError(f"config: {f.name} must be a finite number, got {value!r}")
        elif expected is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise UserError(f"config: {f.name} must be an integer, got {value!r}")
        elif not isinstance(value, expected):
            raise UserError(f"config: {f.name} must be a {expected.__name__}, got {value!r}")
    for name, choices in _CHOICES.items():
        if getattr(c, name) not in choices:
            raise UserError(
                f"config: {name} must be one of {', '.join(choices)}, got {getattr(c, name)!r}"
            )
    for name in ("seed", "task_seed"):
        if not 0 <= getattr(c, name) < _INT_LIMIT:
            raise UserError(f"config: {name} must be in [0, 2**31), got {getattr(c, name)!r}")
    for f in fields(c):
        if _field_type(f) is int and not getattr(c, f.name) < _INT_LIMIT:
            raise UserError(f"config: {f.name} must be below 2**31, got {getattr(c, f.name)!r}")
    for name in _NON_NEGATIVE_INT:
        if not getattr(c, name) >= 0:
            raise UserError(f"config: {name} must be >= 0, got {getattr(c, name)!r}")
    for name in _POSITIVE_INT:
        if not getattr(c, name) > 0:
            raise UserError(f"config: {name} must be positive, got {getattr(c, name)!r}")
    if not 0.0 <= c.exploration_correlation < 1.0:
        raise UserError(
            f"config: exploration_correlation must be in [0, 1), got {c.exploration_correlation!r}"
        )
    if not c.reference_eval_episodes >= 0:
        raise UserError(
            f"config: reference_eval_episodes must be >= 0, got {c.reference_eval_episodes!r}"
        )
    for name in _UNIT_INTERVAL:
        if not 0.0 < getattr(c, name) <= 1.0:
            raise UserError(f"config: {name} must be in (0, 1], got {getattr(c, name)!r}")
    for name in _POSITIVE_FLOAT:
        if not getattr(c, name) > 0:
            raise UserError(f"config: {name} must be > 0, got {getattr(c, name)!r}")
    for name in _NON_NEGATIVE_FLOAT:
        if not getattr(c, name) >= 0:
            raise UserError(f"config: {name} must be >= 0, got {getattr(c, name)!r}")
    if c.devices and c.seeds % c.devices:  # else the mesh would quietly use fewer devices
        raise UserError(
            f"config: devices ({c.devices}) must divide seeds ({c.seeds}): each device runs "
            "whole seeds (devices 0 takes as many as divide seeds)"
        )
    if c.buffer_size < c.steps_per_iteration:
        raise UserError(
            f"config: buffer_size ({c.buffer_size}) must be at least steps_per_iteration "
            f"({c.steps_per_iteration})"
        )


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond the floats' range
        return False


def _field_type(f: dataclasses.Field) -> type:
    hint = _type_hints()[f.name]
    return tuple if typing.get_origin(hint) is tuple else hint


@functools.cache
def _type_hints() -> dict[str, Any]:
    """Config's resolved annotations, once: resolving them takes ~1 ms, and every Config built
    validates each of its ~60 fields."""
    return typing.get_type_hints(Config)


def _coerce(value: Any, expected: type) -> Any:
    """Convert what YAML legitimately gives (lists, ints for floats, and "3e-4", which YAML 1.1
    reads as a string); anything else is left for validation to reject with a clear message."""
    if expected is tuple and isinstance(value, list):
        return tuple(value)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            return float(value)
        except OverflowError:
            return value
    if expected is float and isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def from_mapping(values: Mapping[str, Any], base: Config | None = None) -> Config:
    """Build a Config from a mapping, overriding ``base`` (defaults if None)."""
    known = {f.name: f for f in fields(Config)}
    unknown = sorted(str(k) for k in set(values) - set(known))  # YAML keys may be 1, null, …
    if unknown:
        raise UserError(
            f"config: unknown key(s) {', '.join(unknown)}; known keys: {', '.join(sorted(known))}"
        )
    coerced = {k: _coerce(v, _field_type(known[k])) for k, v in values.items()}
    return dataclasses.replace(Config() if base is None else base, **coerced)


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a mapping that gives a key twice is an error: PyYAML keeps the
    last value and drops the others without a word."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # ``<<: *anchor``: keys given beside it override the merged ones
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, typing.Hashable):
                continue  # PyYAML refuses it below, with its own message
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping with readable errors for missing, unreadable or malformed files.

    An empty file (or one of comments only) is an empty mapping; a file that holds a null, a
    list or a scalar is refused, as is a key given twice.
    """
    path = Path(path)
    try:
        text = path.read_text()
        data = yaml.load(text, Loader=_StrictLoader)
        empty = data is None and yaml.compose(text, Loader=yaml.SafeLoader) is None
    except FileNotFoundError:
        raise UserError(f"config file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"cannot read config file {path}: {err}") from None
    except yaml.YAMLError as err:
        raise UserError(f"cannot read config file {path}: {_yaml_problem(err)}") from None
    if empty:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"config file {path} must hold a mapping of keys to values")
    return data


def _yaml_problem(err: yaml.YAMLError) -> str:
    """A YAML error on one line (PyYAML's own message spans several, with a caret drawing)."""
    problem, mark = getattr(err, "problem", None), getattr(err, "problem_mark", None)
    if problem and mark is not None:
        return f"{problem} (line {mark.line + 1}, column {mark.column + 1})"
    return " ".join(str(err).split())


def env_config_path(env: str) -> Path:
    return CONFIG_DIR / f"{env}.yaml"


def resolve(
    env: str | None = None, config_file: str | Path | None = None, **overrides: Any
) -> Config:
    """The run's config: defaults < ``configs/ENV.yaml`` < ``config_file`` < ``overrides``.

    The env comes from ``env`` (the ``--env`` flag), else from the file's ``env`` key, else
    ``DEFAULT_ENV`` (only when neither is given: an empty name is an unknown env, not a request
    for the default); a flag and a file that name different envs are an error. Every known env
    ships a config: a missing one is an error, never a silent fall-back to the defaults (which are
    the paper's common hyperparameters, not a laptop budget). ``overrides`` set to None are unset.

    Raises:
        UserError: unknown env, conflicting envs, missing or malformed files, bad values.
    """
    file_values = load_yaml(config_file) if config_file is not None else {}
    # A key the file gives is a value, null and "" included: only an absent key means "not set".
    file_env = file_values.get("env")
    if "env" in file_values and not isinstance(file_env, str):
        raise UserError(f"config: env must be a string, got {file_env!r} in {config_file}")
    name = next((n for n in (env, file_env) if n is not None), DEFAULT_ENV)
    _check_known_env(name)
    if env is not None and file_env is not None and env != file_env:
        raise UserError(
            f"--env {env} and the env of {config_file} ({file_env}) disagree; "
            "give one of them, or make them the same"
        )
    default_file = env_config_path(name)
    if not default_file.is_file():
        raise UserError(
            f"no shipped config for env {name!r}: {default_file} is missing "
            "(a broken install? every trainable env ships configs/ENV.yaml)"
        )
    values = load_yaml(default_file)
    values.update(file_values)
    values.update({k: v for k, v in overrides.items() if v is not None})
    values["env"] = name
    return from_mapping(values)


def _check_known_env(name: str) -> None:
    from espl_jax import envs

    if name not in envs.KNOWN_ENVS and not envs.is_family(name):
        raise UserError(
            f"unknown environment {name!r}; known: {', '.join(envs.KNOWN_ENVS)}; "
            f"meta-RL task families: {', '.join(envs.KNOWN_FAMILIES)}"
        )


def dump(config: Config) -> str:
    """The config as YAML text (what config.yaml holds)."""
    return yaml.safe_dump(config.to_dict(), sort_keys=False)


def save(config: Config, path: str | Path) -> None:
    Path(path).write_text(dump(config))


def load(path: str | Path) -> Config:
    return from_mapping(load_yaml(path))
