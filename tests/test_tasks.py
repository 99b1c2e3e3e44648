"""Meta-RL task families (``envs/tasks.py``): registry, seeded draws, ranges, params flow.

The trajectory tests roll out jitted ``vmap``-over-tasks ``lax.scan``s: every lane gets the same
reset key and the same actions, so lanes differ only by their task params. Compiling MJX
dominates the run time (half a minute or more per env on 2 cores), so the default run compiles
ONE MJX rollout (``cheetah_run``, ``MJX_STEPS`` steps of ``cheetah_vel_ood``'s half-cheetah),
whose lanes vary the target velocity and, through ``MjxPhysicsFamily`` (the ``*_params``
sampler), the physics. The registered double-pendulum family's own rollout is ``slow``; that
the registered ``*_params`` families produce exactly their env's params pytree is checked
without compiling (``test_counts_shapes_and_horizon``).
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from espl_jax import envs
from espl_jax.envs.tasks import MjxPhysicsFamily, broadcast_tasks, uniform_union

COUNTS = {
    "cartpole_fl_ood": (40, 10),
    "cheetah_vel_ood": (50, 15),
    "hopper_params": (40, 10),
    "invdoublepend_params": (40, 10),
    "lunarlander_params": (40, 10),
    "walker2d_params": (40, 10),
}
MJX_PARAMS_FAMILIES = ("hopper_params", "invdoublepend_params", "walker2d_params")
BASES = {"body_mass": 1.5, "body_inertia": 1.5, "dof_damping": 1.3, "geom_friction": 1.5}
DESCRIBED = {  # the keys of describe() and the params field each one reads
    "cartpole_fl_ood": ("force_mag", "length"),
    "cheetah_vel_ood": ("target_velocity",),
    "lunarlander_params": ("gravity",),
    **{name: tuple(BASES) for name in MJX_PARAMS_FAMILIES},
}
MJX_STEPS = 10


@functools.cache
def family(name: str) -> envs.TaskFamily:
    return envs.make_family(name)


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def _take(tree, idx):
    """Lanes ``idx`` (a list of task indices) of a task batch."""
    return jax.tree.map(lambda x: jnp.asarray(x)[np.asarray(idx)], tree)


def _rollout_fn(env, extra=lambda state: {}):
    """``f(keys (P,), params (P, ...), actions (P, T, A))``: jitted vmapped rollouts.

    Returns numpy dicts (P, T, ...): obs, reward, terminated, truncated, t, plus ``extra(state)``
    of the state after each step (and ``extra0``, that of the reset state).
    """

    def rollout(key, params, actions):
        _, state = env.reset(key, params)

        def body(state, action):
            obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)
            out = dict(
                obs=obs,
                reward=reward,
                terminated=terminated,
                truncated=truncated,
                t=state.t,
                **extra(state),
            )
            return state, out

        extra0 = extra(state)
        _, out = jax.lax.scan(body, state, actions)
        return out, extra0

    f = jax.jit(jax.vmap(rollout))
    return lambda *args: jax.tree.map(np.asarray, f(*args))


def _same_key_and_actions(env, lanes: int, steps: int, seed: int = 0):
    keys = jnp.stack([jax.random.PRNGKey(seed)] * lanes)
    actions = jax.random.uniform(
        jax.random.PRNGKey(seed + 1), (steps, env.action_dim), minval=-1.0, maxval=1.0
    )
    return keys, jnp.broadcast_to(actions, (lanes, steps, env.action_dim))


# --------------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------------


def test_registry_names_and_errors():
    assert sorted(COUNTS) == list(envs.KNOWN_FAMILIES)
    assert all(envs.is_family(name) for name in COUNTS)
    assert not envs.is_family("hopper") and not envs.is_family("no_such_family")
    with pytest.raises(ValueError, match="unknown task family 'hoper_params'") as err:
        envs.make_family("hoper_params")
    assert ", ".join(envs.KNOWN_FAMILIES) in str(err.value)
    with pytest.raises(ValueError, match="unknown environment 'no_such_env'; known: ") as err:
        envs.make("no_such_env")
    assert ", ".join(envs.KNOWN_ENVS) in str(err.value)
    assert ", ".join(envs.KNOWN_FAMILIES) in str(err.value)
    with pytest.raises(ValueError, match="make_family"):
        envs.make("hopper_params")  # a family is not an env: say where to build it
    with pytest.raises(ValueError, match="already registered"):
        envs.register("cartpole_fl_ood", envs.CartPole)


def test_import_and_cartpole_family_stay_light():
    code = (
        "import sys; from espl_jax import envs; f = envs.make_family('cartpole_fl_ood'); "
        "heavy = [m for m in ('mujoco', 'gymnasium') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_counts_shapes_and_horizon(name):
    fam = family(name)
    train, test = fam.tasks(0)
    assert (fam.n_train, fam.n_test) == COUNTS[name]
    assert fam.name == name
    assert fam.env.horizon == (1000 if name == "lunarlander_params" else 200)
    # exactly the env's params pytree, each leaf with a leading task axis
    default = fam.env.default_params
    assert jax.tree.structure(train) == jax.tree.structure(default)
    for batch, n in ((train, fam.n_train), (test, fam.n_test)):
        for leaf, ref in zip(_leaves(batch), jax.tree.leaves(default), strict=True):
            assert leaf.shape == (n, *np.shape(ref)) and leaf.dtype == np.float32


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_same_seed_same_tasks_other_seed_other_tasks(name):
    fam = family(name)
    for a, b in zip(_leaves(fam.tasks(3)), _leaves(fam.tasks(3)), strict=True):
        np.testing.assert_array_equal(a, b)
    fields = DESCRIBED[name]
    for split in (0, 1):
        for field in fields:
            a = np.asarray(getattr(fam.tasks(3)[split], field))
            b = np.asarray(getattr(fam.tasks(4)[split], field))
            nonzero = np.broadcast_to(a != 0, a.shape)  # zero defaults stay zero
            assert np.all(a[nonzero] != b[nonzero]), (split, field)
    # train and test come from independent keys, not the same stream
    train, test = fam.tasks(3)
    for field in fields:
        a, b = np.asarray(getattr(train, field))[: fam.n_test], np.asarray(getattr(test, field))
        assert not np.any((a == b) & (a != 0)), field


# --------------------------------------------------------------------------------------------
# ranges
# --------------------------------------------------------------------------------------------


def _in_union(x, intervals):
    return np.any([(x >= a) & (x <= b) for a, b in intervals], axis=0)


def test_cartpole_fl_ood_ranges_and_disjoint_test():
    fam = family("cartpole_fl_ood")
    train, test = fam.tasks(0)
    f_tr, l_tr = np.asarray(train.force_mag), np.asarray(train.length)
    f_te, l_te = np.asarray(test.force_mag), np.asarray(test.length)
    assert np.all((f_tr >= 7.5) & (f_tr <= 12.5)) and np.all((l_tr >= 0.3) & (l_tr <= 0.7))
    assert np.all(_in_union(f_te, [(5.0, 7.5), (12.5, 15.0)]))
    assert np.all(_in_union(l_te, [(0.2, 0.3), (0.7, 0.8)]))
    # OOD: every test task lies outside the training box in EACH coordinate
    assert np.all((f_te <= 7.5) | (f_te >= 12.5)) and np.all((l_te <= 0.3) | (l_te >= 0.7))
    # only force_mag and length vary; the rest is DSO's CartPole
    default = fam.env.default_params
    for field in ("gravity", "masscart", "masspole", "tau", "x_threshold"):
        np.testing.assert_array_equal(
            np.asarray(getattr(train, field)), np.float32(getattr(default, field))
        )
    # both halves of each union are used, about equally, each coordinate on its own
    big = fam.sample(jax.random.PRNGKey(5), 4000, "test")
    low_f, low_l = np.asarray(big.force_mag) < 10.0, np.asarray(big.length) < 0.5
    assert abs(low_f.mean() - 0.5) < 0.04 and abs(low_l.mean() - 0.5) < 0.04
    assert abs(np.mean(low_f & low_l) - 0.25) < 0.03  # independent coordinates


def test_uniform_union_is_uniform_over_the_union():
    x = np.asarray(uniform_union(jax.random.PRNGKey(0), (30000,), [(0.0, 1.0), (2.0, 4.0)]))
    assert x.dtype == np.float32 and np.all(_in_union(x, [(0.0, 1.0), (2.0, 4.0)]))
    counts, _ = np.histogram(x, bins=8, range=(0.0, 4.0))  # bins of width 0.5
    expected = 30000 / 3 * 0.5  # density 1/3 on the union; bins 2 and 3 cover the gap
    np.testing.assert_allclose(counts[[0, 1, 4, 5, 6, 7]], expected, rtol=0.06)
    assert counts[2] == counts[3] == 0
    with pytest.raises(ValueError, match="disjoint"):
        uniform_union(jax.random.PRNGKey(0), (3,), [(0.0, 2.0), (1.0, 3.0)])


@pytest.mark.parametrize("name", MJX_PARAMS_FAMILIES)
def test_mjx_multipliers_per_element_and_in_range(name):
    fam = family(name)
    default = fam.env.default_params
    train, test = fam.tasks(0)
    key_train, _ = fam.split_keys(0)
    mult = fam.multipliers(key_train, fam.n_train)
    for field, base in BASES.items():
        d = np.asarray(getattr(default, field))
        m = np.asarray(mult[field])
        # the task is the default times its multipliers, element by element (tasks() is jitted,
        # multipliers() eager here: equal up to float32 rounding)
        np.testing.assert_allclose(np.asarray(getattr(train, field)), d * m, rtol=1e-6)
        # multipliers in [base^-3, base^3] (float32 rounding of the power aside)
        assert np.all(m >= base**-3 * (1 - 1e-6)) and np.all(m <= base**3 * (1 + 1e-6)), field
        for batch in (train, test):
            v = np.asarray(getattr(batch, field))
            nz = np.broadcast_to(d != 0, v.shape)
            ratio = v[nz] / np.broadcast_to(d, v.shape)[nz]
            assert np.all(ratio >= base**-3 * (1 - 1e-6)) and np.all(ratio <= base**3 * (1 + 1e-6))
            assert np.all(v[~nz] == 0)  # zero defaults stay zero
        # one multiplier per element: they differ within each task, and across tasks
        flat = m.reshape(fam.n_train, -1)
        assert flat.shape[1] > 1 and np.all(np.ptp(flat, axis=1) > 0), field
        assert np.all(np.ptp(flat, axis=0) > 0), field
        # log-uniform: exponents spread over (-3, 3)
        exponent = np.log(m) / np.log(base)
        assert exponent.min() < -2.0 and exponent.max() > 2.0, field


def test_cheetah_vel_ood_ranges():
    fam = family("cheetah_vel_ood")
    train, test = fam.tasks(0)
    v_tr, v_te = np.asarray(train.target_velocity), np.asarray(test.target_velocity)
    assert np.all((v_tr >= 0.0) & (v_tr <= 2.5)) and np.all((v_te >= 2.5) & (v_te <= 3.0))
    assert v_te.min() >= 2.5 > v_tr.max()
    assert v_tr.max() - v_tr.min() > 1.5  # spread over the range, not one value
    physics = fam.env.default_params
    for field in BASES:  # physics at defaults for every task
        np.testing.assert_array_equal(
            np.asarray(getattr(train, field)),
            np.broadcast_to(getattr(physics, field), np.shape(getattr(train, field))),
        )


def test_lunarlander_gravity_range_and_host_kwargs():
    fam = family("lunarlander_params")
    train, test = fam.tasks(0)
    for batch in (train, test):
        g = np.asarray(batch.gravity)
        assert np.all((g >= -11.0) & (g <= -5.0))
        assert g.min() < -10.0 < g.max()  # stronger and weaker than the default
    for i in range(fam.n_test):
        kwargs = fam.host_kwargs(test, i)
        assert set(kwargs) == {"gravity"} and type(kwargs["gravity"]) is float
        assert np.float32(kwargs["gravity"]) == np.asarray(test.gravity)[i]  # round trip


# --------------------------------------------------------------------------------------------
# describe
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_describe_is_json_and_reproduces_the_tasks(name):
    fam = family(name)
    for batch, n in zip(fam.tasks(0), (fam.n_train, fam.n_test), strict=True):
        described = fam.describe(batch)
        assert len(described) == n
        assert json.loads(json.dumps(described)) == described
        for i, d in enumerate(described):
            assert tuple(d) == DESCRIBED[name]
            for key, value in d.items():
                np.testing.assert_array_equal(
                    np.asarray(value, np.float32), np.asarray(getattr(batch, key))[i]
                )


# --------------------------------------------------------------------------------------------
# params flow: cartpole_fl_ood
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cartpole_rollout():
    return _rollout_fn(family("cartpole_fl_ood").env, lambda s: {"theta": s.theta, "x": s.x})


def test_cartpole_fl_ood_params_change_the_trajectory(cartpole_rollout):
    fam = family("cartpole_fl_ood")
    train, _ = fam.tasks(0)
    t0, t1 = _take(train, [0]), _take(train, [1])
    # lanes: task 0, task 0 with task 1's force, task 0 with task 1's length, task 0 again
    lanes = jax.tree.map(lambda *xs: jnp.concatenate(xs), t0, t0, t0, t0)
    lanes = lanes.replace(
        force_mag=lanes.force_mag.at[1].set(t1.force_mag[0]),
        length=lanes.length.at[2].set(t1.length[0]),
    )
    keys, actions = _same_key_and_actions(fam.env, 4, 20)
    out, _ = cartpole_rollout(keys, lanes, actions)
    obs = out["obs"]
    np.testing.assert_array_equal(obs[0], obs[3])  # equal params, equal trajectories
    assert np.abs(obs[1] - obs[0]).max() > 1e-3  # force_mag flows
    assert np.abs(obs[2] - obs[0]).max() > 1e-3  # length flows


def test_cartpole_fl_ood_truncates_at_200():
    """A balancing (LQR) policy keeps every task up, so only the time limit ends the episode."""
    fam = family("cartpole_fl_ood")
    env = fam.env
    train, test = fam.tasks(0)
    tasks = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), train, test)
    gains = jnp.array([1.0, 1.72, 10.68, 2.82])  # LQR of the linearised pole, Q=diag(1,1,10,1)

    def episode(key, params):
        obs, state = env.reset(key, params)

        def body(carry, _):
            obs, state = carry
            action = jnp.clip(gains @ obs, -1.0, 1.0)[None]
            obs, state, _, terminated, truncated, _ = env.step(key, state, action, params)
            return (obs, state), (terminated, truncated, state.t)

        return jax.lax.scan(body, (obs, state), None, length=env.horizon + 1)[1]

    n = fam.n_train + fam.n_test
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    terminated, truncated, t = map(np.asarray, jax.jit(jax.vmap(episode))(keys, tasks))
    assert not terminated.any()
    assert not truncated[:, : env.horizon - 1].any()  # t = 1..199
    assert truncated[:, env.horizon - 1].all() and np.all(t[:, env.horizon - 1] == 200)


# --------------------------------------------------------------------------------------------
# params flow: MJX (one compiled half-cheetah rollout serves the default run)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cheetah_run():
    """One rollout of ``cheetah_vel_ood``'s env over five lanes, same key and actions.

    Lanes: 0 train task 0 (v_a), 1 test task 0 (v_b), 2 train task 0 again, 3 and 4 v_a with
    physics drawn by ``MjxPhysicsFamily`` (the sampler of the ``*_params`` families) on the same
    model, so the one compile covers both reward-only and physics task params.
    """
    fam = family("cheetah_vel_ood")
    env = fam.env
    train, test = fam.tasks(0)
    physics, _ = MjxPhysicsFamily("halfcheetah_params", env, 2, 1).tasks(0)
    physics = physics.replace(target_velocity=jnp.broadcast_to(train.target_velocity[0], (2,)))
    lanes = jax.tree.map(
        lambda *xs: jnp.concatenate(xs),
        _take(train, [0]),
        _take(test, [0]),
        _take(train, [0]),
        physics,
    )
    keys, actions = _same_key_and_actions(env, 5, MJX_STEPS)
    out, extra0 = _rollout_fn(env, lambda s: {"qpos": s.data.qpos})(keys, lanes, actions)
    return lanes, actions, out, extra0


def test_cheetah_vel_ood_target_velocity_changes_the_reward_only(cheetah_run):
    _, _, out, _ = cheetah_run
    qpos, reward = out["qpos"], out["reward"]
    assert np.isfinite(qpos).all()
    # v* is a reward param: the physics is the same in lanes 0-2
    np.testing.assert_array_equal(qpos[0], qpos[1])
    np.testing.assert_array_equal(reward[0], reward[2])  # equal params, equal trajectories
    assert np.abs(reward[1] - reward[0]).min() > 0.1  # v* flows into every step's reward
    assert not out["terminated"].any() and not out["truncated"].any()


def test_sampled_physics_change_the_mjx_trajectory(cheetah_run):
    _, _, out, _ = cheetah_run
    qpos = out["qpos"]
    for lane in (3, 4):  # rand_param_envs-style physics vs the default model
        assert np.abs(qpos[lane] - qpos[0]).max() > 1e-3, lane
    assert np.abs(qpos[3] - qpos[4]).max() > 1e-3


def test_cheetah_vel_ood_reward_is_the_target_velocity_formula(cheetah_run):
    lanes, actions, out, extra0 = cheetah_run
    env = family("cheetah_vel_ood").env
    # reward = -|v - v*| - 0.05 ||a||^2, v the root's x displacement per env step / dt
    x = np.concatenate([extra0["qpos"][:, None, 0], out["qpos"][:, :, 0]], axis=1)
    velocity = np.diff(x.astype(np.float64), axis=1) / env.dt
    low, high = env.action_low, env.action_high
    a = low + (np.asarray(actions, np.float64) + 1.0) / 2.0 * (high - low)  # env units
    v_star = np.asarray(lanes.target_velocity, np.float64)[:, None]
    expected = -np.abs(velocity - v_star) - 0.05 * np.sum(a**2, axis=-1)
    np.testing.assert_allclose(out["reward"], expected, atol=1e-4)
    assert env.dt == pytest.approx(0.05) and env.obs_dim == 17


@pytest.mark.slow  # compiling the double pendulum's RK4 step and reset: ~1 min on 2 busy cores
def test_invdoublepend_params_change_the_trajectory():
    """A registered ``*_params`` family end to end (the default run covers the same sampler and
    ``MjxEnv`` params path in ``test_sampled_physics_change_the_mjx_trajectory``)."""
    fam = family("invdoublepend_params")
    train, test = fam.tasks(0)
    default = broadcast_tasks(fam.env.default_params, 1)
    lanes = jax.tree.map(
        lambda *xs: jnp.concatenate(xs),
        _take(train, [0, 1]),
        _take(test, [0]),
        _take(train, [0]),
        default,
    )
    keys, actions = _same_key_and_actions(fam.env, 5, MJX_STEPS)
    rollout = _rollout_fn(fam.env, lambda s: {"qpos": s.data.qpos})
    out, _ = rollout(keys, lanes, actions)
    qpos = out["qpos"]
    assert np.isfinite(qpos).all()
    np.testing.assert_array_equal(qpos[0], qpos[3])  # equal params, equal trajectories
    np.testing.assert_array_equal(out["reward"][0], out["reward"][3])
    for lane in (1, 2, 4):  # another train task, a test task, the default physics
        assert np.abs(qpos[lane] - qpos[0]).max() > 1e-3, lane


# --------------------------------------------------------------------------------------------
# lunarlander_params (gymnasium's Box2D)
# --------------------------------------------------------------------------------------------


def test_lunarlander_params_gravity_changes_the_gymnasium_trajectory():
    fam = family("lunarlander_params")
    train, _ = fam.tasks(0)
    g = np.asarray(train.gravity)
    i, j = int(np.argmin(g)), int(np.argmax(g))  # strongest and weakest gravity
    actions = np.random.default_rng(0).uniform(-1, 1, (40, 2)).astype(np.float32)

    def trajectory(task):
        env = fam.env.make_env(**fam.host_kwargs(train, task))
        try:
            assert env.unwrapped.gravity == fam.host_kwargs(train, task)["gravity"]
            assert env.spec.max_episode_steps == 1000
            obs, _ = env.reset(seed=0)
            out = [obs]
            for action in actions:
                obs, *_ = env.step(fam.env.to_env_action(action))
                out.append(obs)
            return np.stack(out)
        finally:
            env.close()

    a, b, a_again = trajectory(i), trajectory(j), trajectory(i)
    np.testing.assert_array_equal(a, a_again)
    np.testing.assert_array_equal(a[0, [0, 2]], b[0, [0, 2]])  # same seed: same terrain, push
    assert np.abs(a[1:, 3] - b[1:, 3]).max() > 0.05  # vertical velocity: the gravity differs
