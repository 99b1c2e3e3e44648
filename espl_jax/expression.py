"""Host-side export of a trained symbolic network to formulas and deployable code (§3.2, App. A).

One sympy expression per action dimension is built from the deterministic mask (p > 0.5, |w| > 1e-3)
with the operators kept as *protected* sympy functions (``PMul``, ``PDiv``, ``PLog``, ``PExp``,
``PCond``). That protected expression is the single source of truth:

- ``to_python`` / ``to_c`` emit it verbatim (after common-subexpression elimination), with the
  exact protected semantics of :mod:`espl_jax.operators`, so deployed code reproduces the network
  (one observation with ``act``, a batch of robots with ``act_batch``);
- ``to_jax`` turns it back into a jittable, differentiable JAX function built from the operators
  of :mod:`espl_jax.operators` themselves (deployment benchmarks, closed-loop linearisation);
- ``readable`` replaces the protected functions by the plain ones (``a*b``, ``a/b``, ``log``,
  ``exp``) and simplifies with sympy: this is the formula printed for people (``to_text``,
  ``to_latex``) and measured by ``complexity``. It equals the policy wherever no protection is
  active.

Constant subtrees (paths whose inputs are all pruned) fold to numbers as the expression is built.
"""

from __future__ import annotations

import inspect
import math
import operator
import re
from collections.abc import Callable, Sequence
from functools import cache, reduce
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import sympy as sp
from sympy.functions.elementary.trigonometric import TrigonometricFunction

from espl_jax import operators as ops
from espl_jax.envs.base import action_center_half_range, to_env_units
from espl_jax.selector import EXPORT_WEIGHT_THRESHOLD
from espl_jax.symbolic import SymbolicNetwork

if TYPE_CHECKING:
    from espl_jax.learner import Trainer

# Readable expressions longer than this are not passed to sympy.simplify, whose cost grows
# steeply with size (measured on 2 cores: length 5 in 0.4 s, length 116 in ~20 s); they are still
# canonicalised (like terms collected) by sympy. The paper's formulas are all shorter than this.
SIMPLIFY_MAX_LENGTH = 80
# Above this length (counted on the protected tree) the formula stays in protected form: a barely
# pruned network's tree is exponentially large, and sympy's ``replace`` and Add/Mul flattening walk
# the tree, not the shared DAG, so unprotecting it would take hours.
READABLE_MAX_LENGTH = 2000


def _num(x: sp.Expr) -> float | None:
    """The float value of a numeric sympy expression, else None."""
    return float(x) if x.is_Number else None


class PMul(sp.Function):
    """clip(a, ±100) · clip(b, ±100)."""

    nargs = 2

    @classmethod
    def eval(cls, a, b):
        if a.is_zero or b.is_zero:
            return sp.S.Zero
        va, vb = _num(a), _num(b)
        if va is not None and vb is not None:
            bound = ops.MUL_BOUND
            return sp.Float(min(max(va, -bound), bound) * min(max(vb, -bound), bound))
        return None


class PDiv(sp.Function):
    """a / b if b >= 0.01 else 0."""

    nargs = 2

    @classmethod
    def eval(cls, a, b):
        vb = _num(b)
        if vb is not None:
            # A constant denominator decides the branch once and for all.
            return a / b if vb >= ops.DIV_MIN_DENOMINATOR else sp.S.Zero
        if a.is_zero:
            return sp.S.Zero
        return None


class PLog(sp.Function):
    """log(max(x, 0.001))."""

    nargs = 1

    @classmethod
    def eval(cls, x):
        v = _num(x)
        return None if v is None else sp.Float(math.log(max(v, ops.LOG_MIN_ARGUMENT)))


class PExp(sp.Function):
    """exp(clip(x, -10, 4))."""

    nargs = 1

    @classmethod
    def eval(cls, x):
        v = _num(x)
        if v is None:
            return None
        return sp.Float(math.exp(min(max(v, ops.EXP_MIN_ARGUMENT), ops.EXP_MAX_ARGUMENT)))


