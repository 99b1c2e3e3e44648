"""Every value a user gives ``train`` is honoured or refused, never replaced by a default.

Hypothesis draws command lines of ``python -m espl_jax.train``: its config flags (taken from the
parser, so a new flag is drawn too), ``--config`` files whose keys (any of the Config's, and some
unknown ones) hold strings, numbers, lists, nulls, booleans and empty values, ``--out`` and
``--resume`` (empty, missing, a run directory). Each command line goes the way ``train.main``
goes up to training (``check_flags``, ``resolve_config``) and must either

- resolve to a config whose fields equal, in type and value, exactly what was given (a flag over
  the file's key; YAML's ints for float keys become floats, lists become tuples, and a number
  written as text, e.g. ``3e-4``, which YAML 1.1 reads as a string, becomes that number), every
  field not given being the shipped ``configs/ENV.yaml``'s, and round-trip through the run's
  config.yaml; or
- be refused with exit status 2 and one ``error:`` line (argparse's own refusals of a flag's
  type or choice: its usage lines and one error line), with no traceback.

Nothing may be written either way. The examples are derandomized and bounded (600, ~10 s).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import io
import tempfile
from dataclasses import fields
from pathlib import Path
from typing import Any

import yaml
from conftest import TINY
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from espl_jax import config as config_lib
from espl_jax import envs, train
from espl_jax.cli import run_main
from espl_jax.config import Config

FIELD_TYPES = {f.name: config_lib._field_type(f) for f in fields(Config)}
CHOICES = {  # the keys declared with config.choice(...), and their choices
    f.name: f.metadata["check"].choices
    for f in fields(Config)
    if f.metadata["check"] is not None and f.metadata["check"].choices
}
# The parser's flags that set a config field of the same name (--env, --seeds, --physics, …).
CONFIG_FLAGS = {
    a.dest: a for a in train.parser()._actions if a.option_strings and a.dest in FIELD_TYPES
}
ENV_NAMES = [*envs.KNOWN_ENVS, *envs.KNOWN_FAMILIES]

texts = st.sampled_from(["", " ", "0", "none", "null", "yes", "3e-4", "1e5", "nan", "-inf",
                         "fast", "cartpole", "symbolic", "auto", "[1]"])  # fmt: skip
anything = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**40), max_value=2**40),
    st.sampled_from([0, 1, -1, 2**31 - 1, 2**31, 10**400]),
    st.floats(),
    texts,
    st.text(max_size=4),
    st.lists(st.one_of(st.integers(-2, 64), st.none(), st.booleans(), texts), max_size=3),
    st.just({}),
)


def typical(key: str) -> st.SearchStrategy:
    """Values of the key's own type, near the edges of what it accepts."""
    kind = FIELD_TYPES[key]
    if key == "env":
        return st.sampled_from([*ENV_NAMES, "", "mars"])
    if key in CHOICES:
        return st.sampled_from([*CHOICES[key], "", "other"])
    if kind is bool:
        return st.booleans()
    if kind is int:
        return st.one_of(st.integers(1, 64), st.integers(-2, 2048))
    if kind is float:
        return st.one_of(
            st.floats(0.01, 1), st.floats(-2, 2), st.integers(-1, 3), st.sampled_from(["3e-4"])
        )
    if kind is tuple:
        return st.one_of(st.lists(st.integers(1, 64), min_size=1, max_size=3), st.just([]))
    raise AssertionError(f"no values drawn for {key} ({kind})")


def values(key: str) -> st.SearchStrategy:
    """Mostly the key's own type, else anything: a file of several keys is then often valid."""
    return st.one_of(typical(key), typical(key), typical(key), anything)


@st.composite
def mappings(draw) -> str:
    """A YAML mapping of some of the Config's keys (and now and then an unknown one)."""
    keys = draw(st.lists(st.sampled_from(sorted(FIELD_TYPES)), unique=True, max_size=5))
    given = {k: draw(values(k)) for k in keys}
    if draw(st.integers(0, 9)) == 0:
        given[draw(st.sampled_from(["learning_rat", 1, None, True]))] = draw(anything)
    return yaml.safe_dump(given, sort_keys=False)


# Files that are not a plain mapping of keys to values, or that give a key twice.
ODD_FILES = ["", "# only a comment\n", "~\n", "- 1\n", "3\n", "iterations:\n", "env:\n",
             "iterations: 3\niterations: 5\n", "env: cartpole\nenv: cartpole\n", "[1, 2\n",
             "1: 2\n", "null: 3\n", "{}\n"]  # fmt: skip
config_files = st.one_of(mappings(), st.sampled_from(ODD_FILES))


def flag_values(action) -> st.SearchStrategy:
    if action.choices is not None:
        return st.sampled_from([*action.choices, *action.choices, "", "other"])
    if action.type is int:
        return st.one_of(st.integers(0, 4), st.integers(-3, 300), st.sampled_from([2**31, 10**20]))
    return st.one_of(st.just(""), typical(action.dest))


