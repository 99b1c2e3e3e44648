"""One frozen, typed training config, loaded from YAML and validated once (never mutated).

Defaults hold the paper's common ESPL hyperparameters (Table 5); ``configs/<env>.yaml`` adds the
per-environment ones (Table 6) and a budget that fits a laptop CPU.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import textwrap
import typing
from collections.abc import Callable, Mapping
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


# JAX's integers are int32 by default: a count, size or seed beyond them cannot be honoured.
_INT_LIMIT = 2**31


@dataclass(frozen=True)
class Check:
    """One key's range. ``ok`` is asked only once the value has the key's type (and is finite);
    ``requirement`` ends the error "config: KEY must be <requirement>, got VALUE" and is the
    range the key table shows."""

    ok: Callable[[Any], bool]
    requirement: str
    choices: tuple[str, ...] = ()


positive = Check(lambda v: v > 0, "positive")  # counts and sizes
above_zero = Check(lambda v: v > 0, "> 0")  # steps, scales, floors
non_negative = Check(lambda v: v >= 0, ">= 0")
unit_interval = Check(lambda v: 0.0 < v <= 1.0, "in (0, 1]")
seed_range = Check(lambda v: 0 <= v < _INT_LIMIT, "in [0, 2**31)")


def choice(*options: str) -> Check:
    return Check(lambda v: v in options, f"one of {', '.join(options)}", options)


@dataclass(frozen=True)
class Group:
    """A section of the config: ``GROUP(default, doc, check)`` declares one key of it, with its
    doc and its range in the field's metadata, where validation and the key table read them."""

    name: str
    title: str

    def __call__(
        self, default: Any, doc: str, check: Check | None, *, unchecked: str | None = None
    ) -> Any:
        if not doc or (check is None) == (unchecked is None):
            raise TypeError(
                "a config key needs a doc and a check, or check=None and the reason in unchecked"
            )
        return dataclasses.field(
            default=default,
            metadata={"group": self.name, "doc": doc, "check": check, "unchecked": unchecked},
        )


RUN = Group("run", "What is trained, on how many seeds, where.")
BUDGET = Group("budget", "Budget (Algorithm 1): iterations of (collect, update).")
SAC = Group(
    "sac",
    "SAC (Table 5): steps, discount, exploration, the critics, the actors' networks; the entropy "
    "temperature.",
)
SYMBOLIC = Group(
    "symbolic",
    "The symbolic network and its path selector: ESPL's losses and schedules (Table 5 and 6, "
    "Algorithm 1), and what happens after the schedule (ESPL; not in the paper; off by default, "
    "measured in the README, 'Across seeds').",
)
META = Group(
    "meta",
    "Meta-RL: CSP, PEARL and Hyper (paper §4, Algorithm 2, App. C.2, D); single-task runs "
    "ignore these. Sizes are the paper's and the authors' code's.",
)
EVALUATION = Group("evaluation", "Evaluation of single-task runs.")
GROUPS = (RUN, BUDGET, SAC, SYMBOLIC, META, EVALUATION)

_BOOL = "true or false: its type is its range"
_SIZES = "positive integers below 2**31: its type is its range"


