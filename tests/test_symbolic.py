"""Symbolic network (§3.1) and path selector (§3.2, Algorithm 1)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from espl_jax import selector
from espl_jax.symbolic import LAYOUTS, Layout, SymbolicNetwork, get_layout


@pytest.mark.parametrize("obs_dim", [1, 3, 4, 11, 24])
def test_arranged_path_counts(obs_dim):
    net = SymbolicNetwork(LAYOUTS["arranged"], obs_dim, 2)
    assert net.num_weights == 41 * obs_dim + 496
    assert net.num_biases == 41
    params = net.init(jax.random.key(0))
    assert sum(w.size for w in params["w"]) == 2 * (41 * obs_dim + 496)
    assert sum(b.size for b in params["b"]) == 2 * 41


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_every_layout_runs_jitted_and_vmapped(layout):
    net = SymbolicNetwork(get_layout(layout), 5, 3)
    params = net.init(jax.random.key(0))
    mask = selector.ones_mask(params["w"])
    obs = jax.random.normal(jax.random.key(1), (32, 5))
    out, penalty = jax.jit(jax.vmap(net.apply, in_axes=(None, None, 0)))(params, mask, obs)
    assert out.shape == (32, 3) and penalty.shape == (32,)
    assert np.isfinite(out).all() and np.isfinite(penalty).all()
    single, _ = jax.jit(net.apply)(params, mask, obs[7])
    np.testing.assert_allclose(out[7], single, rtol=1e-5, atol=1e-6)


def test_plain_layout_has_no_dense_links():
    net = SymbolicNetwork(LAYOUTS["plain"], 4, 1)
    rows_in = net.layer_shapes
    assert rows_in[0][1] == 4  # first layer sees the observation only
    for (_, cols), ops in zip(rows_in[1:], LAYOUTS["plain"].layers, strict=True):
        assert cols == len(ops)  # every later layer sees only the previous layer's outputs


def test_layout_is_data():
    custom = Layout((("mul", "cond"), ("sin",)))
    net = SymbolicNetwork(custom, 2, 1)
    assert net.layer_shapes == ((5, 2), (1, 4), (1, 5))
    with pytest.raises(ValueError, match="unknown operator 'tan'"):
        Layout((("tan",),))
    with pytest.raises(ValueError, match="known layouts: arranged, csp, csp_cond, dense, plain"):
        get_layout("sparse")


def test_penalty_is_sum_of_operator_penalties():
    # A network whose only active path feeds x0 into a log: the penalty is max(0.001 - x0, 0).
    net = SymbolicNetwork(LAYOUTS["arranged"], 1, 1)
    params = jax.tree.map(jnp.zeros_like, net.init(jax.random.key(0)))
    params["w"][2] = params["w"][2].at[0, 0, 0].set(1.0)  # layer 3, row 0 (a log) reads x0
    params["b"] = [
        b.at[:].set(0.5) if i in (0, 1, 4, 5) else b for i, b in enumerate(params["b"])
    ]  # keep mul/div/log/exp of later layers out of range
    mask = selector.ones_mask(params["w"])
    apply = jax.jit(net.apply)
    _, pen_inside = apply(params, mask, jnp.array([2.0]))
    _, pen_outside = apply(params, mask, jnp.array([-3.0]))
    np.testing.assert_allclose(pen_outside - pen_inside, 3.001, rtol=1e-5)


@jax.jit
def _loss(params, probs, key, tau, obs):
    mask = selector.gumbel_sigmoid_mask(key, probs, tau)
    out, penalty = jax.vmap(SymbolicNetwork(LAYOUTS["arranged"], 3, 1).apply, (None, None, 0))(
        params, mask, obs
    )
    return jnp.mean(out**2) + jnp.mean(penalty)


def test_gradient_reaches_w_b_and_p_through_straight_through_mask():
    net = SymbolicNetwork(LAYOUTS["arranged"], 3, 1)
    params = net.init(jax.random.key(0))
    probs = jax.tree.map(lambda w: jnp.full_like(w, 0.7), params["w"])
    obs = jax.random.normal(jax.random.key(1), (16, 3))
    grad = jax.jit(jax.grad(_loss, argnums=(0, 1)))
    g_params, g_probs = grad(params, probs, jax.random.key(2), 1.0, obs)
    for tree in (g_params["w"], g_params["b"], g_probs):
        leaves = jax.tree.leaves(tree)
        assert all(np.isfinite(g).all() for g in leaves)
        assert all(np.abs(g).sum() > 0 for g in leaves)
    # Masked-out weights receive no gradient through w_m = w ⊗ m.
    mask = selector.gumbel_sigmoid_mask(jax.random.key(2), probs, 1.0)
    assert np.all(np.where(np.asarray(mask[-1]) == 0, np.asarray(g_params["w"][-1]), 0) == 0)


def test_probability_at_exactly_one_can_decrease():
    net = SymbolicNetwork(LAYOUTS["arranged"], 3, 1)
    params = net.init(jax.random.key(0))
    probs = selector.init_probs(params["w"])
    assert all(np.all(p == 1.0) for p in probs)

    # L_select alone wants every p lower: its gradient is exactly 1 at the boundary (a clip inside
    # the loss would halve or zero it), and one Adam step plus projection moves every p below 1.
    grads = jax.jit(jax.grad(lambda p: selector.select_loss(p, 0.1)))(probs)
    assert all(np.all(np.asarray(g) == 1.0) for g in grads)
    opt = optax.adam(1e-2)
    updates, _ = opt.update(grads, opt.init(probs))
    new = selector.project_probs(optax.apply_updates(probs, updates))
    assert all(np.all(np.asarray(p) < 1.0) and np.all(np.asarray(p) >= 0.0) for p in new)

    # Through the relaxed mask the gradient at p = 1.0 is finite (zero: the sigmoid saturates in
    # float32, as in the authors' code); once p has left the boundary it flows through the mask.
    obs = jax.random.normal(jax.random.key(1), (16, 3))
    grad_mask = jax.jit(jax.grad(_loss, argnums=1))
    at_one = grad_mask(params, probs, jax.random.key(2), 1.0, obs)
    assert all(np.isfinite(g).all() for g in at_one)
    below_one = grad_mask(params, new, jax.random.key(2), 1.0, obs)
    assert all(np.isfinite(g).all() for g in below_one)
    assert sum(float(np.abs(g).sum()) for g in below_one) > 0


def test_gumbel_mask_gradient_finite_at_probability_bounds():
    probs = [jnp.array([0.0, 1.0, 0.5, 1e-8, 1 - 1e-7])]

    def total(p, tau):
        return jnp.sum(selector.gumbel_sigmoid_mask(jax.random.key(0), p, tau)[0])

    for tau in (1.0, 0.2):
        assert np.isfinite(jax.jit(jax.grad(total))(probs, tau)[0]).all()


def test_masks_are_binary_and_follow_probabilities():
    probs = [jnp.full((200, 50), 0.3)]
    m_train = selector.gumbel_sigmoid_mask(jax.random.key(0), probs, 0.5)[0]
    m_collect = selector.bernoulli_mask(jax.random.key(0), probs)[0]
    for m in (m_train, m_collect):
        assert set(np.unique(np.asarray(m))) <= {0.0, 1.0}
        assert abs(float(m.mean()) - 0.3) < 0.02


def test_same_key_same_mask_different_key_different_mask():
    net = SymbolicNetwork(LAYOUTS["arranged"], 4, 1)
    params = net.init(jax.random.key(0))
    probs = jax.tree.map(lambda w: jnp.full_like(w, 0.5), params["w"])
    obs = jnp.array([0.1, -0.2, 0.3, 0.05])
    for sample in (
        lambda k: selector.gumbel_sigmoid_mask(k, probs, 0.5),
        lambda k: selector.bernoulli_mask(k, probs),
    ):
        a, b, c = sample(jax.random.key(7)), sample(jax.random.key(7)), sample(jax.random.key(8))
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert not all(np.array_equal(x, z) for x, z in zip(a, c, strict=True))
        apply = jax.jit(net.apply)
        np.testing.assert_array_equal(apply(params, a, obs)[0], apply(params, b, obs)[0])


def test_deterministic_mask_thresholds_probability_and_weight():
    probs = [jnp.array([0.9, 0.9, 0.4, 0.51])]
    weights = [jnp.array([1.0, 5e-4, 2.0, -0.002])]
    np.testing.assert_array_equal(selector.deterministic_mask(probs, weights)[0], [1, 0, 0, 1])


def test_expected_l0_and_select_loss():
    probs = [jnp.full((10, 10), 0.5), jnp.ones((5,))]
    assert float(selector.expected_l0(probs)) == pytest.approx(55.0)
    assert selector.count(probs) == 105
    # max(55 - 0.2 * 105, 0) = 34; a looser l_min makes the loss vanish.
    assert float(selector.select_loss(probs, 0.2)) == pytest.approx(34.0)
    assert float(selector.select_loss(probs, 0.6)) == 0.0
    assert float(selector.l1_loss([jnp.array([-1.0, 2.0]), jnp.array([[0.5]])])) == 3.5


@pytest.mark.parametrize(
    ("t", "tau", "l_min"),
    [(0, 1.0, 1.0), (200, 0.6, 0.002 + 0.998 * 0.25), (400, 0.2, 0.002), (1000, 0.2, 0.002)],
)
def test_schedules_follow_algorithm_1(t, tau, l_min):
    t_s, l_t = 400, 0.002
    assert float(selector.temperature(t, t_s)) == pytest.approx(tau, rel=1e-6)
    assert float(selector.l_min_schedule(t, t_s, l_t)) == pytest.approx(l_min, rel=1e-6)
    # Also as traced values under jit, as the trainer uses them.
    assert float(jax.jit(selector.temperature, static_argnums=1)(t, t_s)) == pytest.approx(tau)
