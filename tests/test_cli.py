"""Command lines: a user error is one "error: ..." line on stderr, exit code 2, no traceback."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY, TINY_MLP

from espl_jax import config as config_lib
from espl_jax import envs, run, rundir

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _share_compilation_cache(jax_cache, monkeypatch):
    """The CLI subprocesses read and fill this session's compilation cache."""
    for name, value in jax_cache.items():
        monkeypatch.setenv(name, value)


def cli(module: str, *args: str, timeout: float = 600):
    return subprocess.run(
        [sys.executable, "-m", f"espl_jax.{module}", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=timeout,
    )


def assert_user_error(proc, *fragments: str) -> str:
    """Exit code 2, one stderr line starting with "error:", no traceback; returns that line."""
    output = proc.stdout + proc.stderr
    assert "Traceback" not in output, output
    assert proc.returncode == 2, output
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    line = lines[0]
    assert line.startswith("error: "), line
    for fragment in fragments:
        assert fragment in line, line
    return line


# --help ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "module, options",
    [
        ("train", ["--env", "--config", "--seeds", "--iterations", "--resume", "--out"]),
        ("evaluate", ["run_dir", "--episodes", "--seed"]),
        ("export", ["run_dir", "--format", "--seed", "--output"]),
    ],
)
def test_help(module, options):
    proc = cli(module, "--help")
    assert proc.returncode == 0, proc.stderr
    assert f"python -m espl_jax.{module}" in proc.stdout
    for option in options:
        assert option in proc.stdout


# Errors before any training ------------------------------------------------------------------


def test_train_unknown_env_lists_known_envs(tmp_path):
    proc = cli("train", "--env", "cartpol", "--out", str(tmp_path / "run"), "--no-progress")
    line = assert_user_error(proc, "cartpol")
    for name in envs.KNOWN_ENVS:
        assert name in line
    assert not (tmp_path / "run").exists()  # nothing written for a run that cannot start


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("batch_size: abc\n", "batch_size must be an integer"),
        ("learning_rat: 0.1\n", "unknown key(s) learning_rat"),
        ("iterations: [1, 2\n", "cannot read config file"),
        ("- 1\n- 2\n", "must hold a mapping"),
    ],
)
def test_train_bad_config_file(tmp_path, text, fragment):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    proc = cli("train", "--config", str(path), "--out", str(tmp_path / "run"), "--no-progress")
    assert_user_error(proc, fragment)
    assert not (tmp_path / "run").exists()


def test_train_missing_config_file(tmp_path):
    proc = cli("train", "--config", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "r"))
    assert_user_error(proc, "config file not found", "nope.yaml")


def test_resume_without_config_yaml(tmp_path):
    proc = cli("train", "--resume", str(tmp_path))
    assert_user_error(proc, "not a run directory", "config.yaml")


def test_resume_without_checkpoints(tmp_path):
    config_lib.save(config_lib.from_mapping(TINY), tmp_path / "config.yaml")
    proc = cli("train", "--resume", str(tmp_path), "--no-progress")
    assert_user_error(proc, "checkpoints/ is missing")


def test_resume_with_empty_checkpoints(tmp_path):
    config_lib.save(config_lib.from_mapping(TINY), tmp_path / "config.yaml")
    (tmp_path / rundir.CHECKPOINT_DIR).mkdir()
    proc = cli("train", "--resume", str(tmp_path), "--no-progress")
    assert_user_error(proc, "no complete checkpoint")


@pytest.mark.parametrize("module", ["evaluate", "export"])
def test_not_a_run_directory(tmp_path, module):
    assert_user_error(cli(module, str(tmp_path)), "not a run directory")


def test_evaluate_without_policy(tmp_path):
    config_lib.save(config_lib.from_mapping(TINY), tmp_path / "config.yaml")
    assert_user_error(cli("evaluate", str(tmp_path)), "no exported policy")


# Errors on real runs --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory):
    """A real run of the tiny config stopped after 2 of its iterations (no export)."""
    run_dir = tmp_path_factory.mktemp("cli") / "run"
    run.train(config_lib.from_mapping(TINY), run_dir, show_progress=False, stop_after=2)
    return run_dir


@pytest.mark.slow
def test_export_of_mlp_run_has_no_formula(tmp_path):
    run.train(config_lib.from_mapping(TINY_MLP), tmp_path, show_progress=False)
    assert_user_error(cli("export", str(tmp_path)), "MLP actor", "no formula")


def _damage(run_dir: Path, keep_metadata: bool) -> None:
    """Overwrite the files of the newest checkpoint with garbage (all of them, or the data
    only); the one before it is the initial state's."""
    steps = [p.name for p in (run_dir / rundir.CHECKPOINT_DIR).iterdir() if p.name.isdigit()]
    assert sorted(steps) == ["0", "2"]
    metadata = {"_CHECKPOINT_METADATA", "commit_success.txt"}
    damaged = 0
    for path in (run_dir / rundir.CHECKPOINT_DIR / "2").rglob("*"):
        if path.is_file() and not (keep_metadata and path.name in metadata):
            path.write_bytes(b"\x00garbage\xff" * 3)
            damaged += 1
    assert damaged


@pytest.mark.parametrize(
    "module, keep_metadata", [("export", False), ("export", True), ("train", False)]
)
def test_corrupt_checkpoint(stopped_run, tmp_path, module, keep_metadata):
    run_dir = tmp_path / "run"
    shutil.copytree(stopped_run, run_dir)
    _damage(run_dir, keep_metadata)
    args = ["--resume", str(run_dir), "--no-progress"] if module == "train" else [str(run_dir)]
    line = assert_user_error(cli(module, *args), "unreadable", "corrupt")
    assert str(run_dir / rundir.CHECKPOINT_DIR / "2") in line


def test_export_bad_seed(stopped_run):
    assert_user_error(cli("export", str(stopped_run), "--seed", "7"), "--seed")


def test_train_refuses_to_overwrite_a_run(stopped_run, tmp_path):
    config = tmp_path / "tiny.yaml"
    config.write_text((stopped_run / "config.yaml").read_text())
    proc = cli("train", "--config", str(config), "--out", str(stopped_run), "--no-progress")
    assert_user_error(proc, "already holds a run", "--resume")


@pytest.mark.parametrize(
    ("variables", "expected"),
    [
        ({"XDG_CACHE_HOME": "{tmp}"}, "{tmp}/espl_jax/xla"),  # the default place
        ({"JAX_COMPILATION_CACHE_DIR": "{tmp}/mine"}, "{tmp}/mine"),  # the user's choice wins
        ({"JAX_COMPILATION_CACHE_DIR": "off"}, None),
    ],
)
def test_compilation_cache_location(tmp_path, monkeypatch, variables, expected):
    import jax

    from espl_jax.cli import use_compilation_cache

    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    for name, value in variables.items():
        monkeypatch.setenv(name, value.format(tmp=tmp_path))
    before = jax.config.jax_compilation_cache_dir
    try:
        got = use_compilation_cache()
        expected = expected and expected.format(tmp=tmp_path)
        assert got == expected
        if "XDG_CACHE_HOME" in variables:
            assert Path(got).is_dir() and jax.config.jax_compilation_cache_dir == got
        if expected is None:
            assert jax.config.jax_compilation_cache_dir is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
