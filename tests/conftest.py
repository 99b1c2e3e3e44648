"""Shared test configs and the JAX compilation cache used by the training and CLI tests."""

from pathlib import Path

import jax
import pytest
from jax.experimental.compilation_cache import compilation_cache

# A tiny training config: small nets, two vmapped seeds, a few iterations. It still needs ~1000
# updates per iteration: the path selector moves p by about the learning rate per update, and
# the formulas should be pruned to ~10–30 paths so that export stays quick. test_training.py and
# test_cli.py use the same dicts so the compilation cache serves both files.
TINY = {
    "env": "cartpole",
    "seeds": 2,
    "iterations": 4,
    "steps_per_iteration": 64,
    "updates_per_iteration": 1000,
    "chunk_iterations": 2,
    "batch_size": 8,
    "critic_hidden": [32, 32],
    "std_hidden": [16],
    "schedule_iterations": 3,
    "progress_eval_episodes": 2,
    "eval_episodes": 2,  # = progress_eval_episodes: one compiled evaluation serves both
    "reference_eval_episodes": 2,
    "buffer_size": 1024,
}
# The neural baseline: no symbolic network, so a handful of updates is enough.
TINY_MLP = {
    **TINY,
    "actor": "mlp",
    "seeds": 1,
    "iterations": 2,
    "updates_per_iteration": 4,
    "mlp_actor_hidden": [16],
}


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory):
    """Persistent compilation cache for this session, in-process and for subprocesses.

    Yields the environment variables that point a subprocess (a CLI run) at the same cache.
    """
    path = tmp_path_factory.getbasetemp() / "jax_cache"
    path.mkdir(exist_ok=True)
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    old = {name: getattr(jax.config, name) for name in names}
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    compilation_cache.reset_cache()
    yield {
        "JAX_COMPILATION_CACHE_DIR": str(path),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
    }
    for name, value in old.items():
        jax.config.update(name, value)
    compilation_cache.reset_cache()


def committed_checkpoints(directory: Path) -> set[int]:
    """The iterations whose orbax checkpoint in ``directory`` was committed (a kill mid-write
    leaves a step folder without ``commit_success.txt``)."""
    if not directory.is_dir():
        return set()
    return {
        int(p.name)
        for p in directory.iterdir()
        if p.name.isdigit() and (p / "commit_success.txt").is_file()
    }
