"""Bad input at every entry point: one ``error:`` line, exit status 2, no traceback, nothing lost.

Each case runs a command line (``train``, ``evaluate`` or ``export``) in-process through the same
``cli.run_main`` the ``python -m`` entry points use, with stdout/stderr captured at the file
descriptors (so orbax/absl log lines would count as extra lines). Cases that touch a run work on a
fresh copy of one tiny finished run, damaged as the case says, and check afterwards that every
file of that run directory is byte-identical to before the command. Cases that can recover
instead of failing (a metrics line cut short by a kill, a missing eval.json) are at the end.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import pytest
import yaml
from conftest import TINY

from espl_jax import config as config_lib
from espl_jax import evaluate, export, run, rundir, train
from espl_jax.cli import run_main

pytestmark = pytest.mark.usefixtures("jax_cache")

ENTRY_POINTS = {"train": train.main, "evaluate": evaluate.main, "export": export.main}


def invoke(capfd, module: str, *args: str) -> tuple[int, str, str]:
    """Exit status, stdout and stderr of ``python -m espl_jax.MODULE ARGS``, run in-process."""
    capfd.readouterr()
    try:
        status = run_main(ENTRY_POINTS[module], list(args))
    except SystemExit as exit_:  # argparse's own errors
        status = exit_.code
    out, err = capfd.readouterr()
    return status, out, err


def snapshot(directory: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A complete tiny run: checkpoints 2 and 4, metrics, eval.json, expression.txt, policy.py."""
    run_dir = tmp_path_factory.mktemp("bad_input") / "run"
    run.train(config_lib.from_mapping(TINY), run_dir, show_progress=False)
    return run_dir


# Ways to damage a copy of the finished run -----------------------------------------------------


def remove(name: str) -> Callable[[Path], None]:
    def damage(run_dir: Path) -> None:
        path = run_dir / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()

    return damage


def write(name: str, text: str) -> Callable[[Path], None]:
    def damage(run_dir: Path) -> None:
        (run_dir / name).write_text(text)

    return damage


def set_config(**values) -> Callable[[Path], None]:
    def damage(run_dir: Path) -> None:
        path = run_dir / "config.yaml"
        path.write_text(yaml.safe_dump({**yaml.safe_load(path.read_text()), **values}))

    return damage


def empty_checkpoints(run_dir: Path) -> None:
    shutil.rmtree(run_dir / rundir.CHECKPOINT_DIR)
    (run_dir / rundir.CHECKPOINT_DIR).mkdir()


def corrupt_checkpoints(keep_metadata: bool) -> Callable[[Path], None]:
    """Overwrite the files of every checkpoint with garbage (all of them, or the data only)."""
    metadata = {"_CHECKPOINT_METADATA", "commit_success.txt"}

    def damage(run_dir: Path) -> None:
        damaged = 0
        for path in (run_dir / rundir.CHECKPOINT_DIR).rglob("*"):
            if path.is_file() and not (keep_metadata and path.name in metadata):
                path.write_bytes(b"\x00garbage\xff" * 3)
                damaged += 1
        assert damaged

    return damage


