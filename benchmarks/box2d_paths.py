"""The two ways of stepping a Box2D env (gymnasium on the host) in training, timed side by side.

- ``host``: the host driver (``espl_jax.host.HostCollector``): a Python loop over the env steps of
  a gymnasium ``SyncVectorEnv`` (one env per seed) that calls the jitted, seed-vmapped
  exploration policy once per step;
- ``callback``: the one rollout path (``Trainer.collect_single`` inside the jitted chunk): the env
  is a functional ``Environment`` (``envs/box2d.py``) whose step is one ``jax.pure_callback`` per
  env step for the whole seed batch, inside the compiled ``lax.scan``.

For each ``--seeds`` count, with the shipped config of ``--env`` (only ``seeds`` changed), it times
(after one warm-up call, best of ``--repeats``, the two paths interleaved so that both see the same
background load) one iteration's collection (``steps_per_iteration`` env steps per seed; also the
part of it spent inside the gymnasium env class's ``step``/``reset``, which depends on the episodes
each path happens to play, and the rest, the path's own overhead) and, with
``--iteration`` (for the ``--iteration-seeds`` counts), one whole iteration (collection and
``updates_per_iteration`` SAC updates; the updates are the same jitted code in both). The load
average is recorded beside each row, since other jobs may share the cores::

    python benchmarks/box2d_paths.py --env lunarlander --seeds 1,2,3 --iteration 2 \
        --json results/box2d_paths_lunarlander.json

For a task family (``--env lunarlander_params``) it times one prior collection phase
(``tasks_per_iteration`` tasks × ``prior_steps`` steps per seed) and PEARL's protocol on the test
tasks instead (``host_meta.HostMetaCollector.phase`` and ``HostAdapter`` against
``Trainer._meta_phase`` and ``Trainer.compiled_adapt``).

Not part of the test suite (CI never runs ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import numpy as np
from env_throughput import write_result

from espl_jax import config as config_lib
from espl_jax import envs
from espl_jax.learner import Trainer


class CallbackTrainer(Trainer):
    """The trainer with the Box2D env on the one rollout path (not the host driver)."""

    on_host = False


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - started)
    return best


class EnvClock:
    """Seconds spent inside the gymnasium env class's own ``step`` and ``reset`` (patched on the
    class, so both paths are timed alike): the rest of a collection is the path's overhead."""

    def __init__(self, env_class):
        self.seconds = 0.0
        for name in ("step", "reset"):
            original = getattr(env_class, name)

            def timed(obj, *args, _original=original, **kwargs):
                started = time.perf_counter()
                try:
                    return _original(obj, *args, **kwargs)
                finally:
                    self.seconds += time.perf_counter() - started

            setattr(env_class, name, timed)


CLOCKS: dict[str, EnvClock] = {}


