"""Export (host side): the printed formula and the generated code are the policy that ran."""

import ctypes
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp

from espl_jax import expression as ex
from espl_jax import selector
from espl_jax.symbolic import LAYOUTS, Layout, SymbolicNetwork

OBS_DIM = 4


def _load_policy(source: str, path):
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"policy_{abs(hash(str(path)))}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _network_actions(net, params, probs, states, dtype=jnp.float32):
    """Pre-tanh values and tanh of the network under the deterministic (export) mask.

    float32 is how the network runs in training; float64 (jax x64) evaluates the same network
    without float32 round-off, which isolates the semantics of the export from precision.
    """
    with jax.enable_x64(dtype == jnp.float64):
        cast = lambda tree: jax.tree.map(lambda a: jnp.asarray(a, dtype), tree)  # noqa: E731
        params, probs = cast(params), cast(probs)
        mask = selector.deterministic_mask(probs, params["w"])
        apply = jax.jit(jax.vmap(net.apply, in_axes=(None, None, 0)))
        pre, _ = apply(params, mask, jnp.asarray(states, dtype))
        pre = np.asarray(pre, np.float64)
    return pre, np.tanh(pre)


def _zero_params(net):
    return jax.tree.map(lambda a: np.zeros(a.shape, np.float32), net.init(jax.random.key(0)))


def test_known_answer_exports_exactly_the_formula(tmp_path):
    net = SymbolicNetwork(LAYOUTS["arranged"], OBS_DIM, 1)
    params = _zero_params(net)
    params["w"][-1][0, 0, 2] = 17.17
    params["w"][-1][0, 0, 3] = 1.2
    probs = [(w != 0).astype(np.float32) for w in params["w"]]
    exprs = ex.network_expressions(net, params, probs)
    x = ex.observation_symbols(OBS_DIM)
    readable = ex.round_floats(ex.readable(exprs[0]))
    assert sp.simplify(readable - (sp.Float(17.17) * x[2] + sp.Float(1.2) * x[3])) == 0
    assert ex.to_text(exprs) == "a0 = 17.17*x2 + 1.2*x3"
    assert ex.mean_complexity([readable]) == 7  # +, *, 17.17, x2, *, 1.2, x3
    assert "x_{2}" in ex.to_latex(exprs) and "17.17" in ex.to_latex(exprs)
    policy = _load_policy(ex.to_python(exprs, OBS_DIM, [-2.0], [2.0]), tmp_path / "policy.py")
    obs = np.array([0.3, -1.0, 0.02, -0.1])
    np.testing.assert_allclose(policy.act(obs), 2.0 * np.tanh(17.17 * 0.02 - 1.2 * 0.1), rtol=1e-6)


def _random_network(seed, action_dim=2):
    """Random weights at training scale, random probabilities, and some tiny weights to drop."""
    net = SymbolicNetwork(LAYOUTS["arranged"], OBS_DIM, action_dim)
    rng = np.random.default_rng(seed)
    params = jax.tree.map(np.asarray, net.init(jax.random.key(seed)))
    params["w"] = [
        w * rng.choice([1.0, 1e-4, 3.0], size=w.shape, p=[0.8, 0.1, 0.1]) for w in params["w"]
    ]
    params["w"] = [w.astype(np.float32) for w in params["w"]]
    probs = [rng.uniform(0, 1, w.shape).astype(np.float32) for w in params["w"]]
    return net, params, probs