@st.composite
def command_lines(draw) -> dict[str, Any]:
    flags = draw(st.lists(st.sampled_from(sorted(CONFIG_FLAGS)), unique=True, max_size=4))
    return {
        "flags": {dest: draw(flag_values(CONFIG_FLAGS[dest])) for dest in flags},
        "config": draw(
            st.one_of(st.none(), config_files, config_files, st.sampled_from(["", "missing"]))
        ),
        "out": draw(st.sampled_from([None, "new", "new", "new", ""])),
        "resume": draw(st.sampled_from([*[None] * 6, "", "missing", "run", "run"])),
    }


@functools.cache
def shipped(env: str) -> Config:
    return config_lib.resolve(env)


RESOLVED: list[Config] = []  # what resolve_only resolved, for the example that ran it


def resolve_only(argv: list[str] | None) -> int:
    """``train.main`` up to training: what it checks and resolves, nothing else."""
    args = train.parser().parse_args(argv)
    train.check_flags(args)
    RESOLVED.append(train.resolve_config(args))
    return 0


def same(a: Any, b: Any) -> bool:
    """Equal in type and value (True is not 1, 1 is not 1.0), element by element for tuples."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def as_given(key: str, value: Any) -> Any:
    """What a given value becomes in the Config when it is honoured (``config._coerce``)."""
    kind = FIELD_TYPES[key]
    if kind is tuple and isinstance(value, list):
        return tuple(value)
    if kind is float and not isinstance(value, bool) and isinstance(value, int | str):
        try:
            return float(value)
        except (ValueError, OverflowError):
            return value
    return value


def expected_config(case: dict[str, Any], file_values: dict, run_config: Config) -> dict:
    """The fields the resolved config must have, if it is honoured."""
    flags = case["flags"]
    if case["resume"] == "run":
        want = {k: getattr(run_config, k) for k in FIELD_TYPES}
        want.update({k: flags[k] for k in ("iterations", "devices") if k in flags})
        return want
    env = flags.get("env", file_values.get("env", config_lib.DEFAULT_ENV))
    assert env in ENV_NAMES, f"an unknown env was honoured: {env!r}"
    base = shipped(env)
    want = {k: getattr(base, k) for k in FIELD_TYPES}
    want.update({k: as_given(k, v) for k, v in file_values.items()})
    want.update({k: as_given(k, v) for k, v in flags.items()})
    return want


def argv_of(case: dict[str, Any], d: Path) -> list[str]:
    argv = []
    for dest, value in case["flags"].items():
        argv += [CONFIG_FLAGS[dest].option_strings[0], str(value)]
    paths = {"": "", "missing": str(d / "missing"), "new": str(d / "new"), "run": str(d / "run")}
    if case["config"] is not None:
        if case["config"] in ("", "missing"):
            argv += ["--config", paths[case["config"]]]
        else:
            (d / "given.yaml").write_text(case["config"])
            argv += ["--config", str(d / "given.yaml")]
    for flag in ("out", "resume"):
        if case[flag] is not None:
            argv += [f"--{flag}", paths[case[flag]]]
    return argv


def snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_every_given_value_is_honoured_or_refused():
    outcomes: collections.Counter = collections.Counter()
    run_config = config_lib.from_mapping(TINY)

    @settings(
        max_examples=600,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(case=command_lines())
    def check(case: dict[str, Any]) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            (d / "run").mkdir()
            config_lib.save(run_config, d / "run" / "config.yaml")
            argv = argv_of(case, d)
            before = snapshot(d)
            RESOLVED.clear()
            stderr = io.StringIO()
            with contextlib.redirect_stderr(stderr):
                try:
                    status = run_main(resolve_only, argv)
                except SystemExit as exit_:  # argparse's refusal of a type or a choice
                    status = exit_.code
            err = stderr.getvalue()
            assert "Traceback" not in err, err
            assert snapshot(d) == before, f"{argv}: resolving wrote a file"
            assert not (d / "new").exists(), f"{argv}: resolving made the run directory"
            if status == 0:
                outcomes["honoured"] += 1
                # Path("") is ".": an empty path cannot be honoured as the file or run it names.
                assert "" not in (case["config"], case["out"], case["resume"]), argv
                file_text = case["config"] if case["config"] not in (None, "", "missing") else ""
                # An empty file (or comments only) gives no values; a null document is one.
                node = yaml.compose(file_text)
                file_values = {} if node is None else yaml.safe_load(file_text)
                assert isinstance(file_values, dict), f"{argv}: {file_text!r} was honoured"
                keys = [k.value for k, _ in getattr(node, "value", [])]
                assert len(set(keys)) == len(keys), f"{file_text!r}: a key given twice"
                want = expected_config(case, file_values, run_config)
                (config,) = RESOLVED
                for key, value in want.items():
                    assert same(getattr(config, key), value), (argv, key, getattr(config, key))
                config_lib.save(config, d / "saved.yaml")  # the run's config.yaml
                assert config_lib.load(d / "saved.yaml") == config
                return
            outcomes["refused"] += 1
            assert status == 2, (argv, err)
            lines = err.strip().splitlines()
            if lines[0].startswith("usage:"):
                assert lines[-1].startswith("python -m espl_jax.train: error: argument "), err
            else:
                assert len(lines) == 1 and lines[0].startswith("error: "), (argv, err)

    check()
    # Both ways are taken, often: the property is not met by refusing everything.
    assert outcomes["honoured"] >= 30 and outcomes["refused"] >= 30, outcomes
