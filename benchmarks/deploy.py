"""Deploy-time cost of exported symbolic policies against the neural policies they replace.

ESPL §5.3 ("Deploying efficiency", table "FLOPs (k)/Inference time (ms)") times one control step
of 5000 simulated robots on a CPU. This harness does the same here: per env, a batch of N
observations in, N actions (in the env's units) out, for

* the exported symbolic policy, three ways: policy.py's ``act_batch`` (vectorised numpy, float64,
  imported from the generated source), the generated C's ``act_batch`` compiled with ``cc -O2``
  and called through ctypes (float64), and ``expression.to_jax`` jitted and vmapped over robots
  (float32);
* the neural policies at the paper's sizes, with random weights, deterministic action
  (tanh-Gaussian mean head only), in numpy and in jitted JAX (float32):
  SAC's MLP actor (``Config.mlp_actor_hidden``, 256×2, ReLU), PEARL's policy (MLP 300×3 on
  s ⊕ z, latent z of 5, ReLU), and Hyper's generated network (one hidden layer of 256 ReLU units
  on s). Hyper's hypernetwork maps z to those weights once per task; at deploy time only the
  generated network runs, so only it is timed. All N robots share one task (one z, one
  generated network), as they share one formula.

Symbolic policies: a run's exported formula with ``--run DIR`` (the env from its config.yaml,
the best seed from eval.json), otherwise the paper's Table 3 formulas (``paper_formulas``). A
meta-RL family (``META_FAMILIES``) gets its CSP row from a CSP run's directory (``--run DIR``):
the formula adapted to each test task under PEARL's protocol (``espl_jax.load(DIR).adapted(i)``,
exactly what the run's test_tasks/<i>/policy.py computes) is timed, and the row gives the
median over test tasks (FLOPs and ms, per implementation) with every task's figures beside it.
PEARL's and Hyper's rows are at the paper's sizes on the family's observation and action sizes,
as for the paper's table "FLOPs (k)/Inference time (ms) of different contextual policies".

Per row: FLOPs per robot-step counted analytically (formula operators over the shared DAG, the
code that runs after CSE, + tanh + 2 for the affine action scaling per action; dense layers
2·in·out + one per ReLU) and by XLA's cost analysis of the jitted JAX function (the same figure is
shown on the numpy/C rows of that policy; XLA counts the protections' clamps and selects too,
transcendentals separately). Timing: 3 warm-up calls, then ``--repeats`` repeats of k back-to-back
calls (k chosen so that a repeat lasts >= 5 ms), each call waiting for its result; the row gives
the median over repeats of the per-call time (and the best). Each row also gives the bound it is
up against, measured once at start-up: the float32 matmul rate (numpy and JAX, 2048³) for the
FLOP bound, a large array copy for the memory bound (bytes in + out + weights), the larger of the
two as "bound", and measured time / bound. Symbolic rows also count their sin/cos/exp/log/tanh
calls per robot and price them at per-element costs measured at start-up (``transcendental_ms``):
a formula's time is mostly those and one array pass per operator, not FLOPs at matmul speed.

    python benchmarks/deploy.py                       # every env, 5000 robots, paper formulas
    python benchmarks/deploy.py --envs cartpole hopper --robots 1000 --json deploy.json
    python benchmarks/deploy.py --run runs/cartpole   # a trained run's formula for its env
    python benchmarks/deploy.py --envs hopper_params --run runs/hopper_params-symbolic-...

Output: a table on stdout, then the acceptance summary (the issue's bar: the symbolic policy is
>= 100x faster per step than PEARL's MLP in the same implementation, numpy vs numpy and JAX vs
JAX, judged on median times, best times shown too; it says where and why not) and the wall time.
``--json PATH`` writes a results file (command, commit, machine, date and ``rows``, as every
file under results/), one row per policy and implementation: env, family (bool), method (ESPL,
CSP, SAC, PEARL, Hyper), policy, impl (numpy | c | jax), robots,
flops_per_robot_step (analytic), ms_per_step (median), ms_per_step_best, timing,
xla_flops_per_robot_step, xla_transcendentals_per_robot_step, dtype, bytes_per_step,
compute_bound_ms, memory_bound_ms, bound (compute | memory), time_over_bound,
transcendentals_per_robot_step, transcendental_ms, note, and the machine's measured rates.
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp

from espl_jax import config as config_lib
from espl_jax import envs, reference_eval
from espl_jax import expression as ex
from espl_jax.analyze import exported_expressions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from env_throughput import write_result  # noqa: E402

SINGLE_TASK_ENVS = (
    "cartpole",
    "mountaincar",
    "pendulum",
    "inverted_double_pendulum",
    "inverted_pendulum_swingup",
    "lunarlander",
    "hopper",
    "bipedalwalker",
)
# Meta-RL families -> the single-task env whose observation/action sizes they share.
META_FAMILIES = {
    "cartpole_fl_ood": "cartpole",
    "invdoublepend_params": "inverted_double_pendulum",
    "hopper_params": "hopper",
    "walker2d_params": "walker2d",
    "cheetah_vel_ood": "halfcheetah",
    "lunarlander_params": "lunarlander",
}

SAC_HIDDEN = tuple(config_lib.Config().mlp_actor_hidden)  # the project's MLP actor, 256×2
PEARL_HIDDEN, PEARL_LATENT = (300, 300, 300), 5  # PEARL's policy on s ⊕ z
HYPER_HIDDEN = (256,)  # Hyper's generated one-hidden-layer network on s

MIN_REPEAT_SECONDS = 5e-3
WARMUP_CALLS = 3


# --------------------------------------------------------------------------------------------
# The paper's Table 3 formulas (pre-tanh), with s_i -> x_{i-1}


def _table3(s: Sequence[sp.Symbol]) -> dict[str, list[sp.Expr]]:
    """Table 3 of the paper; ``s[i]`` is the paper's s_i (``s[0]`` unused).

    Products of two non-constant factors, quotients, log and exp are written with the protected
    operators a symbolic network would export them with (PMul, PDiv, PLog, PExp).
    """
    sin, cos = sp.sin, sp.cos
    mul, div, log, exp = ex.PMul, ex.PDiv, ex.PLog, ex.PExp
    return {
        "cartpole": [17.17 * s[3] + 1.2 * s[4]],
        "mountaincar": [8.06 * sin(9.73 * s[2] - 0.18) + 1.26],
        "pendulum": [-mul(4.27 * s[1] + 0.62, 1.9 * s[2] + 0.42 * s[3])],
        "inverted_double_pendulum": [
            12.39 * s[5]
            - 4.48 * sin(0.35 * s[2] + 4.51 * s[5] + 1.23 * s[6] + 7.97 * s[8] + 1.23 * s[9] + 0.08)
            + 0.34
        ],
        "inverted_pendulum_swingup": [
            4.33 * sin(0.17 * s[1] + 0.14 * s[2] + 0.49 * s[3] + 1.76 * s[4] + 0.33 * s[5] - 0.29)
            - 0.65
        ],
        "lunarlander": [
            mul(0.14 - 2.57 * s[4], 0.48 - 0.68 * log(0.5 * s[2])) - 1.44,
            -5.72 * s[3]
            + 4.42 * sin(2.54 * s[5] + 0.03)
            - 0.4
            - div(
                -6.5 * s[6] - 2.13 * cos(0.78 * sin(4.15 * s[1] - 0.05) + 1.98) - 0.98,
                4.71 * s[7] + 0.77,
            ),
        ],
        "hopper": [
            -0.32 * s[12]
            - 1.46 * s[8]
            - 0.83 * s[10]
            - 0.11 * sin(0.26 * s[11] - 5 * s[13] - 2.57 * s[6] + 0.38)
            - 0.92,
            -0.52 * s[12]
            - 3.63 * s[4]
            - 4.58 * s[8]
            + 0.68 * exp(-7.31 * s[11] - 2.5 * s[13])
            + 0.58
            + div(-1.62 * s[6] + 3.89 * s[9] - 4.7, 1.33 - 0.44 * s[13]),
            0.83
            + div(
                1.12 * s[1]
                - 0.47
                - mul(
                    0.1
                    * exp(
                        mul(10.05 * s[1] - 1.76 * s[6] + 1.65, 0.22 * s[13] - 1.88 * s[14] + 1.32)
                    ),
                    5.59 * s[1] - 0.08,
                ),
                0.23
                + 0.21
                * exp(mul(10.05 * s[1] - 1.76 * s[6] + 1.48, 0.22 * s[13] - 1.88 * s[14] + 1.32)),
            ),
        ],
        "bipedalwalker": [
            1.45
            - 2.94
            * cos(
                -0.73 * s[5] + mul(0.06 - 1.06 * s[3], -1.33 * s[12] - 0.28 * s[6] + 0.41) + 1.32
            ),
            7.53 * exp(0.4 * s[1] - 0.13 * s[6] - 0.52 * sin(1.5 * s[7] - 0.24)) - 11.1,
            -div(
                1.07 * s[6] + 0.41,
                4.56 * s[9] + mul(0.2 - 3.01 * s[21], -1.8 * s[1] - 0.03 * s[7] - 0.96) - 0.54,
            )
            + 0.55,
            -0.28 + div(-3.32 * s[12] + 5.64 * s[3] + 0.29 * s[22] - 2.46, 3.26 * s[23] - 1.45),
        ],
    }


# Where the paper's observation (its s_1, s_2, ...) is not ours.
PAPER_OBSERVATION_NOTES = {
    "inverted_double_pendulum": "paper's obs is PyBullet's InvertedDoublePendulumBulletEnv "
    "(9, another order than our gymnasium v5 obs); same size",
    "inverted_pendulum_swingup": "paper prints 0.33*s4 after 1.76*s4; read as s5 (theta_dot)",
    "hopper": "paper's obs is PyBullet's HopperBulletEnv (15; uses s13, s14); our hopper has 11, "
    "so the formula is timed on 15-wide observations",
}


def paper_formulas(env_name: str) -> list[sp.Expr]:
    """The paper's Table 3 formula for a single-task env, in the symbols x0, x1, ...."""
    return _table3([None, *ex.observation_symbols(24)])[env_name]


