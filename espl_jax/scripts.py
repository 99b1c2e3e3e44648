"""Console scripts (pyproject.toml ``[project.scripts]``): ``espl-train``, ``espl-evaluate``,
``espl-export`` and ``espl-analyze`` are ``python -m espl_jax.<module>``, the same ``main`` behind
``cli.run_main`` (a user error prints one ``error:`` line and exits 2)."""

from __future__ import annotations

import importlib

from espl_jax.cli import run_main


def _run(module: str) -> int:
    return run_main(importlib.import_module(f"espl_jax.{module}").main)


def train() -> int:
    return _run("train")


def evaluate() -> int:
    return _run("evaluate")


def export() -> int:
    return _run("export")


def analyze() -> int:
    return _run("analyze")
