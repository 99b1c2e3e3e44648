"""Packaging: the wheel adds exactly one top-level name, ``espl_jax``; the dependency ranges of
pyproject.toml hold the exact tested set of constraints.txt.

A top-level ``envs`` package (as the wheel once installed) would overwrite PyPI's ``envs``; the
top-level ``envs/`` folder of the source tree installs as ``espl_jax.envs`` instead.
"""

import csv
import io
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
# What the build reads. Copied into a fresh folder so that a stale build/ of the checkout (whose
# files bdist_wheel would pick up) cannot hide or add a name.
SOURCES = ["pyproject.toml", "README.md", "LICENSE", "espl_jax", "envs", "configs"]


def _top(path: str) -> str:
    return path.split("/", 1)[0]


def test_wheel_installs_only_espl_jax(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            # symlinks=True keeps espl_jax/configs and espl_jax/envs as links, as in a checkout
            shutil.copytree(path, src / name, symlinks=True, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    dist = tmp_path / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", str(src), "-w", str(dist)],
        check=True,
        timeout=300,
    )
    (wheel,) = dist.glob("espl_jax-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        info = next(_top(n) for n in names if _top(n).endswith(".dist-info"))
        record = [row[0] for row in csv.reader(io.StringIO(zf.read(f"{info}/RECORD").decode()))]
        top_level = zf.read(f"{info}/top_level.txt").decode().split()

    packages = {_top(n) for n in names} - {info}
    assert packages == {"espl_jax"}, sorted(packages)
    assert {_top(p) for p in record} - {info} == {"espl_jax"}
    assert set(top_level) == {"espl_jax"}, top_level
    # envs/ and configs/ arrive as files under espl_jax/, not as links
    for name in [
        "espl_jax/envs/__init__.py",
        "espl_jax/envs/tasks.py",
        "espl_jax/configs/cartpole.yaml",
    ]:
        assert name in names, name
    assert not any(_top(n) == "envs" or n.startswith("envs/") for n in record)


def _constraints() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not name==version"
            pins[canonicalize_name(name)] = version
    return pins


def test_constraints_satisfy_the_declared_ranges():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = [*project["dependencies"], *project["optional-dependencies"]["dev"]]
    pins = _constraints()
    for line in declared:
        req = Requirement(line)
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is declared but not pinned in constraints.txt"
        assert req.specifier.contains(pins[name]), f"constraints.txt {name}=={pins[name]}: {req}"
    # MJX runs MuJoCo's own model: the two packages must be the same release.
    assert pins["mujoco"] == pins["mujoco-mjx"]
    for line in project["dependencies"]:  # ranges, not pins: installable beside other packages
        assert "==" not in line, line
