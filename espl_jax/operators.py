"""Protected symbolic operators and their penalty terms (ESPL paper, Appendix A).

Every operator maps its inputs to ``(value, penalty)``. The value is the *protected* forward
(clamped, or switched off outside the safe region); the penalty is the hinge that the paper sums
into ``L_penalty`` (§3.1, Eq. 3) to keep inputs out of the "forbidden" area.

All operators are pure, elementwise, ``jit``- and ``vmap``-able. Values and gradients are finite
for every float32 input with ``|x| <= 1e30``; beyond that only ``div`` (``x1 / x2`` with
``x2 >= 0.01``) and ``cond`` (gradient ``sigmoid'(x1) (x2 - x3)``) can overflow, exactly as IEEE
arithmetic does.
The double-``where`` in ``div`` keeps the unused branch from producing ``inf * 0 = nan`` gradients.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp

# Bounds of the protected regions, App. A.
MUL_BOUND = 100.0
DIV_MIN_DENOMINATOR = 0.01
LOG_MIN_ARGUMENT = 0.001
EXP_MIN_ARGUMENT = -10.0
EXP_MAX_ARGUMENT = 4.0


def _hinge_outside(x: jax.Array, low: float, high: float) -> jax.Array:
    """max(x - high, 0) + max(low - x, 0)."""
    return jax.nn.relu(x - high) + jax.nn.relu(low - x)


def mul(x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = clip(x1, ±100) · clip(x2, ±100); L_mul = hinge of both inputs outside ±100."""
    y = jnp.clip(x1, -MUL_BOUND, MUL_BOUND) * jnp.clip(x2, -MUL_BOUND, MUL_BOUND)
    penalty = _hinge_outside(x1, -MUL_BOUND, MUL_BOUND) + _hinge_outside(x2, -MUL_BOUND, MUL_BOUND)
    return y, penalty


def div(x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = x1 / x2 if x2 >= 0.01 else 0 (negative denominators too); L_div = max(0.01 - x2, 0)."""
    valid = x2 >= DIV_MIN_DENOMINATOR
    safe_x2 = jnp.where(valid, x2, 1.0)
    y = jnp.where(valid, x1 / safe_x2, 0.0)
    return y, jax.nn.relu(DIV_MIN_DENOMINATOR - x2)


def log(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = log(max(x, 0.001)); L_log = max(0.001 - x, 0)."""
    return jnp.log(jnp.maximum(x, LOG_MIN_ARGUMENT)), jax.nn.relu(LOG_MIN_ARGUMENT - x)


def exp(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = exp(clip(x, -10, 4)); L_exp = max(x - 4, 0) + max(-10 - x, 0)."""
    y = jnp.exp(jnp.clip(x, EXP_MIN_ARGUMENT, EXP_MAX_ARGUMENT))
    return y, _hinge_outside(x, EXP_MIN_ARGUMENT, EXP_MAX_ARGUMENT)


def sin(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = sin(x); no penalty."""
    return jnp.sin(x), jnp.zeros_like(x)


def cos(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = cos(x); no penalty."""
    return jnp.cos(x), jnp.zeros_like(x)


def identity(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = x; no penalty. Used only by the "plain" (non-dense) ablation layout."""
    return x, jnp.zeros_like(x)


def cond(x1: jax.Array, x2: jax.Array, x3: jax.Array) -> tuple[jax.Array, jax.Array]:
    """y = sigmoid(x1)·x2 + (1 - sigmoid(x1))·x3; no penalty. Used by CSP on cheetah_vel_ood."""
    gate = jax.nn.sigmoid(x1)
    return gate * x2 + (1.0 - gate) * x3, jnp.zeros_like(x1)


@dataclass(frozen=True)
class Operator:
    """A library entry: its name, how many rows of ``W x + b`` it consumes, and its forward."""

    name: str
    arity: int
    fn: Callable[..., tuple[jax.Array, jax.Array]]


OPERATORS: dict[str, Operator] = {
    op.name: op
    for op in (
        Operator("mul", 2, mul),
        Operator("div", 2, div),
        Operator("log", 1, log),
        Operator("exp", 1, exp),
        Operator("sin", 1, sin),
        Operator("cos", 1, cos),
        Operator("identity", 1, identity),
        Operator("cond", 3, cond),
    )
}


def get_operator(name: str) -> Operator:
    """Look an operator up by name; unknown names raise ValueError listing the library."""
    try:
        return OPERATORS[name]
    except KeyError:
        raise ValueError(
            f"unknown operator {name!r}; known operators: {', '.join(sorted(OPERATORS))}"
        ) from None