def test_policy_py_matches_network_on_random_networks_and_states(tmp_path):
    rng = np.random.default_rng(0)
    states = rng.normal(size=(1200, OBS_DIM)) * 10.0 ** rng.uniform(-3, 3, size=(1200, 1))
    low, high = np.array([-1.0, -3.0]), np.array([1.0, 0.5])
    scale = lambda a: low + (a + 1) / 2 * (high - low)  # noqa: E731
    for seed in range(4):
        net, params, probs = _random_network(seed)
        exprs = ex.network_expressions(net, params, probs)
        policy = _load_policy(ex.to_python(exprs, OBS_DIM, low, high), tmp_path / f"p{seed}.py")
        ours_pre = np.array([policy.pre_tanh(s) for s in states])
        ours = np.array([policy.act(s) for s in states])
        # The same network in float64: exported code and network agree to 1e-5 everywhere.
        pre64, act64 = _network_actions(net, params, probs, states, jnp.float64)
        np.testing.assert_allclose(ours_pre, pre64, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(ours, scale(act64), atol=1e-5)
        # The float32 network as trained: untrained random networks chain products and
        # quotients that amplify float32 round-off, so a few states differ beyond 1e-5.
        _, act32 = _network_actions(net, params, probs, states)
        close = np.abs(ours - scale(act32)) <= 1e-5
        assert close.mean() > 0.99 and np.abs(ours - scale(act32)).max() < 1e-3


# Single-path networks that put an observation straight into one protected operator, so every
# protection branch is exercised on both sides. Each entry: layer, first row, operator index in
# the layer, the observations feeding the rows, and the branch predicate on those observations.
BRANCHES = {
    "div": (1, 0, 0, (0, 1), lambda s: s[:, 1] < 0.01),
    "log": (2, 0, 0, (0,), lambda s: s[:, 0] < 0.001),
    "exp_low": (2, 2, 2, (0,), lambda s: s[:, 0] < -10),
    "exp_high": (2, 2, 2, (0,), lambda s: s[:, 0] > 4),
    "mul": (0, 0, 0, (0, 1), lambda s: np.abs(s[:, :2]).max(axis=1) > 100),
}


def _branch_network(branch):
    """A single-path network through one protection branch, and states on both sides of it."""
    layer, row, op_index, sources, protected = BRANCHES[branch]
    net = SymbolicNetwork(LAYOUTS["arranged"], OBS_DIM, 1)
    params = _zero_params(net)
    for k, j in enumerate(sources):
        params["w"][layer][0, row + k, j] = 1.0
    out_column = OBS_DIM + sum(len(ops) for ops in net.layout.layers[:layer]) + op_index
    params["w"][-1][0, 0, out_column] = 0.01 if branch == "mul" else 0.2
    probs = [(w != 0).astype(np.float32) for w in params["w"]]

    rng = np.random.default_rng(1)
    scale = {"div": 0.02, "log": 0.002, "exp_low": 20.0, "exp_high": 8.0, "mul": 150.0}[branch]
    states = rng.uniform(-scale, scale, size=(1000, OBS_DIM))
    hit = protected(states)
    assert 100 < hit.sum() < 900  # both sides of the branch are well represented
    return net, params, probs, states


@pytest.mark.parametrize("branch", sorted(BRANCHES))
def test_policy_py_matches_network_through_every_protection_branch(branch, tmp_path):
    net, params, probs, states = _branch_network(branch)
    exprs = ex.network_expressions(net, params, probs)
    policy = _load_policy(ex.to_python(exprs, OBS_DIM, [-1.0], [1.0]), tmp_path / "policy.py")
    for dtype in (jnp.float32, jnp.float64):
        pre, act = _network_actions(net, params, probs, states, dtype)
        np.testing.assert_allclose([policy.pre_tanh(s) for s in states], pre, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose([policy.act(s) for s in states], act, atol=1e-5)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")
def test_c_export_matches_python_export(tmp_path):
    net, params, probs = _random_network(7)
    exprs = ex.network_expressions(net, params, probs)
    low, high = [-1.0, -3.0], [1.0, 0.5]
    (tmp_path / "policy.c").write_text(ex.to_c(exprs, OBS_DIM, low, high))
    lib = tmp_path / "policy.so"
    subprocess.run(
        ["cc", "-O2", "-shared", "-fPIC", "-o", str(lib), str(tmp_path / "policy.c"), "-lm"],
        check=True,
    )
    c_act = ctypes.CDLL(str(lib)).act
    policy = _load_policy(ex.to_python(exprs, OBS_DIM, low, high), tmp_path / "policy.py")
    rng = np.random.default_rng(3)
    for s in rng.normal(size=(200, OBS_DIM)) * 5:
        out = (ctypes.c_double * 2)()
        c_act((ctypes.c_double * OBS_DIM)(*s), out)
        np.testing.assert_allclose(list(out), policy.act(s), rtol=1e-12, atol=1e-12)


def test_l1_ablation_exports_without_probabilities():
    net = SymbolicNetwork(LAYOUTS["arranged"], OBS_DIM, 1)
    params = _zero_params(net)
    params["w"][-1][0, 0, 0] = 2.0
    params["w"][-1][0, 0, 1] = 5e-4  # below the export threshold: dropped
    params["b"][-1][0, 0] = 0.5
    assert ex.to_text(ex.network_expressions(net, params, None)) == "a0 = 2.0*x0 + 0.5"


def test_complexity_counts_operators_constants_and_variables():
    x0, x1 = sp.symbols("x0 x1")
    assert ex.complexity(x0) == 1
    assert ex.complexity(2.5 * x0 - x1) == 5  # -, *, 2.5, x0, x1
    assert ex.complexity(sp.sin(x0) / x1) == 4  # /, sin, x0, x1
    assert ex.mean_complexity([x0, 2.5 * x0 - x1]) == 3.0


def test_a_trig_formula_simplifies_to_the_same_function():
    """An adapted hopper_params formula (length 70): sympy's trigsimp did not finish on it in
    300 s and stalled a run's export; with trig calls held apart it simplifies to the same
    function, its trig argument simplified too."""
    x = sp.symbols("x0:11")
    inner = (0.9814 * x[5] + 1.013) * (-0.2858 * x[10] + 0.7175 * x[2] + 0.4201 * x[6] + 1.103)
    expr = -4.976 * x[1] - 0.215 * inner + 0.671 * sp.cos(1.095 * x[5] + 0.3699 * inner + 0.34)
    out = ex.readable(expr)
    assert ex.complexity(out) <= ex.complexity(expr) and out.has(sp.cos)
    f, g = (sp.lambdify(x, e, "numpy") for e in (expr, out))
    points = np.random.default_rng(0).normal(size=(11, 50))
    np.testing.assert_allclose(f(*points), g(*points), rtol=1e-9, atol=1e-9)
    # identities between trig calls are the part given up; one call's argument still simplifies
    assert ex.readable(sp.sin(x[0] + x[0]) + x[1]) == sp.sin(2 * x[0]) + x[1]


def test_unpruned_network_exports_in_protected_form():
    # Every path kept: the expression tree has millions of nodes. Unprotecting or printing it walks
    # the whole tree (minutes to hours); above READABLE_MAX_LENGTH neither is attempted.
    net = SymbolicNetwork(LAYOUTS["arranged"], OBS_DIM, 1)
    params = jax.tree.map(np.asarray, net.init(jax.random.PRNGKey(0)))
    probs = jax.tree.map(np.ones_like, params["w"])
    (expr,) = ex.network_expressions(net, params, probs)
    assert ex.complexity(expr) > ex.READABLE_MAX_LENGTH
    assert ex.readable(expr) is expr
    assert ex.to_text([expr]).startswith("a0 = <not printed: length ")
    assert ex.to_latex([expr]).startswith("a_{0} = <not printed: length ")
    assert ex.to_python([expr], OBS_DIM, np.array([-1.0]), np.array([1.0]))


# --------------------------------------------------------------------------------------------
# to_jax: the exported formula back in JAX


def test_to_jax_is_the_network_on_random_pruned_networks():
    rng = np.random.default_rng(5)
    states = rng.normal(size=(500, OBS_DIM)) * 10.0 ** rng.uniform(-2, 1, size=(500, 1))
    for seed in range(3):
        net, params, probs = _random_network(seed)
        exprs = ex.network_expressions(net, params, probs)
        assert sum(ex.complexity(e) for e in exprs) > 20  # pruned, but not to nothing
        policy = jax.jit(ex.to_jax(exprs))
        # float64 isolates the semantics: same operators, only summation order differs
        with jax.enable_x64(True):
            ours64 = np.asarray(policy(jnp.asarray(states, jnp.float64)))
        pre64, _ = _network_actions(net, params, probs, states, jnp.float64)
        np.testing.assert_allclose(ours64, pre64, rtol=1e-9, atol=1e-9)
        # float32, as the network trains: equal up to float32 round-off
        ours32 = np.asarray(policy(jnp.asarray(states, jnp.float32)))
        pre32, _ = _network_actions(net, params, probs, states)
        assert ours32.dtype == np.float32 and ours32.shape == (len(states), 2)
        np.testing.assert_allclose(ours32, pre32, rtol=2e-4, atol=2e-4)


def test_to_jax_vmaps_and_has_finite_gradients_through_every_protection():
    net, params, probs = _random_network(11)
    exprs = ex.network_expressions(net, params, probs)
    pre_tanh = ex.to_jax(exprs)
    rng = np.random.default_rng(2)
    # scales from 1e-4 (div/log guards active) to 1e3 (mul clamps and exp bounds active)
    states = rng.normal(size=(300, OBS_DIM)) * 10.0 ** rng.uniform(-4, 3, size=(300, 1))
    states = jnp.asarray(np.vstack([states, np.zeros((1, OBS_DIM))]), jnp.float32)
    batched = jax.jit(pre_tanh)(states)
    # vmap or batch axes: the same values (XLA may fuse float32 sums in another order)
    np.testing.assert_allclose(jax.jit(jax.vmap(pre_tanh))(states), batched, rtol=1e-5, atol=1e-6)
    grads = jax.jit(jax.vmap(jax.grad(lambda s: jnp.sum(jnp.tanh(pre_tanh(s))))))(states)
    assert grads.shape == states.shape and np.all(np.isfinite(grads))
    assert np.any(np.abs(grads) > 0)


def test_to_jax_known_answer_and_constant_formulas():
    x = ex.observation_symbols(3)
    exprs = [17.17 * x[2] + 1.2 * x[0], sp.Float(0.5), ex.PDiv(x[1], x[0]) + x[1] ** 2]
    f = ex.to_jax(exprs)
    obs = jnp.array([[0.005, 2.0, 0.1], [0.5, 2.0, 0.1]])
    np.testing.assert_allclose(
        f(obs), [[1.717 + 0.006, 0.5, 0.0 + 4.0], [1.717 + 0.6, 0.5, 4.0 + 4.0]], rtol=1e-6
    )
    np.testing.assert_allclose(jax.grad(lambda s: f(s)[2])(obs[1]), [-8.0, 2.0 + 4.0, 0.0])


# --------------------------------------------------------------------------------------------
# act_batch: N robots per call, in policy.py (numpy) and in C


def _batch_cases():
    """(name, exprs, states): every protection branch, a random pruned network, and a network of
    every operator (cond included) on states from 1e-4 to 1e3, zero included."""
    cases = []
    for branch in sorted(BRANCHES):
        net, params, probs, states = _branch_network(branch)
        cases.append((branch, ex.network_expressions(net, params, probs), states))
    rng = np.random.default_rng(4)
    wide = rng.normal(size=(600, OBS_DIM)) * 10.0 ** rng.uniform(-4, 3, size=(600, 1))
    wide = np.vstack([wide, np.zeros((1, OBS_DIM))])
    net, params, probs = _random_network(3)
    cases.append(("random", ex.network_expressions(net, params, probs), wide))
    every_op = Layout((("mul", "div", "log", "exp", "sin", "cos", "cond"),) * 2)
    net = SymbolicNetwork(every_op, OBS_DIM, 2)
    params = jax.tree.map(np.asarray, net.init(jax.random.key(8)))
    params["w"] = [w * 3.0 for w in params["w"]]  # push inputs into the protected regions
    probs = [rng.uniform(0, 1, w.shape) for w in params["w"]]
    cases.append(("every_operator", ex.network_expressions(net, params, probs), wide))
    return cases


def test_act_batch_is_act_on_every_row_without_numpy_warnings(tmp_path):
    low, high = np.array([-1.0, -3.0]), np.array([1.0, 0.5])
    for name, exprs, states in _batch_cases():
        dim = len(exprs)
        source = ex.to_python(exprs, OBS_DIM, low[:dim], high[:dim])
        policy = _load_policy(source, tmp_path / f"{name}.py")
        batch_code = source.split("def pre_tanh_batch")[1]
        assert not re.search(r"^\s*(for|while) ", batch_code, re.M)  # vectorised: no loop over N
        if name == "every_operator":
            assert all(f"_v{op}(" in batch_code for op in ("mul", "div", "log", "exp", "cond"))
        # numpy's defaults plus raising: underflow (exp(-|c|) -> 0 in cond) stays ignored, as in
        # math.exp, but any divide, overflow or invalid operation fails the test
        with warnings.catch_warnings(), np.errstate(divide="raise", over="raise", invalid="raise"):
            warnings.simplefilter("error")
            pre = policy.pre_tanh_batch(states)
            actions = policy.act_batch(states)
        assert pre.shape == actions.shape == (len(states), dim), name
        np.testing.assert_allclose(pre, [policy.pre_tanh(s) for s in states], rtol=1e-12, atol=0)
        np.testing.assert_allclose(actions, [policy.act(s) for s in states], rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="shape"):
        policy.act_batch(states[:, :2])


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on this machine")
def test_c_act_batch_matches_python_act_batch(tmp_path):
    low, high = np.array([-1.0, -3.0]), np.array([1.0, 0.5])
    for name, exprs, states in _batch_cases():
        dim = len(exprs)
        source = tmp_path / f"{name}.c"
        source.write_text(ex.to_c(exprs, OBS_DIM, low[:dim], high[:dim]))
        lib_path = tmp_path / f"{name}.so"
        compile_cmd = ["cc", "-O2", "-shared", "-fPIC", "-o", str(lib_path), str(source), "-lm"]
        subprocess.run(compile_cmd, check=True)
        act_batch = ctypes.CDLL(str(lib_path)).act_batch
        double_p = ctypes.POINTER(ctypes.c_double)
        act_batch.argtypes = [double_p, double_p, ctypes.c_int]
        act_batch.restype = None
        obs = np.ascontiguousarray(states, np.float64)
        out = np.full((len(obs), dim), np.nan)
        act_batch(obs.ctypes.data_as(double_p), out.ctypes.data_as(double_p), len(obs))
        python_source = ex.to_python(exprs, OBS_DIM, low[:dim], high[:dim])
        policy = _load_policy(python_source, tmp_path / f"{name}.py")
        np.testing.assert_allclose(out, policy.act_batch(obs), rtol=1e-12, atol=1e-15, err_msg=name)


# --------------------------------------------------------------------------------------------
# benchmarks/deploy.py: a smoke run (slow: benchmarks are not part of the default suite)


def _deploy_module():
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "deploy.py"
    spec = importlib.util.spec_from_file_location("deploy_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_deploy_benchmark_smoke_and_paper_formulas(tmp_path):
    from test_box2d import _paper_bipedalwalker, _paper_lunarlander

    deploy = _deploy_module()
    # Table 3 as transcribed for deploy.py equals the tested numpy versions of test_box2d.py
    # wherever no protection is active (those use |b| >= 0.01 and log|x|, ours b >= 0.01, log x)
    rng = np.random.default_rng(0)
    for name, reference, dim in (
        ("lunarlander", _paper_lunarlander, 8),
        ("bipedalwalker", _paper_bipedalwalker, 24),
    ):
        plain = ex.to_jax([ex.readable(e) for e in deploy.paper_formulas(name)])
        obs = rng.uniform(-1, 1, size=(500, dim))
        obs[:, 1] = np.abs(obs[:, 1]) + 0.01  # lunarlander's log(0.5 y) argument
        with jax.enable_x64(True):
            ours = np.tanh(np.asarray(plain(obs)))
        expected = np.array([reference(o) for o in obs])
        assert np.mean(np.abs(ours - expected) < 1e-9) > 0.99, name

    out = tmp_path / "deploy.json"
    argv = ["--robots", "16", "--envs", "cartpole", "hopper_params", "--repeats", "2"]
    assert deploy.main([*argv, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    impls = {(r["env"], r["policy"].split()[0], r["impl"]) for r in rows}
    assert {("cartpole", "ESPL", i) for i in ("numpy", "jax")} <= impls
    assert ("hopper_params", "PEARL", "jax") in impls
    assert not any(r["env"] == "hopper_params" and r["policy"].startswith("ESPL") for r in rows)
    espl = next(r for r in rows if r["policy"].startswith("ESPL") and r["impl"] == "numpy")
    assert espl["flops_per_robot_step"] == 6  # 17.17*x2 + 1.2*x3: 2 products, 1 sum; + 3
    for r in rows:
        assert r["robots"] == 16 and r["ms_per_step"] > 0 and r["time_over_bound"] > 0
        assert r["xla_flops_per_robot_step"] > 0