def corrupt_metrics_middle(run_dir: Path) -> None:
    path = run_dir / rundir.METRICS_FILE
    lines = path.read_text().splitlines()
    lines[1] = lines[1][: len(lines[1]) // 2]
    path.write_text("\n".join(lines) + "\n")


def as_env(env: str, actor: str = "symbolic") -> Callable[[Path], None]:
    """The run's config.yaml claims another env or actor (a run of that kind, for the checks
    that read only the config)."""
    return set_config(env=env, actor=actor)


@dataclass(frozen=True)
class Case:
    """A bad command line: ``args`` may hold ``{run}`` (the damaged copy of the finished run),
    ``{config}`` (a YAML file holding ``config_text``) and ``{tmp}`` (an empty directory)."""

    id: str
    module: str
    args: tuple[str, ...]
    fragments: tuple[str, ...]
    damage: Callable[[Path], None] | None = None
    config_text: str = ""
    argparse: bool = False  # argparse's usage-and-error message, not ours


def config_case(id_: str, text: str, *fragments: str) -> Case:
    return Case(id_, "train", ("--config", "{config}", "--out", "{tmp}/new"), fragments,
                config_text=text)  # fmt: skip


# Out-of-range and non-finite values for every numeric key of the config: by the range its
# declaration gives (config.Check), with the message each range has always had.
_OUTSIDE = {
    config_lib.positive: (0, "must be positive"),
    config_lib.non_negative: (-1, "must be >= 0"),
    config_lib.unit_interval: (1.5, "must be in (0, 1]"),
    config_lib.above_zero: (0.0, "must be > 0"),
    config_lib.seed_range: (-1, "must be in [0, 2**31)"),
}
_SPECIAL = {
    "exploration_correlation": (1.0, "exploration_correlation must be in [0, 1)"),
    "task_seed": (2**31, "task_seed must be in [0, 2**31)"),
}
NUMERIC_KEYS = [
    f.name for f in fields(config_lib.Config) if config_lib._field_type(f) in (int, float)
]


def _out_of_range(key: str) -> tuple[object, str]:
    if key in _SPECIAL:
        return _SPECIAL[key]
    check = next(f for f in fields(config_lib.Config) if f.name == key).metadata["check"]
    if check not in _OUTSIDE:
        raise AssertionError(f"the bad-input table has no out-of-range value for {key}")
    value, message = _OUTSIDE[check]
    return value, f"{key} {message}"


def _non_finite(key: str) -> str:
    field = next(f for f in fields(config_lib.Config) if f.name == key)
    if config_lib._field_type(field) is int:
        return f"{key} must be an integer"
    return f"{key} must be a finite number"


CASES: list[Case] = [
    # train: the environment
    Case("unknown-env", "train", ("--env", "cartpol", "--out", "{tmp}/new"),
         ("unknown environment 'cartpol'", "cartpole", "hopper", "lunarlander")),
    Case("env-without-config", "train", ("--env", "halfcheetah", "--out", "{tmp}/new"),
         ("no shipped config for env 'halfcheetah'",)),
    config_case("env-in-file-unknown", "env: mars\n", "unknown environment 'mars'"),
    config_case("env-in-file-not-a-string", "env: 3\n", "env must be a string"),
    config_case("env-in-file-null", "env:\n", "env must be a string, got None"),
    config_case("env-in-file-empty", "env: ''\n", "unknown environment ''"),
    Case("env-flag-empty", "train", ("--env", "", "--out", "{tmp}/new"),
         ("unknown environment ''",)),
    Case("env-flag-empty-beside-a-file", "train",
         ("--env", "", "--config", "{config}", "--out", "{tmp}/new"),
         ("unknown environment ''",), config_text="env: cartpole\n"),
    Case("env-flag-and-file-disagree", "train",
         ("--env", "pendulum", "--config", "{config}", "--out", "{tmp}/new"),
         ("--env pendulum", "(cartpole) disagree"), config_text="env: cartpole\n"),
    # train: the config file
    Case("missing-config-file", "train", ("--config", "{tmp}/nope.yaml", "--out", "{tmp}/new"),
         ("config file not found", "nope.yaml")),
    Case("config-flag-empty", "train", ("--config", "", "--out", "{tmp}/new"),
         ("--config is empty",)),
    config_case("malformed-yaml", "iterations: [1, 2\nseeds: 3\n", "cannot read config file",
                "line 2"),
    config_case("yaml-not-a-mapping", "- 1\n- 2\n", "must hold a mapping"),
    config_case("yaml-null-document", "~\n", "must hold a mapping"),
    config_case("key-given-twice", "iterations: 3\nseeds: 1\niterations: 5\n",
                "key 'iterations' is given twice (line 3"),
    config_case("key-not-a-string", "1: 2\n", "unknown key(s) 1;"),
    config_case("key-null", "null: 2\n", "unknown key(s) None;"),
    config_case("unknown-key", "learning_rat: 0.1\n", "unknown key(s) learning_rat"),
    config_case("int-key-given-text", "batch_size: abc\n", "batch_size must be an integer"),
    config_case("int-key-given-float", "iterations: 3.5\n", "iterations must be an integer"),
    config_case("int-key-given-bool", "seeds: true\n", "seeds must be an integer"),
    config_case("float-key-given-text", "gamma: fast\n", "gamma must be a number"),
    config_case("float-key-given-list", "learning_rate: [1]\n", "learning_rate must be a number"),
    config_case("choice-key-unknown", "actor: transformer\n", "actor must be one of symbolic"),
    config_case("choice-key-wrong-type", "layout: 3\n", "layout must be a str"),
    config_case("list-key-given-int", "critic_hidden: 256\n", "critic_hidden must be a list"),
    config_case("list-key-empty", "critic_hidden: []\n", "critic_hidden must be a list"),
    config_case("list-key-non-positive", "std_hidden: [64, 0]\n", "std_hidden must be a list"),
    config_case("buffer-smaller-than-iteration", "buffer_size: 10\nsteps_per_iteration: 100\n",
                "buffer_size (10) must be at least steps_per_iteration (100)"),
    *(
        config_case(f"out-of-range-{key}", f"{key}: {_out_of_range(key)[0]}\n",
                    _out_of_range(key)[1])
        for key in NUMERIC_KEYS
    ),
    *(config_case(f"nan-{key}", f"{key}: .nan\n", _non_finite(key)) for key in NUMERIC_KEYS),
    config_case("inf-learning_rate", "learning_rate: .inf\n", "learning_rate must be a finite"),
    config_case("minus-inf-gamma", "gamma: -.inf\n", "gamma must be a finite number"),
    config_case("nan-as-text", "select_scale: nan\n", "select_scale must be a finite number"),
    config_case("int-beyond-int32", "iterations: 2147483648\n",
                "iterations must be below 2**31, got 2147483648"),
    config_case("list-entry-beyond-int32", "critic_hidden: [2147483648]\n",
                "critic_hidden must be a list of positive integers below 2**31"),
    config_case("float-key-given-an-int-beyond-floats", f"learning_rate: {10**400}\n",
                "learning_rate must be a finite number"),
    # An empty value (YAML null) for every key is refused, never replaced by the default.
    *(
        config_case(f"null-{f.name}", f"{f.name}:\n", f"{f.name} must be", "got None")
        for f in fields(config_lib.Config)
        if f.name != "env"  # above: "env must be a string"
    ),
    # train: flags
    Case("flag-iterations-zero", "train", ("--iterations", "0", "--out", "{tmp}/new"),
         ("iterations must be positive",)),
    Case("flag-seeds-negative", "train", ("--seeds", "-2", "--out", "{tmp}/new"),
         ("seeds must be positive",)),
    Case("flag-seed-negative", "train", ("--seed", "-1", "--out", "{tmp}/new"),
         ("seed must be in",)),
    Case("flag-devices-too-many", "train",
         ("--seeds", "64", "--devices", "64", "--out", "{tmp}/new"),
         ("devices: 64 asked for, 1 available",)),
    Case("flag-devices-not-dividing-seeds", "train",
         ("--seeds", "3", "--devices", "2", "--out", "{tmp}/new"),
         ("devices (2) must divide seeds (3)",)),
    Case("flag-devices-negative", "train", ("--devices", "-1", "--out", "{tmp}/new"),
         ("devices must be >= 0",)),
    Case("resume-devices-too-many", "train", ("--resume", "{run}", "--devices", "2"),
         ("devices: 2 asked for, 1 available",)),
    Case("flag-iterations-not-int", "train", ("--iterations", "ten"), ("invalid int value",),
         argparse=True),
    Case("flag-actor-unknown", "train", ("--actor", "cnn"), ("invalid choice",), argparse=True),
    Case("flag-unknown", "train", ("--episodes", "3"), ("unrecognized arguments",),
         argparse=True),
    Case("out-holds-a-run", "train", ("--config", "{config}", "--out", "{run}"),
         ("already holds a run", "--resume"), config_text="env: cartpole\n"),
    Case("out-empty", "train", ("--out", ""), ("--out is empty",)),
    Case("coordinator-empty", "train",
         ("--distributed", "--coordinator", "", "--num-processes", "2", "--process-id", "0",
          "--out", "{tmp}/new"), ("--coordinator is empty",)),
    # train --resume: flags that cannot change, and the run directory
    *(
        Case(f"resume-with-{flag}", "train", ("--resume", "{run}", f"--{flag}", value),
             (f"--{flag} cannot be changed on resume",))
        for flag, value in [("env", "cartpole"), ("seeds", "3"), ("actor", "mlp"),
                            ("seed", "4"), ("out", "elsewhere"), ("config", "c.yaml")]
    ),
    Case("resume-shorter-than-trained", "train", ("--resume", "{run}", "--iterations", "3"),
         ("has already trained 4 iterations", "at least 4")),
    Case("resume-iterations-zero", "train", ("--resume", "{run}", "--iterations", "0"),
         ("iterations must be positive",)),
    Case("resume-not-a-run", "train", ("--resume", "{tmp}"), ("not a run directory",)),
    Case("resume-empty", "train", ("--resume", ""), ("--resume is empty",)),
    Case("resume-without-config", "train", ("--resume", "{run}"), ("not a run directory",),
         damage=remove("config.yaml")),
    Case("resume-malformed-config", "train", ("--resume", "{run}"),
         ("cannot read config file",), damage=write("config.yaml", "gamma: [0.9\n")),
    Case("resume-bad-config-value", "train", ("--resume", "{run}"), ("gamma must be in (0, 1]",),
         damage=set_config(gamma=2.0)),
    Case("resume-without-checkpoints", "train", ("--resume", "{run}"),
         ("checkpoints/ is missing",), damage=remove(rundir.CHECKPOINT_DIR)),
    Case("resume-empty-checkpoints", "train", ("--resume", "{run}"),
         ("no complete checkpoint",), damage=empty_checkpoints),
    Case("resume-corrupt-checkpoint", "train", ("--resume", "{run}"),
         ("is unreadable", "corrupt"), damage=corrupt_checkpoints(keep_metadata=False)),
    Case("resume-corrupt-checkpoint-data", "train", ("--resume", "{run}"),
         ("is unreadable", "corrupt"), damage=corrupt_checkpoints(keep_metadata=True)),
    Case("resume-corrupt-metrics", "train", ("--resume", "{run}"),
         ("metrics.jsonl is corrupt at line 2",), damage=corrupt_metrics_middle),
    # evaluate
    Case("evaluate-not-a-run", "evaluate", ("{tmp}",), ("not a run directory",)),
    Case("evaluate-without-config", "evaluate", ("{run}",), ("not a run directory",),
         damage=remove("config.yaml")),
    Case("evaluate-malformed-config", "evaluate", ("{run}",), ("cannot read config file",),
         damage=write("config.yaml", "env: [cartpole\n")),
    Case("evaluate-without-policy", "evaluate", ("{run}",), ("no exported policy",),
         damage=remove(rundir.POLICY_FILE)),
    Case("evaluate-broken-policy", "evaluate", ("{run}",), ("cannot load", "SyntaxError"),
         damage=write(rundir.POLICY_FILE, "def act(obs:\n")),
    Case("evaluate-policy-without-act", "evaluate", ("{run}",), ("has no act(obs) function",),
         damage=write(rundir.POLICY_FILE, "x = 1\n")),
    Case("evaluate-corrupt-eval-json", "evaluate", ("{run}",), ("eval.json is unreadable",),
         damage=write(rundir.EVAL_FILE, '{"env": "cartpole", "jax_')),
    Case("evaluate-eval-json-not-an-object", "evaluate", ("{run}",),
         ("eval.json is unreadable (not a JSON object)",), damage=write(rundir.EVAL_FILE, "[1]\n")),
    Case("evaluate-no-reference-env", "evaluate", ("{run}",),
         ("inverted_pendulum_swingup has no reference environment",),
         damage=as_env("inverted_pendulum_swingup")),
    Case("evaluate-episodes-zero", "evaluate", ("{run}", "--episodes", "0"),
         ("--episodes must be positive",)),
    Case("evaluate-seed-negative", "evaluate", ("{run}", "--seed", "-1"),
         ("--seed must be >= 0, got -1",)),
    Case("evaluate-run-dir-empty", "evaluate", ("",), ("RUN_DIR is empty",)),
    Case("evaluate-episodes-not-int", "evaluate", ("{run}", "--episodes", "many"),
         ("invalid int value",), argparse=True),
    # export
    Case("export-not-a-run", "export", ("{tmp}",), ("not a run directory",)),
    Case("export-without-config", "export", ("{run}",), ("not a run directory",),
         damage=remove("config.yaml")),
    Case("export-without-checkpoints", "export", ("{run}",), ("checkpoints/ is missing",),
         damage=remove(rundir.CHECKPOINT_DIR)),
    Case("export-corrupt-checkpoint", "export", ("{run}",), ("is unreadable", "corrupt"),
         damage=corrupt_checkpoints(keep_metadata=False)),
    Case("export-corrupt-eval-json", "export", ("{run}",),
         ("eval.json is unreadable", "give --seed"), damage=write(rundir.EVAL_FILE, "{")),
    Case("export-bad-best-seed", "export", ("{run}",), ("bad best_seed", "give --seed"),
         damage=write(rundir.EVAL_FILE, '{"best_seed": "first"}\n')),
    Case("export-seed-out-of-range", "export", ("{run}", "--seed", "7"),
         ("--seed must be in [0, 1]",)),
    Case("export-seed-negative", "export", ("{run}", "--seed", "-1"),
         ("--seed must be in [0, 1]",)),
    Case("export-pick-seed-out-of-range", "export", ("{run}", "--pick", "best", "--seed", "7"),
         ("--seed must be in [0, 1]",)),
    Case("export-pick-stable-within-no-equilibrium", "export",
         ("{run}", "--pick", "stable-within", "5"),
         ("stable-within needs the local-stability analysis", "mountaincar has no equilibrium"),
         damage=as_env("mountaincar")),
    Case("export-pick-stable-within-without-percentage", "export",
         ("{run}", "--pick", "stable-within"), ("--pick stable-within takes a percentage",)),
    Case("export-pick-stable-within-not-a-number", "export",
         ("{run}", "--pick", "stable-within", "five"), ("'five' is not a number",)),
    Case("export-pick-stable-within-out-of-range", "export",
         ("{run}", "--pick", "stable-within", "150"),
         ("--pick stable-within needs a percentage in [0, 100]",)),
    Case("export-run-dir-empty", "export", ("",), ("RUN_DIR is empty",)),
    Case("export-output-empty", "export", ("{run}", "--output", ""), ("--output is empty",)),
    Case("export-mlp-run", "export", ("{run}",), ("MLP actor", "no formula"),
         damage=as_env("cartpole", actor="mlp")),
    Case("export-output-in-missing-dir", "export", ("{run}", "-o", "{tmp}/no/such/policy.py"),
         ("No such file or directory", "policy.py")),
    Case("export-format-unknown", "export", ("{run}", "--format", "pdf"), ("invalid choice",),
         argparse=True),
]  # fmt: skip


def test_the_suite_is_large_and_covers_every_entry_point():
    assert len(CASES) >= 40
    assert {c.module for c in CASES} == set(ENTRY_POINTS)
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_bad_input(case, tmp_path, capfd, request):
    run_dir = tmp_path / "run"
    if any("{run}" in a for a in case.args):  # only these need the (one-minute) tiny run
        shutil.copytree(request.getfixturevalue("finished_run"), run_dir)
    else:
        run_dir.mkdir()
    if case.damage is not None:
        case.damage(run_dir)
    (tmp_path / "empty").mkdir()
    config = tmp_path / "config.yaml"
    config.write_text(case.config_text)
    values = {"run": str(run_dir), "config": str(config), "tmp": str(tmp_path / "empty")}
    args = [a.format(**values) for a in case.args]
    before = snapshot(run_dir)

    status, out, err = invoke(capfd, case.module, *args)

    assert "Traceback" not in out + err, out + err
    assert status == 2, out + err
    lines = err.strip().splitlines()
    if case.argparse:  # usage lines, then "PROG: error: ..."
        assert "error:" in lines[-1], err
        assert lines[0].startswith("usage:"), err
    else:
        assert len(lines) == 1, err
        assert lines[0].startswith("error: "), err
    for fragment in case.fragments:
        assert fragment in lines[-1], lines[-1]
    assert snapshot(run_dir) == before, "the command changed the run directory"
    assert not (tmp_path / "empty" / "new").exists(), "a run that cannot start wrote a directory"
    if os.environ.get("BAD_INPUT_TABLE"):  # the table of cases and messages for the docs
        shown = " ".join(case.args).replace("{", "<").replace("}", ">")
        if case.config_text:
            shown += f"` with `{case.config_text.strip()!r}"
        with open(os.environ["BAD_INPUT_TABLE"], "a") as table:
            table.write(f"| {case.id} | `{case.module} {shown}` | `{lines[-1]}` |\n")


# Recoverable damage ---------------------------------------------------------------------------


def test_metrics_line_cut_short_by_a_kill_is_dropped_on_resume(finished_run, tmp_path, capfd):
    """A kill while a metrics row was written leaves half a line after the newest checkpoint's
    rows: resume drops it and finishes; every complete row is kept."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    metrics = run_dir / rundir.METRICS_FILE
    complete = metrics.read_text()
    metrics.write_text(complete + '{"iteration": 5, "seed": 0, "train_re')
    status, _, err = invoke(capfd, "train", "--resume", str(run_dir), "--no-progress")
    assert status == 0, err
    assert metrics.read_text() == complete
    assert rundir.read_eval(run_dir)["best_seed"] in (0, 1)


def test_missing_eval_json_is_recreated_by_evaluate(finished_run, tmp_path, capfd):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    (run_dir / rundir.EVAL_FILE).unlink()
    status, out, err = invoke(capfd, "evaluate", str(run_dir), "--episodes", "2")
    assert status == 0, err
    record = json.loads((run_dir / rundir.EVAL_FILE).read_text())
    assert record["reference_eval"]["episodes"] == 2
    assert "cartpole:" in out


def test_export_without_eval_json_exports_seed_0(finished_run, tmp_path, capfd):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    (run_dir / rundir.EVAL_FILE).unlink()
    status, out, err = invoke(capfd, "export", str(run_dir), "--seed", "0")
    assert status == 0, err
    status_default, out_default, _ = invoke(capfd, "export", str(run_dir))
    assert status_default == 0 and out_default == out and out.startswith("a0 = ")


# A run directory missing each one of its files in turn ------------------------------------------

RUN_FILES = (".lock", "checkpoints", "config.yaml", "eval.json", "expression.txt",
             "formulas.jsonl", "hall_of_fame.png", "learning_curve.png", "metrics.jsonl",
             "policy.py", "timing.json")  # fmt: skip
COMMANDS = {
    "evaluate": ("evaluate", "{run}", "--episodes", "2"),
    "export": ("export", "{run}"),
    "resume": ("train", "--resume", "{run}", "--no-progress"),
}
# What cannot work without the file; everything else must succeed without it.
NEEDED = {
    ("config.yaml", "evaluate"): "is not a run directory (no config.yaml)",
    ("config.yaml", "export"): "is not a run directory (no config.yaml)",
    ("config.yaml", "resume"): "is not a run directory (no config.yaml)",
    ("checkpoints", "export"): "checkpoints/ is missing",
    ("checkpoints", "resume"): "checkpoints/ is missing",
    ("policy.py", "evaluate"): "no exported policy",
}


def test_the_missing_file_table_lists_every_file_of_a_run(finished_run):
    assert sorted(p.name for p in finished_run.iterdir()) == sorted(RUN_FILES)


@pytest.mark.parametrize(
    "name, command",
    [
        pytest.param(
            n, c, marks=[pytest.mark.slow] if c == "resume" and (n, c) not in NEEDED else []
        )
        for n in RUN_FILES
        for c in COMMANDS
    ],
)
def test_run_missing_a_file(name, command, finished_run, tmp_path, capfd):
    """Either a clean error naming what is missing (and no other file touched) or success."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    remove(name)(run_dir)
    before = snapshot(run_dir)
    module, *args = COMMANDS[command]
    status, out, err = invoke(capfd, module, *(a.format(run=run_dir) for a in args))
    assert "Traceback" not in out + err, out + err
    if (name, command) in NEEDED:
        assert status == 2, out + err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), err
        assert NEEDED[name, command] in lines[0], lines[0]
        assert snapshot(run_dir) == before
    else:
        assert status == 0, out + err