def _sigmoid(v: float) -> float:
    return 1.0 / (1.0 + math.exp(-v)) if v >= 0 else math.exp(v) / (1.0 + math.exp(v))


class PCond(sp.Function):
    """sigmoid(c)·a + (1 − sigmoid(c))·b."""

    nargs = 3

    @classmethod
    def eval(cls, c, a, b):
        v = _num(c)
        if v is None:
            return a if a == b else None
        gate = sp.Float(_sigmoid(v))
        return gate * a + (1 - gate) * b


def _sin(x):
    return sp.sin(x)


def _cos(x):
    return sp.cos(x)


def _identity(x):
    return x


SYMPY_OPERATORS = {
    "mul": PMul,
    "div": PDiv,
    "log": PLog,
    "exp": PExp,
    "sin": _sin,
    "cos": _cos,
    "identity": _identity,
    "cond": PCond,
}


def observation_symbols(obs_dim: int) -> list[sp.Symbol]:
    """x0 … x{n−1}: the observation variables of exported formulas."""
    return [sp.Symbol(f"x{i}", real=True) for i in range(obs_dim)]


def pruned_weights(
    weights: Sequence[np.ndarray],
    probs: Sequence[np.ndarray] | None,
    weight_threshold: float = EXPORT_WEIGHT_THRESHOLD,
) -> list[np.ndarray]:
    """w · 1[p > 0.5] · 1[|w| > threshold]; with ``probs=None`` (L1 ablation) only the threshold."""
    out = []
    for i, w in enumerate(weights):
        w = np.asarray(w, np.float64)
        keep = np.abs(w) > weight_threshold
        if probs is not None:
            keep &= np.asarray(probs[i]) > 0.5
        out.append(np.where(keep, w, 0.0))
    return out


def network_expressions(
    network: SymbolicNetwork,
    params: dict[str, Sequence[np.ndarray]],
    probs: Sequence[np.ndarray] | None,
) -> list[sp.Expr]:
    """Protected sympy expressions, one per action dimension, of the deterministic policy.

    Args:
        network: the network structure.
        params: {"w": [...], "b": [...]} with leading action axis (numpy or jax arrays).
        probs: path probabilities shaped like params["w"], or None for the L1 ablation.

    Returns:
        ``action_dim`` expressions in the symbols x0 … x{obs_dim−1} giving the pre-tanh action.
    """
    weights = pruned_weights(params["w"], probs)
    biases = [np.asarray(b, np.float64) for b in params["b"]]
    symbols = observation_symbols(network.obs_dim)
    exprs = []
    for a in range(network.action_dim):
        x: list[sp.Expr] = list(symbols)
        for layer, ops_names in enumerate(network.layout.layers):
            y = _affine(weights[layer][a], biases[layer][a], x)
            outputs, row = [], 0
            for name in ops_names:
                arity = ops.get_operator(name).arity
                outputs.append(SYMPY_OPERATORS[name](*y[row : row + arity]))
                row += arity
            x = x + outputs if network.layout.dense else outputs
        exprs.append(_affine(weights[-1][a], biases[-1][a], x)[0])
    return exprs


def export_expressions(trainer: Trainer, actor_params: dict) -> list:
    """Protected sympy expressions of one seed's deterministic symbolic policy."""
    network = trainer.actor.symbolic
    probs = actor_params["probs"] if trainer.actor.uses_selector else None
    return network_expressions(network, actor_params["mean"], probs)


def _affine(w: np.ndarray, b: np.ndarray, x: list[sp.Expr]) -> list[sp.Expr]:
    """Rows of w·x + b as sympy expressions, skipping pruned (zero) weights."""
    rows = []
    for r in range(w.shape[0]):
        terms = [sp.Float(float(w[r, j])) * x[j] for j in np.flatnonzero(w[r])]
        rows.append(sp.Add(*terms, sp.Float(float(b[r]))))
    return rows


