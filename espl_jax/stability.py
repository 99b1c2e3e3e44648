"""Local stability of a formula in closed loop (the math of ``python -m espl_jax.analyze``,
used by it and by the hall of fame).

The paper checks its CartPole formula by hand (App. "Theoretical Analysis for Cartpole"): linearise
the dynamics under ``a = 17.17 θ + 1.2 θ̇`` at the upright equilibrium and read the eigenvalues
(Hartman–Grobman). This module does that for any exported formula and every env with an
equilibrium, on the env's own JAX step rather than on hand-derived equations:

    f(x) = state after ``env.step(state(x), tanh(formula(obs(x))))``

is the discrete-time closed-loop state map (the env scales the tanh-squashed action to its bounds
inside ``step``, exactly as in training and deployment). Its Jacobian ``J`` at the equilibrium
``x*`` (``jax.jacfwd``: forward mode, because MJX's constraint solver is a ``while_loop``, which
reverse mode cannot differentiate) has eigenvalues ``λ``:

- ``|λ| < 1`` for all modes: locally (asymptotically) stable;
- ``|λ| = 1`` within a tolerance: a marginal mode, named by its eigenvector's dominant state;
- any ``|λ| > 1``: unstable.

Continuous-time eigenvalues: for an explicit-Euler env (cartpole: ``x' = x + Δt·g(x)``),
``J = I + Δt·∂g/∂x`` so ``(λ − 1)/Δt`` are exactly the eigenvalues of the ODE's Jacobian, the
numbers the paper reports; for other integrators ``log(λ)/Δt`` (principal branch), the rates of
the sampled linear system. ``‖f(x*) − x*‖`` says whether the equilibrium is a fixed point under the
learned policy at all (a constant offset in the formula pushes the system off it).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp

from espl_jax import expression as ex
from espl_jax.config import UserError

# |λ| within this of 1 is a marginal mode. The Jacobian is computed in float32 (the envs' dtype),
# whose round-off in J is ~1e-7; 1e-4 is then safely above noise and, at Δt = 0.02 s, separates
# rates slower than 0.005 /s from truly decaying or growing ones.
DEFAULT_TOLERANCE = 1e-4
# A Jacobian that comes out non-finite at x* exactly (autodiff of |v| = sqrt(v·v) at v = 0 in the
# swing-up's link damping gives 0·inf) is taken as the mean of the Jacobians at x* ± this nudge:
# the map is C¹ there, and the mean cancels the first-order change.
NUDGE = 1e-5
# ‖f(x*) − x*‖ below this counts as a fixed point (float32 rounding of one env step).
FIXED_POINT_TOLERANCE = 1e-5


# --------------------------------------------------------------------------------------------
# Equilibria


@dataclass(frozen=True)
class Equilibrium:
    """How one env is linearised: its state vector, the equilibrium and the time model.

    Attributes:
        names: one name per entry of the state vector.
        point: the equilibrium x*, float (n,).
        dt: seconds per env step.
        explicit_euler: whether ``step`` is explicit Euler (then (λ − 1)/Δt is exact).
        description: the equilibrium in words.
        state: state vector (n,) -> env state (step counter 0).
        vector: env state -> state vector (n,).
        obs: env state -> observation (obs_dim,).
    """

    names: tuple[str, ...]
    point: np.ndarray
    dt: float
    explicit_euler: bool
    description: str
    state: Callable[[jax.Array], Any]
    vector: Callable[[Any], jax.Array]
    obs: Callable[[Any], jax.Array]


# envs with an equilibrium, and where it is
EQUILIBRIA = {
    "cartpole": "x = x_dot = theta = theta_dot = 0 (pole upright, cart at rest at the centre)",
    "pendulum": "theta = theta_dot = 0 (upright, at rest)",
    "inverted_pendulum_swingup": "qpos = qvel = 0 (pole upright, cart at rest at the centre)",
    "inverted_double_pendulum": "qpos = qvel = 0 (both poles upright, cart at rest)",
}


def has_equilibrium(env_name: str) -> bool:
    """Whether ``closed_loop`` can analyse formulas of ``env_name`` (it is in ``EQUILIBRIA``)."""
    return env_name in EQUILIBRIA


def check_has_equilibrium(env_name: str) -> None:
    """Raises a UserError for an env without a defined equilibrium."""
    if not has_equilibrium(env_name):
        raise UserError(
            f"no equilibrium defined for {env_name}; analyze knows {', '.join(EQUILIBRIA)}"
        )


def equilibrium(env: Any, params: Any) -> Equilibrium:
    """The equilibrium and state-vector adapters of ``env`` (one of ``EQUILIBRIA``).

    The observation is the env's own (its ``_obs``), so the policy sees what it sees in training.
    """
    check_has_equilibrium(env.name)
    t0 = jnp.zeros((), jnp.int32)
    if env.name == "cartpole":
        from espl_jax.envs.classic import CartPoleState

        return Equilibrium(
            names=("x", "x_dot", "theta", "theta_dot"),
            point=np.zeros(4),
            dt=float(params.tau),
            explicit_euler=True,
            description=EQUILIBRIA[env.name],
            state=lambda v: CartPoleState(x=v[0], x_dot=v[1], theta=v[2], theta_dot=v[3], t=t0),
            vector=lambda s: jnp.stack([s.x, s.x_dot, s.theta, s.theta_dot]),
            obs=env._obs,
        )
    if env.name == "pendulum":
        from espl_jax.envs.classic import PendulumState

        return Equilibrium(
            names=("theta", "theta_dot"),
            point=np.zeros(2),
            dt=float(params.dt),
            explicit_euler=False,  # semi-implicit Euler: θ advances with the new velocity
            description=EQUILIBRIA[env.name],
            state=lambda v: PendulumState(theta=v[0], theta_dot=v[1], t=t0),
            vector=lambda s: jnp.stack([s.theta, s.theta_dot]),
            obs=env._obs,
        )
    # MJX pendula: the state is (qpos, qvel); every joint is a slider or a hinge (nq == nv)
    import mujoco

    from espl_jax.envs.mjx import MjxState

    model = env.model
    nq, nv = int(model.nq), int(model.nv)
    joints = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
    return Equilibrium(
        names=tuple(f"qpos[{j}]" for j in joints) + tuple(f"qvel[{j}]" for j in joints),
        point=np.zeros(nq + nv),
        dt=float(env.dt),
        explicit_euler=False,
        description=EQUILIBRIA[env.name],
        state=lambda v: MjxState(data=env.data_from_qpos_qvel(v[:nq], v[nq:], params), t=t0),
        vector=lambda s: jnp.concatenate([s.data.qpos, s.data.qvel]),
        obs=lambda s: env._obs(s.data),
    )


# --------------------------------------------------------------------------------------------
# The analysis


def closed_loop(
    env: Any,
    exprs: Sequence[sp.Expr],
    params: Any = None,
    tolerance: float = DEFAULT_TOLERANCE,
) -> dict[str, Any]:
    """Linearises env step ∘ tanh ∘ formula at the env's equilibrium and classifies its modes.

    Args:
        env: a JAX env from ``envs.make`` with an entry in ``EQUILIBRIA``.
        exprs: ``env.action_dim`` pre-tanh expressions (``expression.network_expressions``, or
            written by hand) in the symbols x0 … x{obs_dim−1} of the env's observation.
        params: env parameters (default ``env.default_params``).
        tolerance: |λ| within this of 1 is a marginal mode.

    Returns:
        A JSON-serialisable dict: ``verdict`` ("stable", "marginal" or "unstable") and
        ``summary``; ``spectral_radius``, the largest |λ|; ``modes`` (one per eigenvalue,
        largest |λ| first: ``discrete`` λ and ``continuous`` μ as [re, im], ``abs`` |λ|,
        ``kind``, ``dominant_state``); ``jacobian`` (n, n); ``continuous_time`` (how μ was
        obtained); ``fixed_point_residual`` ‖f(x*) − x*‖ with ``fixed_point_offset``
        f(x*) − x* (n,), ``pre_tanh_at_equilibrium`` and ``action_at_equilibrium``
        (action_dim,), normalised to [-1, 1]; plus ``env``, ``equilibrium``, ``state_names``,
        ``dt``, ``tolerance``, ``jacobian_at``.

    Raises:
        UserError: the env has no equilibrium defined.
        ValueError: the number of expressions is not the env's action dimension.
    """
    if len(exprs) != env.action_dim:
        raise ValueError(f"{env.name} has {env.action_dim} actions, got {len(exprs)} expressions")
    eq = equilibrium(env, env.default_params if params is None else params)
    observe, advance = _linearisation(env) if params is None else _linearise(env, params)
    pre_tanh = ex.to_jax(exprs)

    # J at x*, x* + δ and x* − δ. The chain rule through the policy,
    #     J = ∂f/∂x + ∂f/∂a · diag(1 − tanh²(u)) · ∂u/∂o · ∂o/∂x,
    # keeps the formula out of the compiled env parts: those compile once per env (MJX's step
    # with its Jacobian takes ~1 min on CPU), and each formula costs milliseconds after that
    # (the hall of fame analyses every chunk's formula).
    point = jnp.asarray(eq.point, jnp.float32)
    points = jnp.stack([point, point + NUDGE, point - NUDGE])
    obs, obs_jac = observe(points)  # [3, obs_dim], [3, obs_dim, n]
    pre = jnp.asarray(pre_tanh(obs)).reshape(3, env.action_dim)
    pre_jac = jax.vmap(jax.jacfwd(pre_tanh))(obs).reshape(3, env.action_dim, -1)
    images, step_jac, action_jac = advance(points, jnp.tanh(pre))  # [3, n], [3, n, n], [3, n, a]
    pre64 = np.asarray(pre, np.float64)
    policy_jac = (1 - np.tanh(pre64) ** 2)[..., None] * np.asarray(pre_jac, np.float64)
    jacobians = np.asarray(step_jac, np.float64) + np.asarray(action_jac, np.float64) @ (
        policy_jac @ np.asarray(obs_jac, np.float64)
    )
    jac, jacobian_at = jacobians[0], "equilibrium"
    if not np.all(np.isfinite(jac)):
        jac = (jacobians[1] + jacobians[2]) / 2
        jacobian_at = f"mean of x* ± {NUDGE:g} (autodiff is not finite at x* exactly)"
    if not np.all(np.isfinite(jac)):
        raise ValueError(f"the closed-loop Jacobian of {env.name} is not finite: {jac}")

    offset = np.asarray(images[0], np.float64) - eq.point
    residual = float(np.linalg.norm(offset))
    modes = _modes(jac, eq, tolerance)
    verdict, summary = _verdict(modes, tolerance)
    pre0 = pre64[0]
    if residual > FIXED_POINT_TOLERANCE:
        summary += (
            f"; x* is not a fixed point under this policy (‖f(x*) − x*‖ = {residual:.3g}, "
            f"pre-tanh a(x*) = {np.round(pre0, 4).tolist()}), so the linearisation describes "
            "motion near x*, not settling at it"
        )
    return {
        "env": env.name,
        "equilibrium": eq.description,
        "state_names": list(eq.names),
        "dt": eq.dt,
        "tolerance": tolerance,
        "verdict": verdict,
        "spectral_radius": modes[0]["abs"],
        "summary": summary,
        "continuous_time": (
            "(λ − 1)/Δt: exact, the env is explicit Euler (J = I + Δt ∂g/∂x)"
            if eq.explicit_euler
            else "log(λ)/Δt (principal branch): rates of the sampled linear system"
        ),
        "modes": modes,
        "fixed_point_residual": residual,
        "fixed_point_offset": offset.tolist(),
        "pre_tanh_at_equilibrium": pre0.tolist(),
        "action_at_equilibrium": np.tanh(pre0).tolist(),
        "jacobian": jac.tolist(),
        "jacobian_at": jacobian_at,
    }


def _linearise(env: Any, params: Any) -> tuple[Callable, Callable]:
    """The env's parts of the closed-loop Jacobian, compiled, at a batch of state vectors:

    - ``observe(x [B, n]) -> (o [B, obs_dim], ∂o/∂x [B, obs_dim, n])``;
    - ``advance(x [B, n], a [B, action_dim]) -> (f [B, n], ∂f/∂x [B, n, n], ∂f/∂a [B, n, a])``,
      ``f`` the state after one ``env.step`` with the tanh-squashed action ``a``.

    Forward mode (``jax.jacfwd``): MJX's constraint solver is a ``while_loop``.
    """
    eq = equilibrium(env, params)

    def obs(x):
        return eq.obs(eq.state(x))

    def step(x, a):
        _, s_next, *_ = env.step(jax.random.key(0), eq.state(x), a, params)
        return eq.vector(s_next)

    def observe(x):
        return obs(x), jax.jacfwd(obs)(x)

    def advance(x, a):
        return step(x, a), *jax.jacfwd(step, argnums=(0, 1))(x, a)

    return jax.jit(jax.vmap(observe)), jax.jit(jax.vmap(advance))


@functools.lru_cache(maxsize=8)
def _linearisation(env: Any) -> tuple[Callable, Callable]:
    """``_linearise`` at the env's default params, kept per env instance (compiled once)."""
    return _linearise(env, env.default_params)