def measure(env: str, seeds: int, repeats: int, iteration: bool) -> list[dict]:
    cfg = config_lib.resolve(env=env, seeds=seeds)
    host_trainer, cb_trainer = Trainer(cfg), CallbackTrainer(cfg)
    from espl_jax import host

    clock = CLOCKS.setdefault(env, EnvClock(type(host_trainer.env.make_env().unwrapped)))
    collector = host.HostCollector(host_trainer)
    host_state = host_trainer.init_seeds()

    def host_collect():
        key, actor, mask, step_keys, _ = collector._begin(
            host_state.key, host_state.actor, host_state.iteration
        )
        return collector.collect(host_state.replace(actor=actor), mask, step_keys)[0]

    def one_seed_collect(s):
        key, mask, k_collect, _ = cb_trainer.start_iteration(s.key, s.actor)
        return cb_trainer.collect_single(s.replace(key=key), mask, k_collect)

    cb_collect_fn = cb_trainer.over_seeds(one_seed_collect)
    cb_state = {"state": cb_trainer.init_seeds()}

    def cb_collect():  # the episodes go on across calls, as the host path's do
        cb_state["state"], metrics = cb_collect_fn(cb_state["state"])
        return metrics

    timings: dict[str, dict[str, float]] = {"host": {}, "callback": {}}
    loads: dict[str, list[float]] = {"host": [], "callback": []}
    for name, fn in (("host", host_collect), ("callback", cb_collect)):
        started = time.perf_counter()
        jax.block_until_ready(fn())
        timings[name]["collect_first_s"] = time.perf_counter() - started
    times: dict[str, list[float]] = {"host": [], "callback": []}
    env_times: dict[str, list[float]] = {"host": [], "callback": []}
    for _ in range(repeats):
        for name, fn in (("host", host_collect), ("callback", cb_collect)):
            loads[name].append(os.getloadavg()[0])
            clock.seconds = 0.0
            times[name].append(_best(fn, 1))
            env_times[name].append(clock.seconds)
    for name, ts in times.items():
        timings[name]["collect_s"] = min(ts)
        timings[name]["collect_median_s"] = float(np.median(ts))
        overhead = np.asarray(ts) - np.asarray(env_times[name])
        timings[name]["env_median_s"] = float(np.median(env_times[name]))
        timings[name]["overhead_median_s"] = float(np.median(overhead))

    if iteration:
        chunk = cb_trainer.compiled_chunk(1)
        states = {"host": host_state, "callback": cb_state["state"]}

        def host_iteration():
            states["host"], metrics = collector.iteration(states["host"])
            return metrics

        def cb_iteration():
            states["callback"], metrics = chunk(states["callback"])
            return metrics

        fns = (("host", host_iteration), ("callback", cb_iteration))
        for name, fn in fns:
            started = time.perf_counter()
            jax.block_until_ready(fn())
            timings[name]["iteration_first_s"] = time.perf_counter() - started
        times = {"host": [], "callback": []}
        for _ in range(iteration):
            for name, fn in fns:
                loads[name].append(os.getloadavg()[0])
                times[name].append(_best(fn, 1))
        for name, ts in times.items():
            timings[name]["iteration_s"] = min(ts)
            timings[name]["iteration_median_s"] = float(np.median(ts))
    collector.close()

    steps = cfg.steps_per_iteration * seeds
    rows = []
    for name in ("host", "callback"):
        t = timings[name]
        rows.append(
            {
                "env": env,
                "path": name,
                "seeds": seeds,
                "env_steps": steps,
                "collect_s": t["collect_s"],
                "collect_median_s": t["collect_median_s"],
                "env_steps_per_s": steps / t["collect_s"],
                "env_steps_per_s_median": steps / t["collect_median_s"],
                # of a collection (median): inside the gymnasium env class, and the rest
                "env_class_median_s": t["env_median_s"],
                "overhead_median_s": t["overhead_median_s"],
                "overhead_us_per_step": t["overhead_median_s"] / cfg.steps_per_iteration * 1e6,
                "collect_first_s": t["collect_first_s"],
                "iteration_s": t.get("iteration_s"),
                "iteration_median_s": t.get("iteration_median_s"),
                "iteration_first_s": t.get("iteration_first_s"),
                "updates_per_iteration": cfg.updates_per_iteration,
                "load_1min": loads[name],
            }
        )
    return rows