def _unprotect(expr: sp.Expr) -> sp.Expr:
    """Replace the protected functions by the plain operators they guard."""
    return (
        expr.replace(PMul, lambda a, b: a * b)
        .replace(PDiv, lambda a, b: a / b)
        .replace(PLog, sp.log)
        .replace(PExp, sp.exp)
        .replace(PCond, lambda c, a, b: a / (1 + sp.exp(-c)) + b * (1 - 1 / (1 + sp.exp(-c))))
    )


@cache
def readable(expr: sp.Expr) -> sp.Expr:
    """The plain-operator formula, simplified by sympy when small enough to do so quickly.

    Memoised: text, LaTeX, code comments and the length metric all read the same result.
    Expressions longer than ``READABLE_MAX_LENGTH`` are returned unchanged (protected operators
    ``PMul``, ``PDiv``, … stay in the text) so that exporting an unpruned network cannot hang.
    """
    if complexity(expr) > READABLE_MAX_LENGTH:
        return expr
    plain = _unprotect(expr)
    if complexity(plain) <= SIMPLIFY_MAX_LENGTH:
        simplified = _simplify(plain)
        if complexity(simplified) <= complexity(plain):
            return simplified
    return plain


def _simplify(expr: sp.Expr) -> sp.Expr:
    """``sympy.simplify``, except that trigonometric calls are simplified inside but not combined.

    sympy's trigsimp can run for many minutes on a short formula: a hopper_params formula of
    length 70 with one ``cos`` of a product of sums did not finish in 300 s (the end-of-run export
    of its test tasks stalled for over ten minutes), while the same formula with the ``cos``
    held as a symbol simplifies in ~1 s. So each trig call's argument is simplified on its own,
    the call then stands in as a symbol while the whole is simplified, and is put back; what is
    lost are identities between trig calls (sin² + cos² = 1), which pruned formulas rarely hold.
    """
    hidden: dict[sp.Dummy, sp.Expr] = {}

    def hide(call: sp.Expr) -> sp.Dummy:
        symbol = sp.Dummy()
        hidden[symbol] = call.func(sp.simplify(call.args[0]))
        return symbol

    masked = expr.replace(lambda e: isinstance(e, TrigonometricFunction), hide)
    out = sp.simplify(masked)
    while hidden and out.has(*hidden):  # a hidden call's argument may hold another
        out = out.xreplace(hidden)
    return out


def round_floats(expr: sp.Expr, digits: int = 4) -> sp.Expr:
    """Round every float constant to ``digits`` significant digits, for reading."""
    replacements = {f: sp.Float(float(f"{float(f):.{digits}g}")) for f in expr.atoms(sp.Float)}
    return expr.xreplace(replacements)


def complexity(expr: sp.Expr) -> int:
    """The paper's length metric: operators, constants and variables in the expression.

    Sums and products of k terms count k − 1 binary operators; a subtraction ``a − c·b`` counts
    as one operator (the −1 factor is not a constant); ``a·b**−1`` is one division ``a / b``.
    The count is over the expression *tree*, memoised over the shared DAG.
    """
    return _length(expr)


@cache
def _length(e: sp.Expr) -> int:
    if e.is_Atom:
        return 1
    if e.is_Add:
        return len(e.args) - 1 + sum(_length(a) for a in e.args)
    if e.is_Mul:
        factors = list(e.args)
        if factors[0] == -1:  # negation: merged into the enclosing subtraction
            factors = factors[1:]
        # A factor b**-1 is a division: the operator replaces the multiplication, so it counts b.
        lengths = [_length(f.base if _is_reciprocal(f) else f) for f in factors]
        return len(factors) - 1 + sum(lengths)
    if _is_reciprocal(e):  # a lone 1/b: "/", 1, b
        return 2 + _length(e.base)
    return 1 + sum(_length(a) for a in e.args)


def _is_reciprocal(e: sp.Expr) -> bool:
    return e.is_Pow and e.exp == -1