def _modes(jac: np.ndarray, eq: Equilibrium, tolerance: float) -> list[dict[str, Any]]:
    lam, vectors = np.linalg.eig(jac)
    order = np.argsort(-np.abs(lam), kind="stable")
    modes = []
    for i in order:
        size = abs(lam[i])
        kind = (
            "unstable" if size > 1 + tolerance else "stable" if size < 1 - tolerance else "marginal"
        )
        if eq.explicit_euler:
            mu = (lam[i] - 1.0) / eq.dt
        else:
            mu = np.log(complex(lam[i])) / eq.dt if size > 0 else None
        modes.append(
            {
                "discrete": [float(lam[i].real), float(lam[i].imag)],
                "abs": float(size),
                "continuous": None if mu is None else [float(mu.real), float(mu.imag)],
                "kind": kind,
                "dominant_state": eq.names[int(np.argmax(np.abs(vectors[:, i])))],
            }
        )
    # A repeated marginal eigenvalue with fewer eigenvectors than its multiplicity is a Jordan
    # block: a state offset there does not stay put but grows linearly (the cart drifting at a
    # constant velocity, for the paper's CartPole law).
    marginal = [i for i in order if abs(abs(lam[i]) - 1) <= tolerance]
    if len(marginal) > 1:
        rank = np.linalg.matrix_rank(vectors[:, marginal], tol=1e-6)
        if rank < len(marginal):
            for mode in modes:
                if mode["kind"] == "marginal":
                    mode["jordan_block"] = True
    return modes


