"""Config: every shipped YAML resolves and round-trips; bad input is a UserError naming the key."""

import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from espl_jax import config as config_lib
from espl_jax.config import Config, UserError

CONFIG_FILES = sorted(config_lib.CONFIG_DIR.glob("*.yaml"))


def test_there_are_shipped_configs():
    assert CONFIG_FILES, f"no configs in {config_lib.CONFIG_DIR}"


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: p.stem)
def test_shipped_config_resolves_and_round_trips(path, tmp_path):
    env = path.stem
    cfg = config_lib.resolve(env)
    assert isinstance(cfg, Config)
    assert cfg.env == env
    # The file's values reach the Config (lists become tuples, ints become floats where needed).
    raw = yaml.safe_load(path.read_text())
    assert isinstance(raw, dict) and raw
    for key, value in raw.items():
        got = getattr(cfg, key)
        expected = tuple(value) if isinstance(value, list) else value
        assert got == expected, f"{path.name}: {key} is {got!r}, file says {value!r}"
    # save() then load() gives the same frozen Config back.
    out = tmp_path / "config.yaml"
    config_lib.save(cfg, out)
    assert config_lib.load(out) == cfg
    assert set(yaml.safe_load(out.read_text())) == {f.name for f in fields(Config)}


def test_defaults_round_trip(tmp_path):
    out = tmp_path / "c.yaml"
    config_lib.save(Config(), out)
    assert config_lib.load(out) == Config()


def test_precedence_defaults_file_overrides(tmp_path):
    extra = tmp_path / "extra.yaml"
    extra.write_text("iterations: 7\nbatch_size: 64\n")
    cfg = config_lib.resolve("cartpole", extra, iterations=9, seeds=None)
    assert cfg.iterations == 9  # command line beats --config
    assert cfg.batch_size == 64  # --config beats configs/cartpole.yaml and defaults
    assert cfg.seeds == 1  # None means unset


def test_int_is_accepted_for_float_and_list_for_tuple():
    cfg = config_lib.from_mapping({"learning_rate": 1, "critic_hidden": [8, 4]})
    assert cfg.learning_rate == 1.0 and isinstance(cfg.learning_rate, float)
    assert cfg.critic_hidden == (8, 4)


def test_config_is_frozen():
    with pytest.raises(AttributeError):
        Config().gamma = 0.5  # type: ignore[misc]


@pytest.mark.parametrize(
    "key, value",
    [
        ("batch_size", "abc"),
        ("batch_size", 3.5),
        ("batch_size", True),
        ("learning_rate", "fast"),
        ("critic_hidden", [0]),
        ("critic_hidden", []),
        ("critic_hidden", 256),
        ("std_hidden", ["a"]),
        ("env", 3),
        ("gamma", 1.5),
        ("gamma", 0.0),
        ("polyak", -0.1),
        ("seeds", 0),
        ("iterations", -1),
        ("learning_rate", 0.0),
        ("penalty_scale", -1.0),
        ("reference_eval_episodes", -1),
        ("actor", "cnn"),
        ("layout", "tree"),
        ("selector", "gumbel"),
    ],
)
def test_bad_value_names_the_key(key, value):
    with pytest.raises(UserError, match=rf"\b{key}\b"):
        config_lib.from_mapping({key: value})


def test_bad_choice_lists_the_choices():
    with pytest.raises(
        UserError, match="actor must be one of symbolic, mlp, pearl, hyper, got 'cnn'"
    ):
        config_lib.from_mapping({"actor": "cnn"})


def test_buffer_smaller_than_one_iteration():
    with pytest.raises(UserError, match="buffer_size"):
        config_lib.from_mapping({"buffer_size": 10, "steps_per_iteration": 100})


def test_unknown_key_lists_known_keys():
    with pytest.raises(UserError) as err:
        config_lib.from_mapping({"learning_rat": 1e-3})
    message = str(err.value)
    assert "learning_rat" in message
    assert "known keys" in message
    for f in fields(Config):
        assert f.name in message


