"""Wall time of training chunks at several vmapped seed counts (not run by CI).

    python benchmarks/seeds.py --env cartpole --seeds 1 4 --iterations 10

For each seed count: the compile time of one chunk, then the steady-state time per iteration
(collection + updates) and per SAC update, all seeds in one vmapped computation.
"""

from __future__ import annotations

import argparse
import time

import jax

from espl_jax import config
from espl_jax.trainer import Trainer


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env", default="cartpole")
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 4])
    p.add_argument("--iterations", type=int, default=10, help="iterations per timed chunk")
    args = p.parse_args()
    print(f"| seeds | compile (s) | s / iteration | ms / update (all seeds) | env: {args.env} |")
    print("|---|---|---|---|---|")
    for seeds in args.seeds:
        cfg = config.resolve(args.env, seeds=seeds, chunk_iterations=args.iterations)
        trainer = Trainer(cfg)
        state = trainer.init_seeds()
        chunk = trainer.compiled_chunk(args.iterations)
        started = time.perf_counter()
        state, _ = jax.block_until_ready(chunk(state))
        first = time.perf_counter() - started
        started = time.perf_counter()
        state, _ = jax.block_until_ready(chunk(state))
        steady = time.perf_counter() - started
        per_iteration = steady / args.iterations
        per_update = 1000 * per_iteration / cfg.updates_per_iteration
        print(f"| {seeds} | {first - steady:.1f} | {per_iteration:.2f} | {per_update:.2f} | |")


if __name__ == "__main__":
    main()
