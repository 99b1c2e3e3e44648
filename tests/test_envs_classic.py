"""Step-by-step parity of the classic-control JAX envs with their references, plus API checks.

References: gymnasium 1.4.0 ``Pendulum-v1`` and ``MountainCarContinuous-v0`` (their own classes,
``gymnasium.make(...).unwrapped``), and DSO's continuous CartPole, transcribed below in numpy
float64 independently of ``envs``. Rollouts run as one jitted ``vmap(scan)`` per env; the
references are then replayed on the host with the same actions.
"""

from __future__ import annotations

import math

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.wrappers import TimeLimit

from espl_jax import envs
from espl_jax.envs.reference import reference_env

TOL = 1e-4
OPEN_LOOP = 50  # cartpole steps checked open loop in float32 (see the per-step test)
X64_CAP = 250  # cartpole steps per episode checked open loop in float64


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _rollout(env, policy, keys, policy_args, params=None):
    """Rolls out ``env.horizon`` steps per episode from reset, no auto-reset.

    Args:
        env: the JAX env.
        policy: ``policy(key, obs, arg) -> normalized action (action_dim,)``.
        keys: (E,) keys, one per episode.
        policy_args: (E,) per-episode policy argument.
        params: env params (default if None), shared by all episodes.

    Returns:
        dict of numpy arrays with leading (E, T): ``state`` (the pre-step states, a pytree),
        ``action``, ``obs`` (post-step), ``reward``, ``terminated``, ``truncated``; and
        ``obs0`` (E, obs_dim).
    """
    params = env.default_params if params is None else params

    def episode(key, arg):
        key_reset, key_steps = jax.random.split(key)
        obs, state = env.reset(key_reset, params)

        def body(carry, key_t):
            state, obs = carry
            key_a, key_s = jax.random.split(key_t)
            action = policy(key_a, obs, arg)
            obs2, state2, reward, term, trunc, _ = env.step(key_s, state, action, params)
            out = dict(
                state=state,
                action=action,
                obs=obs2,
                reward=reward,
                terminated=term,
                truncated=trunc,
            )
            return (state2, obs2), out

        _, out = jax.lax.scan(body, (state, obs), jax.random.split(key_steps, env.horizon))
        out["obs0"] = obs
        return out

    out = jax.tree.map(np.asarray, jax.jit(jax.vmap(episode))(keys, policy_args))
    for leaf in jax.tree.leaves(out):  # also past each episode's end: step never yields NaN/inf
        if np.issubdtype(leaf.dtype, np.floating):
            assert np.all(np.isfinite(leaf))
    return out


def _valid(out):
    """(E, T) mask of the steps up to and including each episode's first end."""
    done = out["terminated"] | out["truncated"]
    return np.cumsum(done, axis=1) - done == 0


def _dso_cartpole_step(s, a):
    """DSO ``CustomCartPoleContinuous`` (Danforth's gist) step in numpy float64, vectorized.

    Args:
        s: float64 (..., 4), ``[x, x_dot, theta, theta_dot]``.
        a: float64 (...), action in [-1, 1].

    Returns:
        ``(next_state (..., 4), reward (...), done (...))``.
    """
    gravity, masscart, masspole, length, force_mag, tau = 9.8, 1.0, 0.1, 0.5, 30.0, 0.02
    total_mass = masspole + masscart
    polemass_length = masspole * length
    x, x_dot, theta, theta_dot = np.moveaxis(np.asarray(s, np.float64), -1, 0)
    force = force_mag * np.asarray(a, np.float64)
    costheta, sintheta = np.cos(theta), np.sin(theta)
    temp = (force + polemass_length * theta_dot * theta_dot * sintheta) / total_mass
    thetaacc = (gravity * sintheta - costheta * temp) / (
        length * (4.0 / 3.0 - masspole * costheta * costheta / total_mass)
    )
    xacc = temp - polemass_length * thetaacc * costheta / total_mass
    x = x + tau * x_dot
    x_dot = x_dot + tau * xacc
    theta = theta + tau * theta_dot
    theta_dot = theta_dot + tau * thetaacc
    theta_thr = 12 * 2 * math.pi / 360
    done = (x < -2.4) | (x > 2.4) | (theta < -theta_thr) | (theta > theta_thr)
    return np.stack([x, x_dot, theta, theta_dot], -1), np.ones_like(x), done