def mean_complexity(exprs: Sequence[sp.Expr]) -> float:
    """Complexity averaged over action dimensions, as reported in the paper."""
    return float(np.mean([complexity(e) for e in exprs]))


def to_text(exprs: Sequence[sp.Expr], digits: int = 4) -> str:
    """``a0 = …`` lines of readable formulas with constants rounded for reading."""
    return "\n".join(f"a{i} = {_printed(e, sp.sstr, digits)}" for i, e in enumerate(exprs))


def to_latex(exprs: Sequence[sp.Expr], digits: int = 4) -> str:
    """One LaTeX equation line per action dimension."""
    return "\n".join(f"a_{{{i}}} = {_printed(e, sp.latex, digits)}" for i, e in enumerate(exprs))


def _printed(expr: sp.Expr, printer: Callable[[sp.Expr], str], digits: int) -> str:
    """The rounded readable formula, or a note when it is too long to be worth printing.

    An unpruned network's formula has millions of nodes: printing it takes minutes and tens of
    megabytes and nobody can read it. policy.py still reproduces it exactly (CSE keeps it small).
    """
    length = complexity(expr)
    if length > READABLE_MAX_LENGTH:
        return f"<not printed: length {length} > {READABLE_MAX_LENGTH}; the network is not pruned>"
    return printer(round_floats(readable(expr), digits))


# --------------------------------------------------------------------------------------------
# JAX: the protected expression as a jittable, differentiable function.

# The protected functions evaluate through the very operators the network trains with, so the
# function below has the network's semantics (and its NaN-free gradients) by construction.
_JAX_CALLS: dict = {
    PMul: lambda a, b: ops.mul(a, b)[0],
    PDiv: lambda a, b: ops.div(a, b)[0],
    PLog: lambda x: ops.log(x)[0],
    PExp: lambda x: ops.exp(x)[0],
    PCond: lambda c, a, b: ops.cond(c, a, b)[0],
    # plain functions: sin/cos of the network, exp/log of readable (unprotected) formulas
    sp.sin: jnp.sin,
    sp.cos: jnp.cos,
    sp.exp: jnp.exp,
    sp.log: jnp.log,
}

_OBS_SYMBOL = re.compile(r"x(\d+)")


def _observation_index(symbol: sp.Symbol) -> int:
    match = _OBS_SYMBOL.fullmatch(symbol.name)
    if match is None:
        raise ValueError(f"{symbol} is not an observation symbol x0, x1, ...")
    return int(match.group(1))


def to_jax(exprs: Sequence[sp.Expr]) -> Callable[[jax.Array], jax.Array]:
    """A jittable, differentiable JAX function computing the formulas' pre-tanh values.

    The protected functions (``PMul``, ``PDiv``, ``PLog``, ``PExp``, ``PCond``) evaluate through
    :mod:`espl_jax.operators`, so the result is the symbolic network's deterministic mean (§3.1,
    App. A) up to float rounding; shared subexpressions are evaluated once per call.

    Args:
        exprs: ``action_dim`` expressions in the symbols x0, x1, ... (as returned by
            ``network_expressions``; readable formulas work too, without protection).

    Returns:
        ``pre_tanh(obs)``: obs float (..., obs_dim) -> float (..., action_dim), in obs's float
        dtype; any leading batch axes are carried through (``jax.vmap`` works as well).
    """
    exprs = list(exprs)
    columns = {s: _observation_index(s) for e in exprs for s in e.free_symbols}

    def pre_tanh(obs: jax.Array) -> jax.Array:
        obs = jnp.asarray(obs)
        if not jnp.issubdtype(obs.dtype, jnp.floating):
            obs = obs.astype(jnp.float32)
        memo: dict[sp.Expr, jax.Array | float] = {}

        def value(e: sp.Expr) -> jax.Array | float:
            if e in memo:
                return memo[e]
            if e.is_Symbol:
                v = obs[..., columns[e]]
            elif e.is_Number or e.is_NumberSymbol:
                v = float(e)  # a weak-typed Python float: takes obs's dtype
            elif e.is_Add:
                v = reduce(operator.add, map(value, e.args))
            elif e.is_Mul:
                v = reduce(operator.mul, map(value, e.args))
            elif e.is_Pow:
                exponent = e.exp
                # an integer power stays a chain of multiplications (lax.integer_pow)
                v = value(e.base) ** (int(exponent) if exponent.is_Integer else float(exponent))
            elif e.func in _JAX_CALLS:
                v = _JAX_CALLS[e.func](*map(value, e.args))
            else:
                raise ValueError(f"cannot evaluate {e.func} in JAX (in {e})")
            memo[e] = v
            return v

        batch = obs.shape[:-1]
        outputs = [jnp.broadcast_to(jnp.asarray(value(e), obs.dtype), batch) for e in exprs]
        return jnp.stack(outputs, axis=-1)

    return pre_tanh


