"""Env steps per second of brax's own envs, for comparison with ``env_throughput.py`` (MJX).

Same harness as ``env_throughput.py``: one jitted ``lax.scan`` of ``--steps`` steps with uniform
random actions, the env reset (computed every step, selected with ``jnp.where``) when it is done,
batch 1 unbatched, other batches ``vmap``-ed; compile timed apart; one warm-up call, then the
best of ``--repeats`` timed calls. The envs are brax's ``hopper``, ``walker2d`` and
``inverted_double_pendulum`` (brax's ports of the gymnasium tasks, not espl_jax's MJX envs), on
the backend given by ``--backend`` (``generalized``, ``positional``, ``spring`` or ``mjx``)::

    python benchmarks/brax_throughput.py --backend generalized --batch 1,16,256

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from brax import envs as brax_envs
from env_throughput import _fmt_rate, compile_and_time  # same directory: run as a script


def make_run(env, steps: int, batched: bool):
    def step_one(key, state):
        key_action, key_reset = jax.random.split(key)
        action = jax.random.uniform(key_action, (env.action_size,), minval=-1.0, maxval=1.0)
        state = env.step(state, action)
        fresh = env.reset(key_reset)
        done = state.done > 0
        state = jax.tree.map(lambda r, s: jnp.where(done, r, s), fresh, state)
        return state, done

    step = jax.vmap(step_one) if batched else step_one

    def run(key, state):
        def body(carry, key_t):
            state, n_done = carry
            if batched:
                key_t = jax.random.split(key_t, state.done.shape[0])
            state, done = step(key_t, state)
            return (state, n_done + done.sum()), None

        (state, n_done), _ = jax.lax.scan(
            body, (state, jnp.zeros((), jnp.int32)), jax.random.split(key, steps)
        )
        return state, n_done

    return run


def benchmark(name: str, backend: str, batch: int, steps: int, repeats: int) -> dict:
    env = brax_envs.get_environment(name, backend=backend)
    key = jax.random.key(0)
    batched = batch > 1
    if batched:
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(key, batch))
    else:
        state = jax.jit(env.reset)(key)
    compile_s, best, out = compile_and_time(make_run(env, steps, batched), key, (state,), repeats)
    return dict(
        compile_s=compile_s, run_s=best, steps_per_s=batch * steps / best, resets=int(out[1])
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", default="inverted_double_pendulum,hopper,walker2d")
    parser.add_argument("--backend", default="generalized")
    parser.add_argument("--batch", default="1,16,256", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=1000, help="scan length per call")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls (best is kept)")
    args = parser.parse_args(argv)
    print(f"jax {jax.__version__}, brax backend {args.backend}, {args.steps} steps per call\n")
    print("| env | batch | compile (s) | run (s) | env steps/s | resets |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in args.envs.split(","):
        for batch in (int(b) for b in args.batch.split(",")):
            r = benchmark(name.strip(), args.backend, batch, args.steps, args.repeats)
            print(
                f"| {name} | {batch} | {r['compile_s']:.1f} | {r['run_s']:.2f} "
                f"| {_fmt_rate(r['steps_per_s'])} "
                f"| {r['resets']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