def _verdict(modes: list[dict[str, Any]], tolerance: float) -> tuple[str, str]:
    def states(kind):
        return sorted({m["dominant_state"] for m in modes if m["kind"] == kind})

    if states("unstable"):
        return (
            "unstable",
            f"unstable: |λ| > 1 in modes dominated by {', '.join(states('unstable'))}",
        )
    if states("marginal"):
        text = (
            f"marginal: every |λ| ≤ 1, with |λ| = 1 (within {tolerance:g}) in modes dominated by "
            f"{', '.join(states('marginal'))}"
        )
        if any(m.get("jordan_block") for m in modes):
            text += " (a Jordan block: an offset there grows linearly, it is not damped)"
        return "marginal", text
    return "stable", "locally stable: every |λ| < 1"


# --------------------------------------------------------------------------------------------
# Report


def format_report(result: dict[str, Any], formula: str | None = None) -> str:
    """The analysis as readable text: equilibrium, fixed-point check, modes table, verdict."""
    lines = [f"{result['env']}: closed loop at {result['equilibrium']}, Δt = {result['dt']:g} s"]
    if formula:
        lines += [f"  {line}" for line in formula.splitlines()]
    pre = ", ".join(f"{v:.4g}" for v in result["pre_tanh_at_equilibrium"])
    lines.append(
        f"  ‖f(x*) − x*‖ = {result['fixed_point_residual']:.3g}  (pre-tanh action at x*: {pre})"
    )
    lines.append(f"  continuous time: {result['continuous_time']}")
    lines.append(
        f"  {'|λ|':>9}  {'λ (per step)':>24}  {'μ (1/s)':>24}  {'kind':<8}  dominant state"
    )
    for m in result["modes"]:
        mu = "—" if m["continuous"] is None else _complex(*m["continuous"])
        lines.append(
            f"  {m['abs']:9.6f}  {_complex(*m['discrete']):>24}  {mu:>24}  {m['kind']:<8}  "
            f"{m['dominant_state']}"
        )
    if result["jacobian_at"] != "equilibrium":
        lines.append(f"  Jacobian taken as the {result['jacobian_at']}")
    lines.append(f"  spectral radius max |λ| = {result['spectral_radius']:.6f}")
    lines.append(f"  verdict: {result['summary']}")
    return "\n".join(lines)


def _complex(re: float, im: float) -> str:
    return f"{re:.6g}" if abs(im) < 1e-12 else f"{re:.6g} {'+' if im >= 0 else '−'} {abs(im):.6g}j"