@dataclass(frozen=True)
class Config:
    """Everything a run needs. Sizes fix array shapes; the rest are plain hyperparameters.

    Each key is declared once, with its doc and its range (``python -m espl_jax.config`` lists
    them); ``_validate`` checks every key from its declaration.
    """

    env: str = RUN(
        "cartpole",
        "The environment or meta-RL task family.",
        None,
        unchecked="a known env or task family: resolve() checks it against espl_jax.envs",
    )
    actor: str = RUN(
        "symbolic",
        "Single-task envs: symbolic (ESPL) or mlp (plain SAC, the neural baseline). Meta-RL task "
        "families: symbolic (CSP), pearl (MLP policy on s ⊕ z) or hyper (hypernetwork policy).",
        choice("symbolic", "mlp", "pearl", "hyper"),
    )
    seed: int = RUN(
        0,
        "The first seed: the run trains seeds seed … seed + seeds − 1 (PRNGKey(seed + i)).",
        seed_range,
    )
    seeds: int = RUN(
        1, "Independent runs, vmapped in one computation; the best formula is kept.", positive
    )
    devices: int = RUN(
        0,
        "Devices the seed axis is sharded over (jax.sharding, one mesh axis 'seeds'): 0 = as "
        "many of jax.devices() as divide seeds; N > 0 = N devices, which must divide seeds.",
        non_negative,
    )
    physics: str = RUN(
        "auto",
        "How MuJoCo tasks are simulated: native steps MuJoCo's C engine on the host "
        "(envs/native.py, the fast path on a CPU), mjx steps MJX inside the compiled program (the "
        "fast path on an accelerator), auto picks native when JAX's default backend is the CPU, "
        "else mjx. Non-MuJoCo envs ignore it.",
        choice("auto", "mjx", "native"),
    )

    iterations: int = BUDGET(100, "Iterations of (collect, update).", positive)
    steps_per_iteration: int = BUDGET(
        1000, "K environment steps, one Bernoulli mask each iteration.", positive
    )
    updates_per_iteration: int = BUDGET(250, "Gradient steps per iteration.", positive)
    chunk_iterations: int = BUDGET(
        10, "Iterations per compiled chunk: log, plot, checkpoint between.", positive
    )
    buffer_size: int = BUDGET(
        1_000_000, "Replay buffer capacity; at least steps_per_iteration.", positive
    )

    batch_size: int = SAC(256, "Transitions per gradient step.", positive)
    learning_rate: float = SAC(3e-4, "Adam's step for the critics and α.", above_zero)
    actor_learning_rate: float = SAC(
        3e-4,
        "Adam's step for the actor (w, b, p, θ_F). Adam moves each constant by about this much "
        "per update, so a budget with ~10x fewer updates than the paper's needs a larger step "
        "for constants to reach magnitudes like 17.17 (Table 2); the paper's value is 3e-4.",
        above_zero,
    )
    probs_learning_rate: float = SAC(
        3e-4,
        "Adam's step for the selector's probabilities, which keep the paper's step: with the "
        "larger actor step they would cross [0, 1] within one iteration and the sampled masks "
        "would thrash.",
        above_zero,
    )
    gamma: float = SAC(0.99, "Discount γ.", unit_interval)
    exploration_correlation: float = SAC(
        0.0,
        "ρ of the AR(1) exploration noise in collection (rollout.explore); 0 is SAC's white noise.",
        Check(lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
    )
    squash_epsilon: float = SAC(
        0.0,
        "ε in log π's squashing term log(1 − tanh(u)² + ε) (policies.tanh_gaussian_log_prob): "
        "0 is exact and unbounded; rlkit (PEARL, the authors' CSP code) uses 1e-6, which bounds "
        "it.",
        non_negative,
    )
    polyak: float = SAC(0.005, "Polyak step of the target critics.", unit_interval)
    reward_scale: float = SAC(1.0, "Scales the reward in the critics' target (sac.py).", above_zero)
    grad_clip: float = SAC(
        0.5, "Global-norm clip of the policy gradient (authors' code).", above_zero
    )
    critic_hidden: tuple[int, ...] = SAC(
        (256, 256), "Hidden layers of each critic.", None, unchecked=_SIZES
    )
    critic: str = SAC(
        "sac",
        "The critics (sac.py). sac: the paper's twin Q with Polyak-averaged target networks. "
        "crossq: CrossQ (Bhatt et al., ICLR 2024): batch renormalisation in the critics, no "
        "target network, (s, a) and (s', a') in one joint forward pass, the critics' Adam with "
        "β1 0.5. The actor losses, the symbolic actor, the selector and PEARL's encoder are the "
        "same for both.",
        choice("sac", "crossq"),
    )
    critic_layer_norm: bool = SAC(
        False, "LayerNorm before each hidden ReLU of the critics.", None, unchecked=_BOOL
    )
    crossq_momentum: float = SAC(
        0.99, "Momentum of batch renorm's running statistics (CrossQ; sbx).", unit_interval
    )
    crossq_warmup: int = SAC(
        100_000, "Critic updates with plain batch norm before renorm (CrossQ; sbx).", non_negative
    )
    std_hidden: tuple[int, ...] = SAC(
        (64, 64, 64),
        "Hidden layers of F(s), the std network (authors' code).",
        None,
        unchecked=_SIZES,
    )
    mlp_actor_hidden: tuple[int, ...] = SAC(
        (256, 256), "Hidden layers of the MLP actor (only for actor mlp).", None, unchecked=_SIZES
    )
    auto_alpha: bool = SAC(
        True,
        "SAC's entropy temperature: tuned towards −|A| from alpha (ESPL), or fixed at alpha "
        "(the authors' CSP code and PEARL fix it; with reward scale 5, as there).",
        None,
        unchecked=_BOOL,
    )
    alpha: float = SAC(
        1.0, "The entropy temperature's start (auto_alpha) or fixed value.", above_zero
    )

    layout: str = SYMBOLIC(
        "arranged",
        "Symbolic network layout: arranged, dense or plain (ESPL); csp or csp_cond (CSP, "
        "App. C.2).",
        choice("arranged", "dense", "plain", "csp", "csp_cond"),
    )
    selector: str = SYMBOLIC(
        "probabilistic",
        "Path selector: probabilistic, or l1 (the ablations ESPL_l1 and CSP_L1: every path on, "
        "L1 on the weights in L_select's place).",
        choice("probabilistic", "l1"),
    )
    penalty_scale: float = SYMBOLIC(1.0, "α1.", non_negative)
    bias_l1_scale: float = SYMBOLIC(
        0.0,
        "L1 on the symbolic network's biases, weight × mean |b| (the authors' code: bl0_scale, "
        "0 in their released script). Biases are never masked, so a constant the pruned paths "
        "no longer need stays in the formula unless something pulls it back to 0. "
        "configs/cartpole.yaml uses 1.0: an offset of 0.05 there drives the cart off the track "
        "(README, 'Across seeds'). CSP applies it to the generated biases Φ_b(z) "
        "(configs/cartpole_fl_ood.yaml: 10.0).",
        non_negative,
    )
    select_scale: float = SYMBOLIC(0.08, "α2.", non_negative)
    target_l0_ratio: float = SYMBOLIC(0.002, "l_t, as a fraction of all weights.", unit_interval)
    schedule_iterations: int = SYMBOLIC(80, "t_s.", positive)
    target_temperature: float = SYMBOLIC(0.2, "τ_t.", unit_interval)
    finetune: bool = SYMBOLIC(
        False,
        "After the schedule: from iteration t_s on, p is set to the exported mask (p > 0.5, "
        "|w| > 1e-3, as 0/1) and frozen, so collection, the critic's target and the actor loss "
        "all use exactly the formula that is exported, and the constants (and F, the critics) "
        "are fine-tuned on it with the step finetune_learning_rate (EQL-style symbolic "
        "regression does the same). ESPL; not in the paper.",
        None,
        unchecked=_BOOL,
    )
    finetune_learning_rate: float = SYMBOLIC(3e-4, "Adam's step when finetune.", above_zero)
    keep_best_formula: bool = SYMBOLIC(
        False,
        "Export the formula that scored best on the selection episodes after each chunk from "
        "t_s on (the hall of fame's best), not the last one; the reported return is measured "
        "afresh on other episodes. ESPL; not in the paper.",
        None,
        unchecked=_BOOL,
    )

    task_seed: int = META(
        0, "The train/test task sets are drawn from this seed (saved in tasks.json).", seed_range
    )
    latent_dim: int = META(
        5, "Size of the task latent z that the context encoder infers.", positive
    )
    encoder_hidden: tuple[int, ...] = META(
        (200, 200, 200), "Hidden layers of PEARL's context encoder.", None, unchecked=_SIZES
    )
    generator_hidden: tuple[int, ...] = META(
        (64, 64),
        "Hidden layers of CSP's Φ and Ψ, one MLP per action dimension.",
        None,
        unchecked=_SIZES,
    )
    pearl_hidden: tuple[int, ...] = META(
        (300, 300, 300), "Hidden layers of PEARL's policy on s ⊕ z.", None, unchecked=_SIZES
    )
    hyper_trunk: tuple[int, ...] = META(
        (256, 512, 1024),
        "Widths of Hyper's hypernetwork trunk, two residual blocks at each (HypeRL's 256, 512, "
        "1024); the weight heads read its last width, so it sets most of the weight count.",
        None,
        unchecked=_SIZES,
    )
    hyper_policy_hidden: int = META(
        256,
        "Hidden width of the policy network s → hidden → (μ, log σ) that Hyper's hypernetwork "
        "generates.",
        positive,
    )
    kl_weight: float = META(
        0.1, "β: PEARL's and the authors' code (the paper's table says 1).", non_negative
    )
    posterior_var_floor: float = META(
        1e-7,
        "Floor of each context transition's factor variance σ²_n before the product of "
        "Gaussians. PEARL's 1e-7 is a numerical guard; a factor at the floor outweighs every "
        "other, and the posterior is then that one transition's μ_n (lunarlander_params, "
        "docs/notes).",
        above_zero,
    )
    meta_batch: int = META(10, "Tasks per gradient step, sampled with replacement.", positive)
    context_batch: int = META(
        100, "Context transitions per task, from its encoder buffer.", positive
    )
    initial_steps: int = META(
        2000,
        "Collection (PEARL's rl_algorithm): before the first iteration every training task "
        "gets initial_steps with z from the prior.",
        non_negative,
    )
    tasks_per_iteration: int = META(
        5,
        "Tasks visited each iteration: their encoder buffers are cleared, then prior_steps and "
        "posterior_steps are collected in each.",
        positive,
    )
    prior_steps: int = META(
        400, "Steps with z from the prior per visited task; they go to both buffers.", positive
    )
    posterior_steps: int = META(
        600,
        "Steps per visited task with z from the posterior of that fresh context (prior_steps' "
        "transitions); they go to the RL buffer only.",
        non_negative,
    )
    task_buffer_size: int = META(100_000, "RL buffer capacity per task.", positive)
    eval_runs: int = META(
        2,
        "Evaluation protocol (PEARL): runs per test task, each from the prior, whole "
        "trajectories until eval_steps.",
        positive,
    )
    eval_steps: int = META(600, "Steps of each evaluation run (PEARL's protocol).", positive)
    eval_exploration_trajectories: int = META(
        2,
        "Trajectories after which the posterior of the run's own transitions is used (PEARL's "
        "protocol); the last trajectory's return is reported.",
        non_negative,
    )
    csp_relaxed_mask: str = META(
        "straight_through",
        "CSP's relaxed mask for the actor loss: straight_through (paper, as ESPL) or soft (the "
        "authors' code).",
        choice("straight_through", "soft"),
    )
    logit_clamp_scale: float = META(
        0.001,
        "CSP (the authors' code, constrain_scale 0.001 in their script): a penalty on Ψ's "
        "logits outside ±6.",
        non_negative,
    )
    weight_l1_scale: float = META(
        0.01,
        "CSP (the authors' code, l0_scale 0.01 in their script): L1 on Φ's weights.",
        non_negative,
    )

    progress_eval_episodes: int = EVALUATION(
        10, "Deterministic episodes after each chunk (learning curve).", positive
    )
    eval_episodes: int = EVALUATION(
        1000, "Final evaluation of the exported formula in JAX.", positive
    )
    reference_eval_episodes: int = EVALUATION(
        100, "Episodes of the exported policy.py in the reference (gymnasium) env.", non_negative
    )

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def total_env_steps(self) -> int:
        return self.iterations * self.steps_per_iteration

    def to_dict(self) -> dict[str, Any]:
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def view(cls: type, config: Config) -> Any:
    """A component's view of the config: the frozen dataclass ``cls`` (e.g. ``sac.SACConfig``)
    with ``config``'s values of its fields, so the component receives the keys it uses and no
    other (each key is still declared, documented and validated once, in ``Config``)."""
    return cls(**{f.name: getattr(config, f.name) for f in fields(cls)})


def _validate(c: Config) -> None:
    # Types first, for every key, so that each range below sees a value of its key's type.
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
            # Every range is written so that NaN fails it, but say what is wrong.
            if not _finite(value):
                raise UserError(f"config: {f.name} must be a finite number, got {value!r}")
        elif expected is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise UserError(f"config: {f.name} must be an integer, got {value!r}")
        elif not isinstance(value, expected):
            raise UserError(f"config: {f.name} must be a {expected.__name__}, got {value!r}")
    # Each key's own range, from its declaration; then int32 for every integer.
    for f in fields(c):
        value, check = getattr(c, f.name), f.metadata["check"]
        if check is not None and not check.ok(value):
            raise UserError(f"config: {f.name} must be {check.requirement}, got {value!r}")
        if _field_type(f) is int and not value < _INT_LIMIT:
            raise UserError(f"config: {f.name} must be below 2**31, got {value!r}")
    # Ranges that involve two keys.
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


def key_table() -> str:
    """Every key, by group: name, type, default and range, then its doc (from the metadata)."""
    width = max(len(f.name) for f in fields(Config))
    lines = []
    for group in GROUPS:
        lines += ["", f"[{group.name}] {group.title}"]
        for f in fields(Config):
            if f.metadata["group"] != group.name:
                continue
            kind = _field_type(f)
            type_name = "list[int]" if kind is tuple else kind.__name__
            check = f.metadata["check"]
            limits = check.requirement if check is not None else f.metadata["unchecked"]
            if kind is int and "2**31" not in limits:
                limits += ", below 2**31"
            lines.append(
                f"  {f.name:<{width}}  {type_name:<9}  {_plain(f.default)!s:<16}  {limits}"
            )
            lines += textwrap.wrap(
                f.metadata["doc"], 98, initial_indent=" " * 6, subsequent_indent=" " * 6
            )
    return "\n".join(lines[1:]) + "\n"


if __name__ == "__main__":
    print(key_table(), end="")