# --------------------------------------------------------------------------------------------
# Policies under test


@dataclass
class Impl:
    """One timed implementation of a policy: ``call()`` runs one control step for all robots."""

    name: str
    call: Callable[[], Any]
    bytes_per_step: int
    dtype: str
    xla: dict[str, float] | None = None  # XLA cost analysis of this very function (JAX only)


@dataclass
class Policy:
    """A policy of one env, with its analytic FLOPs per robot-step and its implementations."""

    env: str
    name: str
    flops: int
    impls: list[Impl]
    note: str = ""
    transcendentals: dict[str, int] | None = None  # per robot-step, symbolic policies only


def _cost(compiled) -> dict[str, float]:
    """XLA's cost analysis; a dict or a one-element list of dicts depending on the JAX version."""
    cost = compiled.cost_analysis()
    if isinstance(cost, list | tuple):
        cost = cost[0] if cost else {}
    return {k: float(cost.get(k, 0.0)) for k in ("flops", "transcendentals", "bytes accessed")}


def _jax_impl(fn: Callable, args: tuple, bytes_per_step: int) -> Impl:
    """Jit, compile once (for the cost analysis) and call the compiled function."""
    compiled = jax.jit(fn).lower(*args).compile()
    return Impl(
        "jax",
        lambda: jax.block_until_ready(compiled(*args)),
        bytes_per_step,
        "float32",
        _cost(compiled),
    )