def test_missing_config_file(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(UserError, match="not found") as err:
        config_lib.resolve("cartpole", missing)
    assert str(missing) in str(err.value)


def test_malformed_yaml(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("iterations: [1, 2\nseeds: 3\n")
    with pytest.raises(UserError, match="cannot read config file") as err:
        config_lib.load(bad)
    assert str(bad) in str(err.value)
    assert "(line 2, column 6)" in str(err.value)
    assert "\n" not in str(err.value)  # the CLI prints it as one line


def test_binary_config_file(tmp_path):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(UserError, match="cannot read config file"):
        config_lib.load(binary)


def test_yaml_list_is_not_a_mapping(tmp_path):
    listy = tmp_path / "list.yaml"
    listy.write_text("- iterations\n- 3\n")
    with pytest.raises(UserError, match="must hold a mapping"):
        config_lib.resolve("cartpole", listy)


def test_bad_value_in_file_names_the_key(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("batch_size: abc\n")
    with pytest.raises(UserError, match="batch_size must be an integer"):
        config_lib.resolve("cartpole", f)


def test_empty_yaml_is_an_empty_mapping(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert config_lib.resolve("cartpole", empty) == config_lib.resolve("cartpole")


# The trust issue's defects, each pinned (they were silent before) -----------------------------


def test_config_file_may_choose_the_env(tmp_path):
    """`--config h.yaml` holding `env: hopper` trains hopper with hopper's shipped config."""
    path = tmp_path / "h.yaml"
    path.write_text("env: hopper\niterations: 7\n")
    cfg = config_lib.resolve(None, path)
    hopper = config_lib.resolve("hopper")
    assert cfg.env == "hopper" and cfg.iterations == 7
    assert (cfg.gamma, cfg.reward_scale) == (hopper.gamma, hopper.reward_scale)
    assert config_lib.resolve("hopper", path) == cfg  # the same env named twice is fine


def test_shipped_configs_are_inside_the_package():
    """The wheel carries what `--env NAME` loads (package-data espl_jax/configs/*.yaml)."""
    import espl_jax

    package = Path(espl_jax.__file__).resolve().parent
    assert config_lib.CONFIG_DIR.resolve() == (package / "configs").resolve()
    assert (package / "configs" / "cartpole.yaml").is_file()


def test_main_dependencies_cover_the_reference_envs():
    """`pip install -e .` (no extras) must be able to build gymnasium's MuJoCo envs."""
    import tomllib

    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    deps = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    names = {d.split("[")[0].split("=")[0].split(">")[0].split("<")[0].strip() for d in deps}
    assert {"imageio", "mujoco", "gymnasium"} <= names, names


def test_two_runs_started_in_the_same_second_get_different_directories(tmp_path):
    from espl_jax import run

    cfg = config_lib.resolve("cartpole")
    first, second = run.new_run_dir(cfg, tmp_path), run.new_run_dir(cfg, tmp_path)
    assert first != second and first.is_dir() and second.is_dir()


# Each key declared once: its doc and its range in the field's metadata ------------------------


def test_every_key_is_declared_with_a_doc_and_a_range():
    """A new key cannot come without them: validation and the key table read nothing else."""
    groups = {g.name for g in config_lib.GROUPS}
    for f in fields(Config):
        meta = f.metadata
        assert meta["group"] in groups, f.name
        assert meta["doc"].strip(), f"{f.name} has no doc"
        if meta["check"] is None:
            assert meta["unchecked"].strip(), f"{f.name} has no range and no reason for none"
            assert config_lib._field_type(f) not in (int, float), f"{f.name}: a number's range"
        else:
            assert isinstance(meta["check"], config_lib.Check), f.name
            assert meta["check"].ok(getattr(Config(), f.name)), f"{f.name}'s default is refused"
    with pytest.raises(TypeError, match="needs a doc and a check"):
        config_lib.RUN(1, "a count", None)
    with pytest.raises(TypeError, match="needs a doc and a check"):
        config_lib.RUN(1, "", config_lib.positive)


def test_each_group_is_declared_in_one_piece():
    """The meta-RL keys (and every other group's) sit together, in the order of GROUPS."""
    order = [f.metadata["group"] for f in fields(Config)]
    runs = [g for i, g in enumerate(order) if i == 0 or g != order[i - 1]]
    assert runs == [g.name for g in config_lib.GROUPS]


def test_a_file_with_the_keys_in_another_order_loads_the_same(tmp_path):
    """config.yaml is read by name: a run saved with another key order resumes unchanged."""
    cfg = config_lib.resolve("cheetah_vel_ood")
    out = tmp_path / "config.yaml"
    out.write_text(yaml.safe_dump(dict(reversed(cfg.to_dict().items())), sort_keys=False))
    assert config_lib.load(out) == cfg


def test_key_table_lists_every_key():
    proc = subprocess.run(
        [sys.executable, "-m", "espl_jax.config"], capture_output=True, text=True, check=True
    )
    lines = proc.stdout.splitlines()
    for group in config_lib.GROUPS:
        assert f"[{group.name}] {group.title}" in lines
    rows = {line.split()[0]: line for line in lines if line.startswith("  ") and line[2] != " "}
    assert set(rows) == {f.name for f in fields(Config)}
    assert rows["actor"].split()[1:4] == ["str", "symbolic", "one"]
    assert rows["gamma"].split()[1:] == ["float", "0.99", "in", "(0,", "1]"]
    assert rows["critic_hidden"].split()[1:4] == ["list[int]", "[256,", "256]"]
    assert "posterior of that fresh context" in proc.stdout  # the docs are printed


def test_component_views_hold_the_configs_values():
    # The update and the policy kinds receive the keys they read, not the whole Config.
    from espl_jax.policies import PolicyConfig
    from espl_jax.sac import SACConfig

    cfg = config_lib.resolve("cartpole_fl_ood", actor="symbolic")
    for cls in (SACConfig, PolicyConfig):
        view = config_lib.view(cls, cfg)
        for f in fields(cls):
            assert getattr(view, f.name) == getattr(cfg, f.name), f.name
