"""Replay a run's iterations from one of its checkpoints and record every update's losses.

A run's metrics.jsonl holds each iteration's *mean* over its updates; a divergence inside one
iteration (e.g. lunarlander_params at iteration 28: critic loss 3e3 → 2e5, KL 55 → 1248) needs
the updates one by one, and the quantities that feed the critic's target. This script restores
the checkpoint at ``--from`` (the run resumes bit for bit from it, so the replay is the run's own
history), runs ``--iterations`` more iterations with the run's config, and writes per update:
critic loss, Q, KL, log π, the actor loss, the encoder's mean |μ_z| and the largest |μ_z|
(meta-RL), the smallest factor variance σ²_n and largest |μ_n| of the context's factors, and the
largest |reward| in the RL batch and in the context::

    python benchmarks/update_trace.py RUN --from 25 --iterations 5 --out trace.json

Any config key can be overridden for the replay (``--set critic_layer_norm=true``) to see
whether a change stops the divergence from the same state; keys that change array shapes
cannot.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from functools import cached_property
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from espl_jax import checkpoint, rundir
from espl_jax import config as config_lib
from espl_jax import run as run_lib
from espl_jax.iteration import Iteration
from espl_jax.learner import Trainer
from espl_jax.sac import SAC, SACConfig


class TracingSAC(SAC):
    """SAC whose update also reports what feeds the critic's target and the encoder."""

    def update(self, state, key, tau, l_min, frozen=None):
        new, metrics = super().update(state, key, tau, l_min, frozen)
        # The same batch and context the update drew (same key split as SAC.update).
        k_batch = jax.random.split(key, 3)[0]
        batch, context = self.tasks.sample_batch(state, k_batch, self.config.batch_size)
        metrics["reward_abs_max"] = jnp.max(jnp.abs(batch.reward))
        if self.encoder is not None:
            mu, _ = jax.vmap(self.encoder.posterior, (None, 0))(state.encoder, context)
            metrics["z_mu_abs_mean"] = jnp.mean(jnp.abs(mu))
            metrics["z_mu_abs_max"] = jnp.max(jnp.abs(mu))
            # The product of Gaussians: one confident factor (small σ²_n) sets the posterior.
            mu_n, var_n = jax.vmap(self.encoder.factors, (None, 0))(state.encoder, context)
            metrics["factor_var_min"] = jnp.min(var_n)
            metrics["factor_mu_abs_max"] = jnp.max(jnp.abs(mu_n))
            metrics["context_reward_abs_max"] = jnp.max(jnp.abs(context.reward))
        return new, metrics


class TracingIteration(Iteration):
    """The run's iteration, with every update's metrics kept instead of their mean."""

    def learn(self, state, collect_metrics, key):
        tau, l_min = self.schedules(state.iteration)
        frozen = self.frozen(state.iteration)
        keys = jax.random.split(key, self.updates_per_iteration)
        state, u_metrics = jax.lax.scan(
            lambda s, k: self.sac.update(s, k, tau, l_min, frozen), state, keys
        )
        u_metrics.pop("batch_l0_ratio")
        return state.replace(iteration=state.iteration + 1), {
            **u_metrics,
            "iteration": state.iteration + 1,
        }


class TracingTrainer(Trainer):
    """The run's trainer, with the tracing SAC and iteration."""

    @cached_property
    def sac(self) -> SAC:
        return TracingSAC(config_lib.view(SACConfig, self.config), self.actor, self.task_set)

    @cached_property
    def iteration(self) -> Iteration:
        return TracingIteration(**vars(super().iteration))


def restore_at(run_dir: Path, trainer: Trainer, step: int):
    """The checkpoint ``step`` of a run (restore_latest reads the newest, so hide the others)."""
    directory = run_dir / rundir.CHECKPOINT_DIR
    steps = sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit())
    if step not in steps:
        raise SystemExit(f"error: {directory} holds checkpoints {steps}, not {step}")
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(directory / str(step), Path(tmp) / str(step))
        template = trainer.init_seeds()
        _, state = checkpoint.restore_latest(tmp, template)
    return trainer.seed_axis.place(state)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--from", dest="start", type=int, required=True, help="checkpoint")
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    config = run_lib.saved_config(args.run)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key] = yaml.safe_load(value)
    config = dataclasses.replace(config, **overrides)
    trainer = TracingTrainer(config)
    state = restore_at(args.run, trainer, args.start)
    run_chunk = run_lib.chunk_runner(trainer)
    rows = []
    for _ in range(args.iterations):
        state, metrics = run_chunk(state, 1)
        m = jax.tree.map(lambda x: np.asarray(x)[:, 0], metrics)  # [seeds, updates]
        it = int(np.asarray(m.pop("iteration")).ravel()[0])
        per_update = {k: np.asarray(v)[0].tolist() for k, v in m.items()}
        rows.append({"iteration": it, **per_update})
        peak = {k: float(np.max(np.abs(v))) for k, v in per_update.items()}
        print(
            f"iteration {it}: " + ", ".join(f"max|{k}| {v:.4g}" for k, v in sorted(peak.items())),
            flush=True,
        )
    args.out.write_text(
        json.dumps(
            {
                "command": "python benchmarks/update_trace.py " + " ".join(sys.argv[1:]),
                "run": str(args.run),
                "from": args.start,
                "overrides": overrides,
                "rows": rows,
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