# --------------------------------------------------------------------------------------------
# Code generation: the protected expression, after common-subexpression elimination.

_PY_CALLS = {PMul: "_mul", PDiv: "_div", PLog: "_log", PExp: "_exp", PCond: "_cond"}
_PY_CALLS.update({sp.sin: "math.sin", sp.cos: "math.cos", sp.exp: "math.exp", sp.log: "math.log"})
# act_batch: numpy ufuncs over a column of N robots (np.where selects, so no Python branch)
_NP_CALLS = {PMul: "_vmul", PDiv: "_vdiv", PLog: "_vlog", PExp: "_vexp", PCond: "_vcond"}
_NP_CALLS.update({sp.sin: "np.sin", sp.cos: "np.cos", sp.exp: "np.exp", sp.log: "np.log"})
_C_CALLS = {PMul: "p_mul", PDiv: "p_div", PLog: "p_log", PExp: "p_exp", PCond: "p_cond"}
_C_CALLS.update({sp.sin: "sin", sp.cos: "cos", sp.exp: "exp", sp.log: "log"})


def _code(e: sp.Expr, calls: dict, number: str, power: str) -> str:
    """Render an expression with explicit parentheses; ``number``/``power`` are format strings."""
    if e.is_Symbol:
        return e.name
    if e.is_Number:
        return number.format(float(e))
    if e.is_Add:
        return "(" + " + ".join(_code(a, calls, number, power) for a in e.args) + ")"
    if e.is_Mul:
        return "(" + " * ".join(_code(a, calls, number, power) for a in e.args) + ")"
    if e.is_Pow:
        return power.format(_code(e.base, calls, number, power), float(e.exp))
    if e.func in calls:
        args = ", ".join(_code(a, calls, number, power) for a in e.args)
        return f"{calls[e.func]}({args})"
    raise ValueError(f"cannot generate code for {e.func} in {e}")


def _cse(exprs: Sequence[sp.Expr]) -> tuple[list[tuple[sp.Symbol, sp.Expr]], list[sp.Expr]]:
    # order="none": canonical ordering sorts arguments by tree size, which walks the whole
    # (exponential) tree of an unpruned network; discovery order is deterministic as well.
    return sp.cse(list(exprs), symbols=sp.numbered_symbols("t"), optimizations=None, order="none")


