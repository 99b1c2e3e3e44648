"""Protected operators (App. A): exact forward and penalty, and finite values/gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from espl_jax import operators as ops

# "Extreme finite" float32 inputs: everything up to 1e30 in magnitude, the protection boundaries
# included (the limit the operators module docstring states). Subnormals are excluded because XLA
# runs the CPU in flush-to-zero mode, where they cannot be represented at all.
LIMIT_HIGH = float(np.float32(1e30))  # 1e30 rounded to float32
LIMIT_LOW = -LIMIT_HIGH
extreme = st.floats(
    min_value=LIMIT_LOW, max_value=LIMIT_HIGH, allow_nan=False, allow_subnormal=False, width=32
)
BOUNDARIES = [LIMIT_LOW, -100.0, -10.0, 0.0, 1e-3, 0.01, 4.0, 100.0, LIMIT_HIGH]


def test_forward_and_penalty_match_appendix():
    x = jnp.array([-150.0, -100.0, -5.0, 0.0, 0.0005, 0.005, 0.5, 3.0, 5.0, 150.0])
    y = jnp.array([2.0, -200.0, 0.02, 0.009, 1.0, -1.0, 0.01, 300.0, 4.0, -0.5])

    v, p = ops.mul(x, y)
    np.testing.assert_allclose(v, np.clip(x, -100, 100) * np.clip(y, -100, 100), rtol=1e-6)
    hinge = lambda z: np.maximum(z - 100, 0) + np.maximum(-100 - z, 0)  # noqa: E731
    np.testing.assert_allclose(p, hinge(x) + hinge(y), rtol=1e-6)

    v, p = ops.div(x, y)
    np.testing.assert_allclose(v, np.where(y >= 0.01, x / np.where(y >= 0.01, y, 1), 0), rtol=1e-6)
    np.testing.assert_allclose(p, np.maximum(0.01 - y, 0), rtol=1e-6)

    v, p = ops.log(x)
    np.testing.assert_allclose(v, np.log(np.maximum(x, 0.001)), rtol=1e-6)
    np.testing.assert_allclose(p, np.maximum(0.001 - x, 0), rtol=1e-6)

    v, p = ops.exp(x)
    np.testing.assert_allclose(v, np.exp(np.clip(x, -10, 4)), rtol=1e-6)
    np.testing.assert_allclose(p, np.maximum(x - 4, 0) + np.maximum(-10 - x, 0), rtol=1e-6)

    for fn, ref in ((ops.sin, np.sin), (ops.cos, np.cos), (ops.identity, lambda z: z)):
        v, p = fn(x)
        np.testing.assert_allclose(v, ref(np.asarray(x)), rtol=1e-6, atol=1e-7)
        assert not np.any(p)

    v, p = ops.cond(x, y, 2.0 * y)
    s = 1 / (1 + np.exp(-np.asarray(x, np.float64)))
    np.testing.assert_allclose(v, s * y + (1 - s) * 2 * y, rtol=1e-5, atol=1e-6)
    assert not np.any(p)


def test_div_is_zero_for_every_small_or_negative_denominator():
    v, p = ops.div(jnp.array([3.0, 3.0, 3.0]), jnp.array([-5.0, 0.0, 0.00999]))
    assert np.all(v == 0)
    np.testing.assert_allclose(p, [5.01, 0.01, 0.00001], rtol=1e-4)


@pytest.mark.parametrize("name", sorted(ops.OPERATORS))
def test_operators_jit_and_vmap(name):
    op = ops.OPERATORS[name]
    args = [jnp.linspace(-3.0, 3.0, 7) + i for i in range(op.arity)]
    eager = op.fn(*args)
    jitted = jax.jit(op.fn)(*args)
    vmapped = jax.vmap(op.fn)(*args)
    for a, b, c in zip(eager, jitted, vmapped, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6)
        np.testing.assert_allclose(a, c, rtol=1e-6)


def _value_and_grads(name, args):
    op = ops.OPERATORS[name]

    def total(*xs):
        value, penalty = op.fn(*xs)
        return value + penalty

    values = op.fn(*args)
    grads = jax.grad(total, argnums=tuple(range(op.arity)))(*args)
    return [*values, *grads]


@pytest.mark.parametrize("name", sorted(ops.OPERATORS))
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_values_and_gradients_finite_for_extreme_inputs(name, data):
    arity = ops.OPERATORS[name].arity
    draw = st.one_of(extreme, st.sampled_from(BOUNDARIES))
    args = [jnp.float32(data.draw(draw)) for _ in range(arity)]
    for out in _value_and_grads(name, args):
        assert np.isfinite(np.asarray(out)).all(), (name, args, out)


def test_unknown_operator_lists_library():
    with pytest.raises(ValueError, match="known operators: .*cond.*mul"):
        ops.get_operator("tan")