def measure_family(env: str, seeds: int, repeats: int) -> list[dict]:
    """A task family (lunarlander_params): one prior collection phase (``prior_steps`` steps on
    ``tasks_per_iteration`` tasks per seed) and PEARL's protocol on the test tasks, both paths."""
    cfg = config_lib.resolve(env=env, seeds=seeds)
    host_trainer, cb_trainer = Trainer(cfg), CallbackTrainer(cfg)
    from espl_jax.host_meta import HostAdapter, HostMetaCollector

    clock = CLOCKS.setdefault(env, EnvClock(type(host_trainer.env.make_env().unwrapped)))
    collector = HostMetaCollector(host_trainer)
    host_state, cb_state = host_trainer.init_seeds(), cb_trainer.init_seeds()
    slots, steps = cb_trainer.rollout_slots, cfg.prior_steps
    tasks = np.tile(np.arange(slots), (seeds, 1))
    keys = jax.vmap(jax.random.fold_in, (0, None))(cb_state.key, 7)

    def cb_phase_one(s, t, k):
        return cb_trainer._meta_phase(s, t, k, steps, posterior=False, to_encoder=False)[2]

    cb_phase_fn = cb_trainer.over_seeds(cb_phase_one)
    test = cb_trainer.tasks[1]
    adapter = HostAdapter(host_trainer, test)
    fns = {
        "phase": {
            "host": lambda: collector.phase(host_state, tasks, keys, steps, False)[1],
            "callback": lambda: cb_phase_fn(cb_state, tasks, keys),
        },
        "protocol": {
            "host": lambda: adapter(host_state, keys).final_return,
            "callback": lambda: cb_trainer.compiled_adapt(cb_state, test, keys).final_return,
        },
    }
    rows = []
    for what, by_path in fns.items():
        for fn in by_path.values():
            jax.block_until_ready(fn())  # compile
        times: dict[str, list[float]] = {"host": [], "callback": []}
        env_times: dict[str, list[float]] = {"host": [], "callback": []}
        loads: dict[str, list[float]] = {"host": [], "callback": []}
        for _ in range(repeats):
            for name, fn in by_path.items():
                loads[name].append(os.getloadavg()[0])
                clock.seconds = 0.0
                times[name].append(_best(fn, 1))
                env_times[name].append(clock.seconds)
        for name in by_path:
            overhead = np.asarray(times[name]) - np.asarray(env_times[name])
            rows.append(
                {
                    "env": env,
                    "what": what,
                    "path": name,
                    "seeds": seeds,
                    "best_s": min(times[name]),
                    "median_s": float(np.median(times[name])),
                    "env_class_median_s": float(np.median(env_times[name])),
                    "overhead_median_s": float(np.median(overhead)),
                    "load_1min": loads[name],
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="lunarlander")
    parser.add_argument("--seeds", default="1,2,3", help="comma-separated seed counts")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--iteration", type=int, default=0, help="also time whole iterations (this many repeats)"
    )
    parser.add_argument(
        "--iteration-seeds", default="2", help="the seed counts whose iterations are timed"
    )
    parser.add_argument("--json", help="also write the rows, command and machine here")
    args = parser.parse_args(argv)
    if envs.is_family(args.env):
        rows = []
        for s in (int(x) for x in args.seeds.split(",")):
            rows += measure_family(args.env, s, args.repeats)
        print(f"\n{args.env}: best / median of {args.repeats}\n")
        print("| what | path | seeds | time (s) | in the env class (s) | overhead (s) | load |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            load = ", ".join(f"{x:.1f}" for x in r["load_1min"])
            print(
                f"| {r['what']} | {r['path']} | {r['seeds']} | {r['best_s']:.2f} / "
                f"{r['median_s']:.2f} | {r['env_class_median_s']:.2f} "
                f"| {r['overhead_median_s']:.2f} | {load} |"
            )
        if args.json:
            write_result(args.json, rows, argv, script="benchmarks/box2d_paths.py")
        return
    rows = []
    timed = {int(x) for x in args.iteration_seeds.split(",")}
    for s in (int(x) for x in args.seeds.split(",")):
        rows += measure(args.env, s, args.repeats, args.iteration if s in timed else 0)
    print(f"\n{args.env}: best / median of {args.repeats} (collection), {args.iteration} "
          "(iteration)\n")  # fmt: skip
    print(
        "| path | seeds | collection (s) | env steps/s | in the env class (s) | overhead per step "
        "(us) | iteration (s) | load (1 min) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        it = "-"
        if r["iteration_s"] is not None:
            it = f"{r['iteration_s']:.2f} / {r['iteration_median_s']:.2f}"
        load = ", ".join(f"{x:.1f}" for x in r["load_1min"])
        print(
            f"| {r['path']} | {r['seeds']} | {r['collect_s']:.2f} / {r['collect_median_s']:.2f} "
            f"| {r['env_steps_per_s']:.0f} / {r['env_steps_per_s_median']:.0f} "
            f"| {r['env_class_median_s']:.2f} | {r['overhead_us_per_step']:.0f} | {it} | {load} |"
        )
    if args.json:
        write_result(args.json, rows, argv, script="benchmarks/box2d_paths.py")


if __name__ == "__main__":
    main()