_PY_TEMPLATE = '''"""Symbolic policy exported by espl-jax. Needs only Python's math and numpy.

{formula}

act(obs) evaluates these formulas with the protected operators used in training, squashes with tanh
and scales to the action bounds [{low}, {high}] as the training env does (to_env_units).
act_batch(obs) does the same for a batch of observations [N, {obs_dim}], vectorised with numpy.
"""

import math

import numpy as np

OBS_DIM = {obs_dim}
ACTION_LOW = np.array({low}, dtype=np.float64)
ACTION_HIGH = np.array({high}, dtype=np.float64)
ACTION_CENTER = (ACTION_HIGH + ACTION_LOW) / 2.0
ACTION_HALF_RANGE = (ACTION_HIGH - ACTION_LOW) / 2.0


# The action scaling of the environments the policy was trained in (espl_jax.envs.base), verbatim.
{to_env_units}


def _mul(a, b):
    return min(max(a, -100.0), 100.0) * min(max(b, -100.0), 100.0)


def _div(a, b):
    return a / b if b >= 0.01 else 0.0


def _log(x):
    return math.log(max(x, 0.001))


def _exp(x):
    return math.exp(min(max(x, -10.0), 4.0))


def _cond(c, a, b):
    g = 1.0 / (1.0 + math.exp(-c)) if c >= 0 else math.exp(c) / (1.0 + math.exp(c))
    return g * a + (1.0 - g) * b


def pre_tanh(obs):
    """The formulas' raw values, one per action dimension."""
    {unpack}
{body}
    return [{results}]


def act(obs):
    """Action in the environment's own units for one observation of shape ({obs_dim},)."""
    u = np.tanh(np.asarray(pre_tanh(obs), dtype=np.float64))
    return to_env_units(u, ACTION_CENTER, ACTION_HALF_RANGE)


# Batched versions of the protected operators: the same values as above, elementwise. The masked
# branch is computed on safe inputs (denominator 1, clipped exponent), so numpy never warns.


def _vmul(a, b):
    return np.clip(a, -100.0, 100.0) * np.clip(b, -100.0, 100.0)


def _vdiv(a, b):
    ok = b >= 0.01
    return np.where(ok, a / np.where(ok, b, 1.0), 0.0)


def _vlog(x):
    return np.log(np.maximum(x, 0.001))


def _vexp(x):
    return np.exp(np.clip(x, -10.0, 4.0))


def _vcond(c, a, b):
    e = np.exp(-np.abs(c))
    g = np.where(c >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    return g * a + (1.0 - g) * b


def pre_tanh_batch(obs):
    """pre_tanh for a batch: obs [N, {obs_dim}] -> [N, {action_dim}], no Python loop over N."""
    obs = np.asarray(obs, dtype=np.float64)
    if obs.ndim != 2 or obs.shape[1] != OBS_DIM:
        raise ValueError(f"obs must have shape [N, {{OBS_DIM}}], got {{obs.shape}}")
    n = obs.shape[0]
    {vunpack}
{vbody}
    columns = [{results_batch}]
    return np.stack([np.broadcast_to(c, (n,)) for c in columns], axis=1)


def act_batch(obs):
    """act for a batch: obs [N, {obs_dim}] -> actions [N, {action_dim}] in the env's own units."""
    u = np.tanh(pre_tanh_batch(obs))
    return to_env_units(u, ACTION_CENTER, ACTION_HALF_RANGE)
'''


def to_python(
    exprs: Sequence[sp.Expr],
    obs_dim: int,
    action_low: Sequence[float],
    action_high: Sequence[float],
) -> str:
    """Source of a standalone ``policy.py`` whose ``act(obs)`` reproduces the network exactly.

    The module also defines ``act_batch(obs)`` (and ``pre_tanh_batch``): obs [N, obs_dim] ->
    [N, action_dim], the same semantics vectorised over N robots with numpy.
    """
    replacements, reduced = _cse(exprs)
    py = {"calls": _PY_CALLS, "number": "{!r}", "power": "{}**{:g}"}
    names = ", ".join(f"x{i}" for i in range(obs_dim))
    unpack = f"{names}{',' if obs_dim == 1 else ''} = (float(v) for v in obs)"
    body = "\n".join(f"    {s} = {_code(e, **py)}" for s, e in replacements)
    vec = {**py, "calls": _NP_CALLS}
    # Contiguous columns: each x_i is then a plain 1-D array, which numpy's ufuncs stream fastest.
    vunpack = f"{names}{',' if obs_dim == 1 else ''} = np.ascontiguousarray(obs.T)"
    vbody = "\n".join(f"    {s} = {_code(e, **vec)}" for s, e in replacements)
    return _PY_TEMPLATE.format(
        formula=to_text(exprs),
        low=[float(v) for v in action_low],
        high=[float(v) for v in action_high],
        to_env_units=inspect.getsource(to_env_units).rstrip(),
        obs_dim=obs_dim,
        action_dim=len(exprs),
        unpack=unpack,
        body=body,
        results=", ".join(_code(e, **py) for e in reduced),
        vunpack=vunpack,
        vbody=vbody,
        results_batch=", ".join(_code(e, **vec) for e in reduced),
    )


