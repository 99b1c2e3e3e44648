"""Where a meta-RL iteration's time goes, per actor kind: collection vs the SAC updates.

For one task family and each ``--actors`` kind, with the family's shipped config, this times (after
one warm-up call, best of ``--repeats``) the jitted, seed-vmapped pieces of one iteration:

- ``collect``: PEARL's collection (``Trainer.collect_meta``: prior and posterior phases);
- ``updates``: ``--updates`` SAC steps (``Trainer.learn`` without collection), from a buffer filled
  by one warm-up collection, reported per update;
- ``adapt``: the protocol on the test tasks (``Trainer.compiled_adapt``), once.

Compile times are printed beside (the first call minus a timed one). Prints a markdown table::

    python benchmarks/meta_cost.py --env invdoublepend_params --actors symbolic,pearl,hyper

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import time

import jax

from espl_jax import config as config_lib
from espl_jax.trainer import Trainer


def _timed(fn, *args, repeats: int):
    """(first call's seconds, best later call's seconds, last result)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return first, best, out


def measure(env: str, actor: str, updates: int, repeats: int) -> dict:
    # A short initial collection: it only has to put data in the buffers (whose size, and so the
    # cost of sampling them, does not depend on how full they are).
    trainer = Trainer(
        config_lib.resolve(env=env, actor=actor, updates_per_iteration=updates, initial_steps=200)
    )
    state = trainer.init_seeds()
    state = jax.block_until_ready(trainer.compiled_warmup()(state))
    key = jax.random.PRNGKey(1)
    keys = key[None]

    collect = trainer.over_seeds(lambda s, k: trainer.collect_meta(s, k)[0])
    c_first, c_best, state = _timed(collect, state, keys, repeats=repeats)

    def learn(s, k):
        return trainer.learn(s, {}, k)[0]

    learn = trainer.over_seeds(learn)
    u_first, u_best, _ = _timed(learn, state, keys, repeats=repeats)

    test_params = trainer.tasks[1]
    a_first, a_best, _ = _timed(trainer.compiled_adapt, state, test_params, keys, repeats=1)
    return {
        "actor": actor,
        "collect_s": c_best,
        "collect_compile_s": c_first - c_best,
        "update_ms": 1000 * u_best / updates,
        "updates_compile_s": u_first - u_best,
        "adapt_s": a_best,
        "adapt_compile_s": a_first - a_best,
        "steps_per_iteration": trainer.steps_per_iteration,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole_fl_ood")
    parser.add_argument("--actors", default="symbolic,pearl,hyper")
    parser.add_argument("--updates", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    rows = [measure(args.env, a, args.updates, args.repeats) for a in args.actors.split(",")]
    print(f"\n{args.env}, {args.updates} updates per timed call, best of {args.repeats}\n")
    print(
        "| actor | collection / iteration (s) | ms / update | protocol on the test tasks (s) "
        "| compile: collect, updates, protocol (s) |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['actor']} | {r['collect_s']:.2f} ({r['steps_per_iteration']} env steps) "
            f"| {r['update_ms']:.1f} | {r['adapt_s']:.1f} | {r['collect_compile_s']:.0f}, "
            f"{r['updates_compile_s']:.0f}, {r['adapt_compile_s']:.0f} |"
        )


if __name__ == "__main__":
    main()