def dag_operations(exprs: Sequence[sp.Expr]) -> int:
    """Operators in the expressions, each shared subexpression once (what runs after CSE).

    A k-term sum or product counts k − 1; every function (protected or not) and power counts 1.
    """
    seen: set[sp.Expr] = set()
    count = 0
    stack = list(exprs)
    while stack:
        e = stack.pop()
        if e in seen or e.is_Atom:
            continue
        seen.add(e)
        count += len(e.args) - 1 if (e.is_Add or e.is_Mul) else 1
        stack.extend(e.args)
    return count


TRANSCENDENTALS = ("sin", "cos", "exp", "log", "tanh")
_TRANSCENDENTAL_OF = {
    sp.sin: "sin",
    sp.cos: "cos",
    sp.exp: "exp",
    sp.log: "log",
    ex.PExp: "exp",
    ex.PLog: "log",
    ex.PCond: "exp",  # its sigmoid
}


def transcendental_calls(exprs: Sequence[sp.Expr]) -> dict[str, int]:
    """sin/cos/exp/log calls per robot-step over the shared DAG, plus one tanh per action."""
    counts = dict.fromkeys(TRANSCENDENTALS, 0)
    counts["tanh"] = len(exprs)
    seen: set[sp.Expr] = set()
    stack = list(exprs)
    while stack:
        e = stack.pop()
        if e in seen or e.is_Atom:
            continue
        seen.add(e)
        if e.func in _TRANSCENDENTAL_OF:
            counts[_TRANSCENDENTAL_OF[e.func]] += 1
        stack.extend(e.args)
    return counts