def _cartpole_policy(key, obs, w):
    """Noisy PD balancer ``10 theta + theta_dot`` (DSO's symbolic policy) blended with noise."""
    noise = jax.random.uniform(key, (1,), minval=-1.2, maxval=1.2)
    return w * jnp.clip(10.0 * obs[2:3] + obs[3:4], -1, 1) + (1 - w) * noise


def _x64_state(state, **values):
    """``state`` with the named fields replaced by float64 scalars (call under ``enable_x64``)."""
    return state.replace(**{k: jnp.asarray(v, jnp.float64) for k, v in values.items()})


def _assert_close(actual, desired):
    np.testing.assert_allclose(np.asarray(actual), np.asarray(desired), rtol=0, atol=TOL)


# --------------------------------------------------------------------------------------------
# parity with the references
# --------------------------------------------------------------------------------------------


def test_pendulum_matches_gymnasium_per_step():
    """float32 JAX vs gymnasium float64, gymnasium re-synced to the JAX state before every step.

    Open loop, float32 round-off grows chaotically in some 200-step episodes (up to ~1e-3), so this
    check re-syncs; ``test_pendulum_matches_gymnasium_open_loop_x64`` covers open loop.
    """
    env = envs.make("pendulum")
    n_ep = 6

    def policy(key, obs, arg):
        del obs, arg  # actions beyond [-1, 1] exercise the clip (gymnasium clips at +-2 too)
        return jax.random.uniform(key, (1,), minval=-1.2, maxval=1.2)

    out = _rollout(env, policy, jax.random.split(jax.random.key(0), n_ep), jnp.zeros(n_ep))
    assert _valid(out).all()  # 200 steps each, never terminated
    ref = gymnasium.make("Pendulum-v1").unwrapped
    ref.reset(seed=0)
    ref_obs, ref_reward = np.zeros(out["obs"].shape), np.zeros(out["reward"].shape)
    for e in range(n_ep):
        for t in range(env.horizon):
            ref.state = np.array([out["state"].theta[e, t], out["state"].theta_dot[e, t]])
            ref_obs[e, t], ref_reward[e, t], term, trunc, _ = ref.step(2.0 * out["action"][e, t])
            assert not term and not trunc
    _assert_close(out["obs"], ref_obs)
    _assert_close(out["reward"], ref_reward)
    assert not out["terminated"].any()
    assert out["obs"].shape[0] * out["obs"].shape[1] >= 1000


def test_pendulum_matches_gymnasium_open_loop_x64():
    """The same env run open loop in float64 (jax x64) tracks gymnasium over 5 whole episodes."""
    env = envs.make("pendulum")
    rng = np.random.default_rng(1)
    ref = gymnasium.make("Pendulum-v1").unwrapped
    ref.reset(seed=1)
    got, want = [], []
    with jax.enable_x64(True):
        params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), env.default_params)
        step = jax.jit(env.step)
        key = jax.random.key(1)
        for _ in range(5):
            ref.state = np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1)])
            _, state = env.reset(key, params)
            state = _x64_state(state, theta=ref.state[0], theta_dot=ref.state[1])
            for _ in range(env.horizon):
                a = rng.uniform(-1, 1, size=(1,)).astype(np.float32)
                obs, state, reward, term, trunc, _ = step(key, state, jnp.asarray(a), params)
                ref_obs, ref_reward, ref_term, _, _ = ref.step(2.0 * a)
                got.append((obs, reward, term))
                want.append((ref_obs, ref_reward, ref_term))
            assert bool(trunc)
    _assert_close([g[0] for g in got], [w[0] for w in want])
    _assert_close([g[1] for g in got], [w[1] for w in want])
    assert [bool(g[2]) for g in got] == [w[2] for w in want]
    assert len(got) >= 1000


