"""Bitwise fingerprints of two tiny training runs: the guard of a refactoring that must not change
results (issue 32, deliverable 8).

Trains a tiny single-task config (cartpole, 2 vmapped seeds, 4 iterations) and a tiny meta-RL
config (cartpole_fl_ood, CSP, 3 iterations) end to end with ``espl_jax.run.train`` — training,
hall of fame, final export and evaluation — and prints sha256 fingerprints of

- the final checkpoint's TrainState: ``actor``, ``critic``, ``target_critic``, ``log_alpha``,
  ``encoder``, ``anchor`` and every leaf together (``state``, replay buffers and keys included);
- the end-of-run numbers: eval.json without wall-clock and device fields (``eval``), and the
  exported formulas (expression.txt, and test_tasks/*/expression.txt for CSP).

Run it before a change and after it, on the same machine, and compare (``--check FILE`` does the
comparison against a JSON written by ``--out FILE``). The hashes are bitwise: they hold on one
machine and one set of library versions, not across machines (XLA's CPU code differs with the
CPU's instruction set), so nothing here is committed as a reference.

    python benchmarks/bitwise_params.py --out /tmp/before.json
    ... change the code ...
    python benchmarks/bitwise_params.py --check /tmp/before.json

Run it from the checkout under test (``PYTHONPATH=.`` when espl_jax is installed from another
checkout; the first line printed says which espl_jax ran). On 2 loaded CPU cores the first run
took ~15 min, most of it compiling the CSP chunk; with a persistent compilation cache
(``JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0``) a
run of unchanged programs takes ~5 min. The cache cannot hide a change: a changed program is a
cache miss and is compiled anew.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

from espl_jax import config as config_lib
from espl_jax import run as run_lib

SINGLE = {
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
    "eval_episodes": 2,
    "reference_eval_episodes": 2,
    "buffer_size": 1024,
    "keep_best_formula": True,
}
META = {
    "env": "cartpole_fl_ood",
    "actor": "symbolic",
    "layout": "csp",
    "seeds": 2,
    "iterations": 3,
    "chunk_iterations": 2,
    "updates_per_iteration": 4,
    "meta_batch": 3,
    "batch_size": 8,
    "context_batch": 6,
    "initial_steps": 30,
    "tasks_per_iteration": 2,
    "prior_steps": 20,
    "posterior_steps": 20,
    "task_buffer_size": 200,
    "critic_hidden": [16],
    "std_hidden": [8],
    "encoder_hidden": [16],
    "generator_hidden": [8],
    "latent_dim": 2,
    "eval_steps": 40,
    "eval_runs": 1,
    "schedule_iterations": 2,
}
CONFIGS = {"single": SINGLE, "meta": META}
STATE_PARTS = ("actor", "critic", "target_critic", "log_alpha", "encoder", "anchor")
# eval.json fields that vary from run to run (wall clock) or machine to machine.
VOLATILE = {"wall_seconds_training", "devices", "warnings"}
# eval.json fields measured with the exported policy.py in a reference env (gymnasium, numpy
# CartPole): they follow the policy.py text, which an export change may change on purpose while
# training stays bitwise equal, so they are hashed apart ("eval_policy_py").
POLICY_PY = {"reference_eval", "policy_py_return", "policy_py_mean"}


def tree_hash(tree: Any) -> str:
    """sha256 over every leaf's path, dtype, shape and bytes, in tree order."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if jax.dtypes.issubdtype(getattr(leaf, "dtype", None), jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{jax.tree_util.keystr(path)}|{a.dtype}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _split(record: Any, policy_py: bool) -> Any:
    """``record`` without the volatile fields, and either without (False) or with only (True)
    the policy.py fields (with the paths that lead to them)."""
    if isinstance(record, list):
        return [_split(v, policy_py) for v in record]
    if not isinstance(record, dict):
        return None if policy_py else record
    out = {}
    for k, v in record.items():
        if k in VOLATILE:
            continue
        if k in POLICY_PY:
            if policy_py:
                out[k] = v
        else:
            out[k] = _split(v, policy_py)
    return out


def _digest(record: Any) -> str:
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def fingerprint(name: str, overrides: dict[str, Any], root: Path) -> dict[str, str]:
    config = config_lib.from_mapping(overrides)
    run_dir = root / name
    run_lib.train(config, run_dir, show_progress=False)
    _, state, step = run_lib.load_run(run_dir)
    assert step == config.iterations, step
    state = state.replace(buffer=None, encoder_buffer=None)  # large; covered by "state_all"
    out = {part: tree_hash(getattr(state, part)) for part in STATE_PARTS}
    _, full, _ = run_lib.load_run(run_dir)
    out["state_all"] = tree_hash(full)
    record = json.loads((run_dir / "eval.json").read_text())
    out["eval"] = _digest(_split(record, False))
    out["eval_policy_py"] = _digest(_split(record, True))
    formulas = sorted(run_dir.rglob("expression.txt"))
    text = "".join(f"{p.relative_to(run_dir)}\n{p.read_text()}" for p in formulas)
    out["formulas"] = hashlib.sha256(text.encode()).hexdigest()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, help="write the fingerprints to this JSON file")
    p.add_argument("--check", type=Path, help="compare with fingerprints written by --out")
    p.add_argument("--only", choices=sorted(CONFIGS), help="one of the two configs")
    p.add_argument("--keep", type=Path, help="write the run directories here (default: a temp dir)")
    args = p.parse_args(argv)
    print(f"espl_jax from {Path(run_lib.__file__).parent}", flush=True)
    names = [args.only] if args.only else list(CONFIGS)
    result = {}
    with tempfile.TemporaryDirectory(prefix="espl-bitwise-") as tmp:
        root = args.keep or Path(tmp)
        for name in names:
            result[name] = fingerprint(name, CONFIGS[name], root)
            print(json.dumps({name: result[name]}, indent=1), flush=True)
    if args.out:
        args.out.write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    if args.check:
        reference = json.loads(args.check.read_text())
        diff = [
            f"{name}.{part}"
            for name in names
            for part in reference.get(name, {})
            if reference[name][part] != result[name].get(part)
        ]
        print("bitwise equal" if not diff else f"DIFFERENT: {', '.join(diff)}")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
