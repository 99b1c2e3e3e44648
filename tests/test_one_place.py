"""One function per repeated concept, held to the formula it replaced (issue 32, item 4).

A refactoring of these must leave training bitwise unchanged. ``benchmarks/bitwise_params.py``
checks that on whole tiny runs, but its hashes hold on one machine only (XLA's CPU code follows
the CPU's instruction set), so none is committed. These tests are the machine-independent part,
and they are quick: each shared function against the expression it replaced, bit for bit, and the
key salts against the values every earlier run was drawn with.
"""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp

from espl_jax import expression as ex
from espl_jax import keys
from espl_jax.envs.base import Environment
from espl_jax.envs.box2d import HostEnv
from espl_jax.reference_eval import load_policy
from espl_jax.seeds import one_seed, take

# Key streams ------------------------------------------------------------------------------------


def test_salts_keep_the_values_every_earlier_run_used():
    # Changing one changes every run's results: these are the numbers of run.py, host.py,
    # host_meta.py, meta.py (now meta_report.py), trainer.py (now learner.py) and sac.py before
    # they got names.
    assert (keys.PROGRESS_EVAL, keys.SELECTION, keys.REPORT) == (1, 2, 3)
    assert keys.RETIRED_SALTS == (4, 5)  # the former host collectors' (host.py, host_meta.py)
    assert (keys.POSTERIOR_DRAW, keys.ENCODER) == (1, 1)
    assert (keys.FRESH_EPISODES_OFFSET, keys.COEFFICIENTS_OFFSET) == (10_000, 20_000)
    assert (keys.REFERENCE_FIRST_EPISODE, keys.EVALUATE_FIRST_EPISODE) == (0, 10_000)


def test_salts_of_the_state_key_are_distinct():
    salts = [keys.PROGRESS_EVAL, keys.SELECTION, keys.REPORT, *keys.RETIRED_SALTS]
    assert len(set(salts)) == len(salts)


def test_key_helpers_are_the_expressions_they_replaced():
    state_keys = jnp.stack([jax.random.PRNGKey(3), jax.random.PRNGKey(11)])
    np.testing.assert_array_equal(
        keys.salted(state_keys, keys.REPORT),
        jax.vmap(jax.random.fold_in, (0, None))(state_keys, 3),
    )
    np.testing.assert_array_equal(
        keys.seed_keys(7, 3), jnp.stack([jax.random.PRNGKey(s) for s in (7, 8, 9)])
    )
    np.testing.assert_array_equal(
        keys.offset_key(2, keys.COEFFICIENTS_OFFSET), jax.random.PRNGKey(2 + 20_000)
    )


# Per-seed slicing -------------------------------------------------------------------------------


def test_one_seed_is_a_host_copy_of_one_seed():
    tree = {"w": jnp.arange(12.0).reshape(3, 4), "b": [np.arange(3)]}
    got = one_seed(tree, 1)
    assert isinstance(got["w"], np.ndarray) and isinstance(got["b"][0], np.ndarray)
    np.testing.assert_array_equal(got["w"], [4.0, 5.0, 6.0, 7.0])
    assert got["b"][0] == 1
    traced = jax.jit(lambda t, i: take(t, i))(tree, 2)  # take also works under jit
    np.testing.assert_array_equal(traced["w"], [8.0, 9.0, 10.0, 11.0])


# Action scaling ---------------------------------------------------------------------------------


def _near_boundary() -> np.ndarray:
    """float32 u at and next to ±1 and 0, and outside [-1, 1] (clipped).

    The tiny ones tell the formulas apart: the earlier policy.py computed
    ``low + (u + 1) / 2 · (high − low)``, which rounds u through u + 1 and, for |u| below ~2e-9,
    missed the env's float32 action (about a quarter of such u; all four here, for every bound
    in ``BOUNDS``)."""
    one = np.float32(1.0)
    near = [one]
    for _ in range(4):
        near.append(np.nextafter(near[-1], np.float32(0.0)))
    near = np.array(near, np.float32)
    tiny = np.array(
        [0.0, 7.9e-12, 1.11043804e-11, 1.5059646e-11, 4.4980485e-11, 1e-8, 3e-4, 0.5, 0.999],
        np.float32,
    )
    outside = np.array([1.0 + 2**-23, 1.5, 1e6], np.float32)
    u = np.concatenate([near, tiny, outside])
    return np.concatenate([u, -u]).astype(np.float32)


# The action bounds of the registered envs (cartpole, mountaincar and the MuJoCo and Box2D envs:
# [-1, 1]; pendulum [-2, 2]) and others that are float32 numbers, as gymnasium's Box bounds are:
# with symmetric float32 bounds the float32 env and the float64 policy.py agree exactly. (Bounds
# that are not float32 numbers, such as a float64 0.4, are rounded to float32 by the env alone.)
BOUNDS = [(-1.0, 1.0), (-2.0, 2.0), (-float(np.float32(0.4)), float(np.float32(0.4))), (-3.0, 3.0)]


def _env(low, high, dim=1):
    return SimpleNamespace(action_low=np.full(dim, low), action_high=np.full(dim, high))


@pytest.mark.parametrize("low, high", [*BOUNDS, (-3.0, 0.5), (0.1, 0.3)])
def test_env_scaling_is_the_formula_training_used(low, high):
    """``Environment.scale_action`` (JAX envs) and ``HostEnv.to_env_action`` (Box2D) compute what
    they computed before they shared ``to_env_units``: training is unchanged."""
    env, u = _env(low, high), _near_boundary()[:, None]
    lo, hi = np.float64(low), np.float64(high)
    c32, h32 = jnp.float32((hi + lo) / 2.0), jnp.float32((hi - lo) / 2.0)
    old_jax = c32 + jnp.clip(jnp.asarray(u, jnp.float32), -1.0, 1.0) * h32
    np.testing.assert_array_equal(Environment.scale_action(env, u), old_jax)
    u64 = np.concatenate([u, [[np.nan], [np.inf]]]).astype(np.float64)
    old_host = (hi + lo) / 2.0 + np.clip(np.nan_to_num(u64), -1.0, 1.0) * ((hi - lo) / 2.0)
    np.testing.assert_array_equal(HostEnv.to_env_action(env, u64), old_host.astype(np.float32))


@pytest.mark.parametrize("low, high", BOUNDS)
def test_policy_py_and_env_agree_bit_for_bit_on_the_boundary(low, high, tmp_path):
    """The exported policy.py sends the reference env (as float32, in
    ``reference_eval.rollout_returns``) exactly the action the training env steps with, at u = ±1
    and next to it."""
    env = _env(low, high, dim=2)
    source = ex.to_python([sp.Float(30.0), sp.Float(-30.0)], 1, env.action_low, env.action_high)
    path = tmp_path / "policy.py"
    path.write_text(source)
    policy = load_policy(path)
    # act: tanh(±30) is ±1 in float64; the action is exactly the bound, as the env's.
    np.testing.assert_array_equal(policy.act([0.0]), [high, low])
    np.testing.assert_array_equal(
        np.float32(policy.act([0.0])), Environment.scale_action(env, np.float32([1.0, -1.0]))
    )
    # The scaling itself, on float32 u (the network's) at and near the boundary.
    u = np.repeat(_near_boundary()[:, None], 2, axis=1)
    exported = np.asarray(
        policy.to_env_units(u.astype(np.float64), policy.ACTION_CENTER, policy.ACTION_HALF_RANGE),
        np.float32,
    )
    np.testing.assert_array_equal(exported, Environment.scale_action(env, u))
    np.testing.assert_array_equal(exported, HostEnv.to_env_action(env, u))