@pytest.mark.parametrize("power", [0.0015, 0.004])
def test_mountaincar_matches_gymnasium_open_loop(power):
    """float32 open loop across whole episodes (max error ~1e-6); energy pumping ``sign(v)``
    mixed with noise reaches the goal in some episodes, so the +100 branch is checked. The
    stronger engine (``power`` set on both envs) also drives the speed limit and the left wall."""
    env = envs.make("mountaincar")
    params = env.default_params.replace(power=power)
    weights = jnp.array([0.0, 0.6, 0.9, 1.0, 0.0, 0.8, 0.3, 0.95])

    def policy(key, obs, w):
        noise = jax.random.uniform(key, (1,), minval=-1.3, maxval=1.3)
        return w * jnp.sign(obs[1:2]) + (1 - w) * noise

    out = _rollout(env, policy, jax.random.split(jax.random.key(2), len(weights)), weights, params)
    valid = _valid(out)
    ref = gymnasium.make("MountainCarContinuous-v0").unwrapped
    ref.reset(seed=0)
    ref.power = power
    ref_obs, ref_reward = np.zeros(out["obs"].shape), np.zeros(out["reward"].shape)
    ref_term = np.zeros(out["terminated"].shape, bool)
    for e in range(len(weights)):
        ref.state = np.array(out["obs0"][e], np.float64)
        for t in range(int(valid[e].sum())):
            # gymnasium penalizes the unclipped action; the JAX env clips first (its contract).
            ref_obs[e, t], ref_reward[e, t], ref_term[e, t], _, _ = ref.step(
                np.clip(out["action"][e, t], -1, 1)
            )
    _assert_close(out["obs"][valid], ref_obs[valid])
    _assert_close(out["reward"][valid], ref_reward[valid])
    np.testing.assert_array_equal(out["terminated"][valid], ref_term[valid])
    assert not (out["truncated"] & out["terminated"]).any()
    assert ref_term.sum() >= 2, "the goal branch (reward +100) was never exercised"
    position, velocity = out["obs"][..., 0][valid], out["obs"][..., 1][valid]
    if power == 0.0015:
        assert valid.sum() >= 1000
        assert out["truncated"][valid].sum() >= 1
    else:
        assert (np.abs(velocity) == np.float32(0.07)).any(), "speed limit never reached"
        assert (position == np.float32(-1.2)).any(), "left wall never reached"


def test_cartpole_matches_dso_per_step():
    """float32 JAX vs the numpy float64 transcription of DSO's equations.

    The upright pole is unstable, so replaying fixed actions open loop amplifies float32 round-off
    about e-fold every 13 steps: the float32 open-loop error first exceeds 1e-4 after ~90-160
    steps. So every step is checked from the JAX pre-step state (re-synced), the first
    ``OPEN_LOOP`` steps of each episode also open loop, and
    ``test_cartpole_matches_dso_open_loop_x64`` checks long stretches open loop in float64.
    """
    env = envs.make("cartpole")
    n_ep = 24
    weights = jnp.linspace(0.0, 1.0, n_ep)
    out = _rollout(env, _cartpole_policy, jax.random.split(jax.random.key(3), n_ep), weights)
    valid = _valid(out)
    st = out["state"]
    pre = np.stack([st.x, st.x_dot, st.theta, st.theta_dot], -1)
    action = np.clip(out["action"][..., 0], -1, 1)
    nxt, reward, done = _dso_cartpole_step(pre, action)
    _assert_close(out["obs"][valid], nxt[valid])
    np.testing.assert_array_equal(out["reward"][valid], reward[valid])
    np.testing.assert_array_equal(out["terminated"][valid], done[valid])
    assert valid.sum() >= 1000
    assert out["terminated"][valid].sum() >= n_ep // 2
    for e in range(n_ep):
        s = out["obs0"][e].astype(np.float64)  # both start from the same reset state
        for t in range(min(int(valid[e].sum()), OPEN_LOOP)):
            s, _, d = _dso_cartpole_step(s, action[e, t])
            _assert_close(out["obs"][e, t], s)
            assert bool(out["terminated"][e, t]) == d


def test_cartpole_matches_dso_open_loop_x64():
    """JAX in float64 (jax x64) open loop vs the numpy transcription, ``X64_CAP`` steps at most
    per episode (beyond ~300 steps even float64 round-off is amplified past 1e-4). The noisy
    balancing action is computed on the host from the reference state and fed to both."""
    env = envs.make("cartpole")
    rng = np.random.default_rng(3)
    n, n_term = 0, 0
    with jax.enable_x64(True):
        params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), env.default_params)
        step = jax.jit(env.step)
        key = jax.random.key(0)
        for w in (0.0, 0.0, 0.1, 0.3, 0.6, 0.9, 1.0):
            s = rng.uniform(-0.05, 0.05, size=4)
            _, state = env.reset(key, params)
            state = _x64_state(state, x=s[0], x_dot=s[1], theta=s[2], theta_dot=s[3])
            got, want = [], []
            for _ in range(X64_CAP):
                pd = np.clip(10.0 * s[2] + s[3], -1, 1)
                a = np.float32(w * pd + (1 - w) * rng.uniform(-1, 1))
                obs, state, reward, term, _, _ = step(key, state, jnp.array([a]), params)
                s, _, done = _dso_cartpole_step(s, a)
                got.append((obs, reward, term))
                want.append((s, done))
                if done:
                    break
            _assert_close([g[0] for g in got], [w_[0] for w_ in want])
            assert all(float(g[1]) == 1.0 for g in got)
            assert [bool(g[2]) for g in got] == [bool(w_[1]) for w_ in want]
            n += len(got)
            n_term += bool(done)
    assert n >= 1000
    assert n_term >= 2