_C_TEMPLATE = """/* Symbolic policy exported by espl-jax.
{formula}
 * act(obs, action) evaluates the formulas with the protected operators used in training, squashes
 * with tanh and scales to the action bounds low ({low}), high ({high}) as the training env does
 * (center + clip(u, -1, 1) * half_range, espl_jax.envs.base.to_env_units).
 * Compile with: cc -O2 -c policy.c (link with -lm). */
#include <math.h>

#define OBS_DIM {obs_dim}
#define ACTION_DIM {action_dim}

static const double ACTION_CENTER[ACTION_DIM] = {{{center}}};
static const double ACTION_HALF_RANGE[ACTION_DIM] = {{{half_range}}};

static double clampd(double x, double lo, double hi) {{ return x < lo ? lo : (x > hi ? hi : x); }}
static double p_mul(double a, double b) {{
    return clampd(a, -100.0, 100.0) * clampd(b, -100.0, 100.0);
}}
static double p_div(double a, double b) {{ return b >= 0.01 ? a / b : 0.0; }}
static double p_log(double x) {{ return log(x > 0.001 ? x : 0.001); }}
static double p_exp(double x) {{ return exp(clampd(x, -10.0, 4.0)); }}
static double p_cond(double c, double a, double b) {{
    double g = c >= 0 ? 1.0 / (1.0 + exp(-c)) : exp(c) / (1.0 + exp(c));
    return g * a + (1.0 - g) * b;
}}

void act(const double *obs, double *action) {{
{unpack}
{body}
    double u[ACTION_DIM] = {{{results}}};
    for (int i = 0; i < ACTION_DIM; ++i)
        action[i] = ACTION_CENTER[i] + clampd(tanh(u[i]), -1.0, 1.0) * ACTION_HALF_RANGE[i];
}}

/* act for n robots: obs [n][OBS_DIM] in, actions [n][ACTION_DIM] out, both row-major. */
void act_batch(const double *obs, double *actions, int n) {{
    for (long i = 0; i < n; ++i)
        act(obs + i * OBS_DIM, actions + i * ACTION_DIM);
}}
"""


def to_c(
    exprs: Sequence[sp.Expr],
    obs_dim: int,
    action_low: Sequence[float],
    action_high: Sequence[float],
) -> str:
    """C99 source of ``void act(const double *obs, double *action)``, same semantics as Python.

    Also ``void act_batch(const double *obs, double *actions, int n)``: ``act`` over n row-major
    observations [n][obs_dim] into [n][action_dim].
    """
    replacements, reduced = _cse(exprs)
    center, half_range = action_center_half_range(action_low, action_high)
    c = {"calls": _C_CALLS, "number": "{:.17g}", "power": "pow({}, {:g})"}
    unpack = "\n".join(f"    const double x{i} = obs[{i}];" for i in range(obs_dim))
    body = "\n".join(f"    const double {s} = {_code(e, **c)};" for s, e in replacements)
    formula = "\n".join(f" * {line}" for line in to_text(exprs).splitlines())
    return _C_TEMPLATE.format(
        formula=formula,
        obs_dim=obs_dim,
        action_dim=len(exprs),
        low=", ".join(repr(float(v)) for v in action_low),
        high=", ".join(repr(float(v)) for v in action_high),
        center=", ".join(f"{float(v):.17g}" for v in center),
        half_range=", ".join(f"{float(v):.17g}" for v in half_range),
        unpack=unpack,
        body=body,
        results=", ".join(_code(e, **c) for e in reduced),
    )