def symbolic_policy(
    env_name: str,
    label: str,
    exprs: list[sp.Expr],
    obs: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    workdir: Path,
    note: str,
) -> Policy:
    """The exported formula as policy.py (numpy), C (ctypes) and JAX (to_jax, vmapped)."""
    n, obs_dim = obs.shape
    action_dim = len(exprs)
    flops = dag_operations(exprs) + 3 * action_dim  # + tanh and the affine scaling per action
    constants = sum(len(e.atoms(sp.Number)) for e in exprs)
    impls = []

    path = workdir / f"{env_name}_policy.py"
    path.write_text(ex.to_python(exprs, obs_dim, low, high))
    module = reference_eval.load_policy(path)
    obs64 = np.ascontiguousarray(obs, np.float64)
    bytes64 = 8 * (n * (obs_dim + action_dim) + constants)
    impls.append(Impl("numpy", lambda: module.act_batch(obs64), bytes64, "float64"))

    if shutil.which("cc") is not None:
        c_path, lib_path = workdir / f"{env_name}_policy.c", workdir / f"{env_name}_policy.so"
        c_path.write_text(ex.to_c(exprs, obs_dim, low, high))
        cmd = ["cc", "-O2", "-shared", "-fPIC", "-o", str(lib_path), str(c_path), "-lm"]
        subprocess.run(cmd, check=True)
        act_batch = ctypes.CDLL(str(lib_path)).act_batch
        double_p = ctypes.POINTER(ctypes.c_double)
        act_batch.argtypes = [double_p, double_p, ctypes.c_int]
        act_batch.restype = None
        out = np.empty((n, action_dim))
        in_p, out_p = obs64.ctypes.data_as(double_p), out.ctypes.data_as(double_p)
        impls.append(Impl("c", lambda: act_batch(in_p, out_p, n), bytes64, "float64"))

    pre_tanh = ex.to_jax(exprs)
    center = jnp.asarray((high + low) / 2, jnp.float32)
    half = jnp.asarray((high - low) / 2, jnp.float32)
    act = jax.vmap(lambda o: center + jnp.tanh(pre_tanh(o)) * half)
    obs32 = jnp.asarray(obs, jnp.float32)
    impls.append(_jax_impl(act, (obs32,), bytes64 // 2))
    return Policy(env_name, label, flops, impls, note, transcendental_calls(exprs))


def _mlp_params(rng: np.random.Generator, sizes: Sequence[int]) -> list[tuple]:
    """Random float32 (W [in, out], b [out]) per dense layer, at the fan-in scale."""
    return [
        (
            (rng.standard_normal((i, o)) / np.sqrt(i)).astype(np.float32),
            (0.1 * rng.standard_normal(o)).astype(np.float32),
        )
        for i, o in zip(sizes[:-1], sizes[1:], strict=True)
    ]


def mlp_policy(
    env_name: str,
    label: str,
    obs: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    hidden: Sequence[int],
    latent: int = 0,
    note: str = "",
) -> Policy:
    """A ReLU MLP mean head on s (⊕ a per-task z of size ``latent``), then tanh and scaling."""
    n, obs_dim = obs.shape
    action_dim = len(low)
    sizes = (obs_dim + latent, *hidden, action_dim)
    rng = np.random.default_rng(len(sizes) * 1000 + obs_dim)
    params = _mlp_params(rng, sizes)
    weights = sum(w.size + b.size for w, b in params)
    flops = sum(2 * i * o for i, o in zip(sizes[:-1], sizes[1:], strict=True))
    flops += sum(hidden) + 3 * action_dim  # ReLUs; tanh and scaling per action
    bytes32 = 4 * (n * (obs_dim + latent + action_dim) + weights)
    center32 = ((high + low) / 2).astype(np.float32)
    half32 = ((high - low) / 2).astype(np.float32)
    obs32 = np.ascontiguousarray(obs, np.float32)
    z = np.broadcast_to(rng.standard_normal(latent).astype(np.float32), (n, latent)).copy()

    def numpy_act():
        h = np.concatenate([obs32, z], axis=1) if latent else obs32
        for w, b in params[:-1]:
            h = np.maximum(h @ w + b, 0.0)
        w, b = params[-1]
        return center32 + np.tanh(h @ w + b) * half32

    def jax_act(p, o, zz):
        h = jnp.concatenate([o, zz], axis=1) if latent else o
        for w, b in p[:-1]:
            h = jax.nn.relu(h @ w + b)
        w, b = p[-1]
        return center32 + jnp.tanh(h @ w + b) * half32

    jax_params = jax.tree.map(jnp.asarray, params)
    impls = [
        Impl("numpy", numpy_act, bytes32, "float32"),
        _jax_impl(jax_act, (jax_params, jnp.asarray(obs32), jnp.asarray(z)), bytes32),
    ]
    return Policy(env_name, label, flops, impls, note)


# --------------------------------------------------------------------------------------------
# Machine limits and timing


def time_call(call: Callable[[], Any], repeats: int) -> tuple[float, float, int]:
    """(median, best) seconds per call over ``repeats`` repeats of k calls, and k."""
    for _ in range(WARMUP_CALLS):
        call()
    k = 1
    while True:
        start = time.perf_counter()
        for _ in range(k):
            call()
        elapsed = time.perf_counter() - start
        if elapsed >= MIN_REPEAT_SECONDS or k >= 4096:
            break
        k *= 2
    samples = [elapsed / k]
    for _ in range(repeats - 1):
        start = time.perf_counter()
        for _ in range(k):
            call()
        samples.append((time.perf_counter() - start) / k)
    return float(np.median(samples)), float(np.min(samples)), k


def machine_limits(repeats: int = 3) -> dict[str, float]:
    """float32 matmul FLOP/s (numpy, JAX), copy bandwidth (B/s) and per-call floors (s)."""
    size = 2048
    rng = np.random.default_rng(0)
    a = rng.standard_normal((size, size), dtype=np.float32)
    b = rng.standard_normal((size, size), dtype=np.float32)
    flops = 2.0 * size**3
    numpy_s = min(_seconds(lambda: a @ b) for _ in range(repeats))
    ja, jb = jnp.asarray(a), jnp.asarray(b)
    matmul = jax.jit(jnp.matmul)
    jax.block_until_ready(matmul(ja, jb))
    jax_s = min(_seconds(lambda: jax.block_until_ready(matmul(ja, jb))) for _ in range(repeats))
    src = np.ones(64 * 2**20, np.float32)  # 256 MiB
    dst = np.empty_like(src)
    copy_s = min(_seconds(lambda: np.copyto(dst, src)) for _ in range(repeats + 2))
    return {
        "numpy_matmul_flops_per_s": flops / numpy_s,
        "jax_matmul_flops_per_s": flops / jax_s,
        "copy_bytes_per_s": 2 * src.nbytes / copy_s,  # read + write
    }


def _seconds(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def transcendental_costs(robots: int, repeats: int) -> dict[str, dict[str, float]]:
    """Seconds per element of sin, cos, exp, log, tanh over N values: numpy float64 (policy.py's
    dtype) and jitted JAX float32. Unlike a matmul FLOP (~0.03 ns here), each costs nanoseconds,
    which is what bounds a formula with a few of them per robot."""
    x = np.random.default_rng(1).uniform(0.1, 2.0, robots)
    xj = jnp.asarray(x, jnp.float32)
    costs = {"numpy": {}, "jax": {}}
    for name in TRANSCENDENTALS:
        fn = getattr(np, name)
        costs["numpy"][name] = time_call(lambda fn=fn: fn(x), repeats)[0] / robots
        compiled = jax.jit(getattr(jnp, name)).lower(xj).compile()
        seconds = time_call(lambda c=compiled: jax.block_until_ready(c(xj)), repeats)[0]
        costs["jax"][name] = seconds / robots
    return costs


def call_floors(robots: int, repeats: int) -> dict[str, float]:
    """Per-call cost of doing (almost) nothing on arrays of this size: the overhead floor.

    numpy: one tanh over [N, 1] float64; JAX: a jitted tanh over [N, 1] float32 (dispatch,
    argument handling, wait for the result).
    """
    x = np.ones((robots, 1))
    numpy_floor = time_call(lambda: np.tanh(x), repeats)[0]
    fn = jax.jit(jnp.tanh).lower(jnp.ones((robots, 1), jnp.float32)).compile()
    xj = jnp.ones((robots, 1), jnp.float32)
    jax_floor = time_call(lambda: jax.block_until_ready(fn(xj)), repeats)[0]
    return {"numpy": numpy_floor, "c": 0.0, "jax": jax_floor}


# --------------------------------------------------------------------------------------------
# The benchmark


def env_sizes(name: str) -> tuple[int, np.ndarray, np.ndarray]:
    """(obs_dim, action_low, action_high) from ``envs.make``."""
    env = envs.make(name)
    return env.obs_dim, np.asarray(env.action_low, float), np.asarray(env.action_high, float)


def adapted_formulas(run_dir: Path) -> list[tuple[int, list[sp.Expr]]]:
    """(test task, CSP's protected expressions adapted to it) for every test task of a CSP run,
    rebuilt from its checkpoint and eval.json's z (``espl_jax.api.Run.adapted``)."""
    import espl_jax

    run = espl_jax.load(run_dir)
    tasks = run.eval.get("test", {}).get("per_task", [])
    return [(i, list(run.adapted(i).expressions)) for i in range(len(tasks))]


def method_of(policy_name: str) -> str:
    """ESPL, CSP, SAC, PEARL or Hyper: the policy column of the paper's tables."""
    return policy_name.split()[0]


def median_over_tasks(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (env, policy, impl) where a policy was timed once per test task: the task at
    the median time (lower median) stands for them, with every task's FLOPs and ms beside it."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["env"], r["policy"], r["impl"]), []).append(r)
    out = []
    for group in groups.values():
        if len(group) == 1:
            out.append(group[0])
            continue
        ranked = sorted(group, key=lambda r: r["ms_per_step"])
        row = dict(ranked[(len(ranked) - 1) // 2])
        row["tasks"] = len(group)
        row["per_task_flops"] = [r["flops_per_robot_step"] for r in group]
        row["per_task_ms"] = [r["ms_per_step"] for r in group]
        row["note"] = f"median of {len(group)} test tasks ({row['note']})"
        out.append(row)
    return out


def policies_for(
    name: str, robots: int, runs: dict[str, Path], workdir: Path, rng: np.random.Generator
) -> list[Policy]:
    """Every policy row of one env or meta-RL family."""
    family = name in META_FAMILIES
    size_env = META_FAMILIES.get(name, name)
    obs_dim, low, high = env_sizes(size_env)
    policies = []
    sizes_note = f"sizes of {size_env}" if family else ""

    exprs, label, note = None, "", ""
    if family and name in runs:
        for task, task_exprs in adapted_formulas(runs[name]):
            obs = rng.standard_normal((robots, obs_dim))
            label, note = f"CSP ({runs[name].name})", f"test task {task}"
            policies.append(symbolic_policy(name, label, task_exprs, obs, low, high, workdir, note))
    elif name in runs:
        exprs = exported_expressions(runs[name])
        label, note = f"ESPL ({runs[name].name})", str(runs[name])
    elif not family:
        exprs, label = paper_formulas(name), "ESPL (paper Table 3)"
        note = PAPER_OBSERVATION_NOTES.get(name, "")
    if exprs is not None:
        used = [int(s.name[1:]) for e in exprs for s in e.free_symbols]
        width = max(obs_dim, 1 + max(used, default=0))  # the paper's hopper reads 15 obs
        obs = rng.standard_normal((robots, width))
        policies.append(symbolic_policy(name, label, exprs, obs, low, high, workdir, note))

    obs = rng.standard_normal((robots, obs_dim))
    if not family:
        sac = "x".join(map(str, SAC_HIDDEN))
        policies.append(mlp_policy(name, f"SAC MLP {sac}", obs, low, high, SAC_HIDDEN))
    pearl_note = sizes_note + ("; " if sizes_note else "") + "z fixed per task"
    policies.append(
        mlp_policy(
            name, "PEARL MLP 300x3 (s+z5)", obs, low, high, PEARL_HIDDEN, PEARL_LATENT, pearl_note
        )
    )
    hyper_note = (sizes_note + "; " if sizes_note else "") + "generated net only (z -> W once)"
    policies.append(
        mlp_policy(name, "Hyper generated 256", obs, low, high, HYPER_HIDDEN, 0, hyper_note)
    )
    return policies


def measure(
    policy: Policy,
    robots: int,
    repeats: int,
    limits: dict[str, float],
    costs: dict[str, dict[str, float]],
) -> list[dict[str, Any]]:
    """One row per implementation of ``policy``."""
    xla = next((i.xla for i in policy.impls if i.xla), None)
    rows = []
    for impl in policy.impls:
        median, best, k = time_call(impl.call, repeats)
        transcendental_ms = None
        if policy.transcendentals is not None and impl.name in costs:
            per_robot = sum(n * costs[impl.name][f] for f, n in policy.transcendentals.items())
            transcendental_ms = 1e3 * robots * per_robot
        rate = limits[
            "jax_matmul_flops_per_s" if impl.name == "jax" else "numpy_matmul_flops_per_s"
        ]
        compute_s = policy.flops * robots / rate
        memory_s = impl.bytes_per_step / limits["copy_bytes_per_s"]
        bound_s = max(compute_s, memory_s)
        rows.append(
            {
                "env": policy.env,
                "family": policy.env in META_FAMILIES,
                "method": method_of(policy.name),
                "policy": policy.name,
                "impl": impl.name,
                "robots": robots,
                "flops_per_robot_step": policy.flops,
                "ms_per_step": 1e3 * median,
                "ms_per_step_best": 1e3 * best,
                "timing": f"median of {repeats} repeats x {k} calls",
                "xla_flops_per_robot_step": None if xla is None else xla["flops"] / robots,
                "xla_transcendentals_per_robot_step": (
                    None if xla is None else xla["transcendentals"] / robots
                ),
                "dtype": impl.dtype,
                "bytes_per_step": impl.bytes_per_step,
                "compute_bound_ms": 1e3 * compute_s,
                "memory_bound_ms": 1e3 * memory_s,
                "bound": "compute" if compute_s >= memory_s else "memory",
                "time_over_bound": median / bound_s,
                # the formula's sin/cos/exp/log/tanh calls at the measured per-element costs
                "transcendentals_per_robot_step": policy.transcendentals,
                "transcendental_ms": transcendental_ms,
                "note": policy.note,
            }
        )
    return rows


def acceptance(rows: list[dict[str, Any]], floors: dict[str, float]) -> list[str]:
    """Symbolic vs PEARL per env and implementation (numpy vs numpy, JAX vs JAX), by median
    time (the verdict) and by best time; for a shortfall, what the formula's time is made of."""
    lines = []
    for env in dict.fromkeys(r["env"] for r in rows):
        by = {(r["policy"].split()[0], r["impl"]): r for r in rows if r["env"] == env}
        symbolic = [p for p in ("ESPL", "CSP") if (p, "numpy") in by]
        if not symbolic:
            lines.append(f"{env}: no symbolic policy (give a CSP run directory with --run)")
            continue
        for impl in ("numpy", "jax"):
            ours, pearl = by[(symbolic[0], impl)], by[("PEARL", impl)]
            speedup = pearl["ms_per_step"] / ours["ms_per_step"]
            best = pearl["ms_per_step_best"] / ours["ms_per_step_best"]
            verdict = "ok" if speedup >= 100 else "BELOW 100x"
            line = f"{env} [{impl}]: {speedup:,.0f}x (best-time {best:,.0f}x) faster ({verdict})"
            floor_ms = 1e3 * floors[impl]
            if speedup < 100:
                calls = ours["transcendentals_per_robot_step"]
                listed = ", ".join(f"{n} {f}" for f, n in calls.items() if n)
                if ours["ms_per_step"] < 3 * floor_ms:
                    line += (
                        f": {ours['ms_per_step']:.4f} ms is near the per-call floor of a one-op "
                        f"{impl} call ({floor_ms:.4f} ms)"
                    )
                spent, total = ours["transcendental_ms"], ours["ms_per_step"]
                line += (
                    f"; the formula's {ours['flops_per_robot_step']} ops/robot include {listed} "
                    f"per robot ({spent:.3f} ms of its {total:.3f} ms at this machine's {impl} "
                    "per-element costs) and the rest are one array pass each, while PEARL's "
                    f"{pearl['flops_per_robot_step']:,} FLOPs/robot run at matmul speed"
                )
            lines.append(line)
    return lines


def format_table(rows: list[dict[str, Any]]) -> str:
    head = (
        f"{'env':<26} {'policy':<24} {'impl':<5} {'FLOPs/robot':>11} {'XLA':>9} "
        f"{'ms/step':>9} {'best':>9} {'bound ms':>9} {'kind':<7} {'x bound':>8}  note"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        xla = (
            "" if r["xla_flops_per_robot_step"] is None else f"{r['xla_flops_per_robot_step']:.0f}"
        )
        bound = max(r["compute_bound_ms"], r["memory_bound_ms"])
        lines.append(
            f"{r['env']:<26} {r['policy']:<24} {r['impl']:<5} {r['flops_per_robot_step']:>11,} "
            f"{xla:>9} {r['ms_per_step']:>9.4f} {r['ms_per_step_best']:>9.4f} {bound:>9.4f} "
            f"{r['bound']:<7} {r['time_over_bound']:>8.1f}  {r['note']}"
        )
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python benchmarks/deploy.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    known = (*SINGLE_TASK_ENVS, *META_FAMILIES)
    p.add_argument("--robots", type=int, default=5000, help="robots per step, N (default 5000)")
    p.add_argument("--json", help="also write the rows as a JSON list to this path")
    p.add_argument(
        "--run",
        action="append",
        default=[],
        metavar="DIR",
        help="a training run whose exported formula replaces the paper's for its env "
        "(repeatable; env from its config.yaml, best seed from eval.json)",
    )
    p.add_argument(
        "--envs",
        nargs="+",
        choices=known,
        metavar="ENV",
        help=f"envs and meta-RL families to time (default: all of {', '.join(known)})",
    )
    p.add_argument(
        "--repeats", type=int, default=15, help="timed repeats per row; median reported (15)"
    )
    args = p.parse_args(argv)
    if args.robots <= 0 or args.repeats <= 0:
        p.error("--robots and --repeats must be positive")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    start = time.perf_counter()
    runs = {}
    for run_dir in map(Path, args.run):
        if not (run_dir / "config.yaml").is_file():
            sys.exit(f"error: {run_dir} is not a run directory (no config.yaml)")
        run_config = config_lib.load(run_dir / "config.yaml")
        if run_config.env in META_FAMILIES and run_config.actor != "symbolic":
            sys.exit(f"error: {run_dir} is a {run_config.actor} run; --run takes CSP runs")
        runs[run_config.env] = run_dir
    names = list(args.envs or (*SINGLE_TASK_ENVS, *META_FAMILIES))
    names += [env for env in runs if env not in names]

    limits = machine_limits()
    floors = call_floors(args.robots, args.repeats)
    costs = transcendental_costs(args.robots, args.repeats)
    print(
        f"{args.robots} robots; CPUs available: {len(os.sched_getaffinity(0))}; "
        f"jax {jax.__version__} on {jax.devices()[0].platform}, numpy {np.__version__}\n"
        f"float32 matmul (2048^3): numpy {limits['numpy_matmul_flops_per_s'] / 1e9:.1f} GFLOP/s, "
        f"JAX {limits['jax_matmul_flops_per_s'] / 1e9:.1f} GFLOP/s; "
        f"copy bandwidth {limits['copy_bytes_per_s'] / 1e9:.1f} GB/s; "
        f"per-call floor (one tanh over [N, 1]): numpy {1e3 * floors['numpy']:.4f} ms, "
        f"JAX {1e3 * floors['jax']:.4f} ms\n"
        "per-element ns of "
        + ", ".join(
            f"{impl}: " + " ".join(f"{f} {1e9 * c:.2f}" for f, c in costs[impl].items())
            for impl in ("numpy", "jax")
        )
        + "\n"
        f"timing: {WARMUP_CALLS} warm-up calls, then the median (and best) over {args.repeats} "
        f"repeats of k back-to-back calls (each repeat >= {MIN_REPEAT_SECONDS * 1e3:g} ms). "
        "Symbolic: numpy/C float64, JAX float32; MLPs float32. FLOPs/robot: analytic; XLA: "
        "cost analysis of the JAX version (shown on all rows of that policy). Hyper: only the "
        "generated network runs at deploy time (its hypernetwork runs once per task).\n",
        flush=True,
    )
    rows = []
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            for policy in policies_for(name, args.robots, runs, Path(tmp), rng):
                rows += measure(policy, args.robots, args.repeats, limits, costs)
            print(f"  timed {name} ({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    rows = median_over_tasks(rows)
    machine = {**limits, **{f"{k}_call_floor_s": v for k, v in floors.items() if k != "c"}}
    for row in rows:
        row.update(machine)
    print(format_table(rows))
    print("\nacceptance (symbolic >= 100x faster per step than PEARL, same implementation):")
    for line in acceptance(rows, floors):
        print(f"  {line}")
    wall = time.perf_counter() - start
    print(f"\nwall time: {wall:.0f} s")
    if args.json:
        write_result(args.json, rows, argv, script="benchmarks/deploy.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