def test_cartpole_reference_env_matches_jax():
    """Short open-loop check (the first ``OPEN_LOOP`` steps, or to termination)."""
    env = envs.make("cartpole")
    weights = jnp.array([0.0, 0.3, 0.8])
    out = _rollout(env, _cartpole_policy, jax.random.split(jax.random.key(4), 3), weights)
    valid = _valid(out)
    ref = reference_env("cartpole")
    n_term = 0
    for e in range(3):
        ref.reset(seed=e)
        ref.unwrapped.state = out["obs0"][e].astype(np.float64)
        for t in range(min(int(valid[e].sum()), OPEN_LOOP)):
            obs, reward, term, trunc, _ = ref.step(out["action"][e, t])  # env units == normalized
            _assert_close(out["obs"][e, t], obs)
            assert reward == out["reward"][e, t] == 1.0
            assert term == bool(out["terminated"][e, t])
            assert trunc == bool(out["truncated"][e, t])
            n_term += term
    assert n_term >= 1


@pytest.mark.parametrize("name", ["cartpole", "mountaincar", "pendulum"])
def test_reference_env_units_and_time_limit(name):
    env = envs.make(name)
    ref = reference_env(name)
    np.testing.assert_allclose(ref.action_space.low, env.action_low)
    np.testing.assert_allclose(ref.action_space.high, env.action_high)
    wrapper = ref
    while not isinstance(wrapper, TimeLimit):
        wrapper = wrapper.env
    assert wrapper._max_episode_steps == env.horizon
    obs, _ = ref.reset(seed=0)
    assert obs.shape == (env.obs_dim,)


# --------------------------------------------------------------------------------------------
# API
# --------------------------------------------------------------------------------------------


def test_unknown_name_lists_known_names():
    with pytest.raises(ValueError) as err:
        envs.make("no_such_env")
    for name in ("cartpole", "mountaincar", "pendulum"):
        assert name in str(err.value)
    assert ", ".join(envs.KNOWN_ENVS) in str(err.value)
    with pytest.raises(ValueError) as err:
        reference_env("no_such_env")
    for name in ("cartpole", "mountaincar", "pendulum", "lunarlander", "bipedalwalker"):
        assert name in str(err.value)


def test_registry():
    assert list(envs.KNOWN_ENVS) == sorted(envs.KNOWN_ENVS)
    assert {"cartpole", "mountaincar", "pendulum"} <= set(envs.KNOWN_ENVS)
    assert envs.make("cartpole", horizon=200).horizon == 200
    with pytest.raises(ValueError, match="already registered"):
        envs.register("pendulum", envs.Pendulum)


@pytest.mark.parametrize(
    ("name", "obs_dim", "horizon", "high"),
    [("cartpole", 4, 1000, 1.0), ("mountaincar", 2, 999, 1.0), ("pendulum", 3, 200, 2.0)],
)
def test_static_metadata_and_output_types(name, obs_dim, horizon, high):
    env = envs.make(name)
    assert env.name == name
    assert (env.obs_dim, env.action_dim, env.horizon) == (obs_dim, 1, horizon)
    assert isinstance(env.action_low, np.ndarray) and isinstance(env.action_high, np.ndarray)
    np.testing.assert_array_equal(env.action_low, [-high])
    np.testing.assert_array_equal(env.action_high, [high])
    params = env.default_params
    assert all(isinstance(leaf, float) for leaf in jax.tree.leaves(params))
    obs, state = jax.jit(env.reset)(jax.random.key(0), params)
    assert obs.shape == (obs_dim,) and obs.dtype == jnp.float32
    assert int(state.t) == 0
    obs, state, reward, term, trunc, info = jax.jit(env.step)(
        jax.random.key(1), state, jnp.zeros(1), params
    )
    assert obs.shape == (obs_dim,) and obs.dtype == jnp.float32
    assert reward.shape == () and reward.dtype == jnp.float32
    assert term.shape == () and term.dtype == jnp.bool_
    assert trunc.shape == () and trunc.dtype == jnp.bool_
    assert isinstance(info, dict)
    assert int(state.t) == 1


def test_truncated_exactly_at_horizon_and_separate_from_terminated():
    env = envs.make("pendulum")
    out = _rollout(
        env, lambda k, o, a: jnp.ones(1), jax.random.split(jax.random.key(5), 2), jnp.zeros(2)
    )
    assert not out["terminated"].any()
    assert not out["truncated"][:, :199].any()
    assert out["truncated"][:, 199].all()

    cartpole = envs.make("cartpole", horizon=5)
    params = cartpole.default_params
    step = jax.jit(cartpole.step)
    _, state = cartpole.reset(jax.random.key(0), params)
    upright = jax.tree.map(jnp.zeros_like, state)  # t == 0 too
    state = upright
    for t in range(1, 6):  # the upright pole with zero force stays exactly upright
        _, state, _, term, trunc, _ = step(jax.random.key(0), state, jnp.zeros(1), params)
        assert not bool(term)
        assert bool(trunc) == (t == 5)
    # an episode that truly ends on the horizon step is terminated, not truncated
    edge = upright.replace(x=upright.x + 2.39, x_dot=upright.x_dot + 1.0, t=upright.t + 4)
    _, _, reward, term, trunc, _ = step(jax.random.key(0), edge, jnp.zeros(1), params)
    assert bool(term) and not bool(trunc) and float(reward) == 1.0


@pytest.mark.parametrize(
    ("name", "field", "value"),
    [
        ("pendulum", "g", 5.0),
        ("cartpole", "force_mag", 10.0),
        ("cartpole", "length", 0.7),
        ("mountaincar", "power", 0.003),
    ],
)
def test_params_flow_under_jit_vmap(name, field, value):
    """A batch of two params (default, changed) under jit+vmap: default matches the unbatched
    step, the changed one diverges."""
    env = envs.make(name)
    default = env.default_params
    changed = default.replace(**{field: value})
    params = jax.tree.map(lambda a, b: jnp.array([a, b]), default, changed)
    _, state = env.reset(jax.random.key(7), default)
    states = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    keys = jax.random.split(jax.random.key(8), 2)
    vstep = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, 0)))
    step = jax.jit(env.step)
    actions = jax.random.uniform(jax.random.key(9), (10, 1), minval=-1, maxval=1)
    for a in actions:
        obs_b, states, *_ = vstep(keys, states, jnp.stack([a, a]), params)
        obs, state, *_ = step(keys[0], state, a, default)
        np.testing.assert_allclose(obs_b[0], obs, rtol=1e-6, atol=1e-6)
    assert np.abs(np.asarray(obs_b[0] - obs_b[1])).max() > 1e-4


@pytest.mark.parametrize("name", ["cartpole", "mountaincar", "pendulum"])
def test_reset_deterministic_and_in_range(name):
    env = envs.make(name)
    params = env.default_params
    reset = jax.jit(env.reset)
    obs_a, state_a = reset(jax.random.key(11), params)
    obs_b, state_b = reset(jax.random.key(11), params)
    obs_c, _ = reset(jax.random.key(12), params)
    np.testing.assert_array_equal(obs_a, obs_b)
    jax.tree.map(np.testing.assert_array_equal, state_a, state_b)
    assert not np.array_equal(obs_a, obs_c)
    obs, states = jax.vmap(reset, in_axes=(0, None))(
        jax.random.split(jax.random.key(13), 512), params
    )
    if name == "cartpole":
        assert np.all(np.abs(obs) <= 0.05)
    elif name == "pendulum":
        assert np.all(np.abs(states.theta) <= np.pi) and np.all(np.abs(states.theta_dot) <= 1)
        np.testing.assert_allclose(obs[:, 0] ** 2 + obs[:, 1] ** 2, 1.0, atol=1e-5)
    else:
        assert np.all((states.position >= -0.6) & (states.position <= -0.4))
        assert np.all(states.velocity == 0)


def test_step_past_the_end_stays_finite():
    """No auto-reset: cartpole stepped 1000 steps past its end with saturated actions stays finite.

    (The parity rollouts above also run every episode to the horizon past its end; ``_rollout``
    checks those for NaN/inf too.)
    """
    env = envs.make("cartpole")
    out = _rollout(
        env,
        lambda k, o, a: a * jnp.sign(jax.random.normal(k, (1,))) * 5.0,
        jax.random.split(jax.random.key(14), 2),
        jnp.array([1.0, 0.0]),
    )
    assert out["terminated"].any(axis=1).all()
