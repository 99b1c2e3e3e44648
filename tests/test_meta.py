"""Meta-RL: PEARL's machinery (product of Gaussians, KL, buffers, collection, protocol), CSP's
export at its z, and the single-task case unchanged by the one-trainer restructure."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TINY
from flax import struct

from espl_jax import config as config_lib
from espl_jax import expression as ex
from espl_jax import pearl, reference_eval, rollout
from espl_jax.envs.base import Environment
from espl_jax.learner import Trainer
from espl_jax.policies import Actor, GeneratedSymbolic, PolicyConfig
from espl_jax.replay import Transition

DATA = Path(__file__).resolve().parent / "data"


# Product of Gaussians and KL -------------------------------------------------------------------


def test_product_of_gaussians_matches_its_closed_form():
    mu, var = pearl.product_of_gaussians(jnp.asarray([[1.0], [3.0]]), jnp.asarray([[1.0], [1.0]]))
    np.testing.assert_allclose([mu[0], var[0]], [2.0, 0.5], rtol=1e-6)
    rng = np.random.default_rng(0)
    mus, variances = rng.normal(size=(7, 5)), rng.uniform(0.1, 3.0, size=(7, 5))
    mu, var = pearl.product_of_gaussians(jnp.asarray(mus), jnp.asarray(variances))
    # The product's density ∝ Π N(x; μ_n, σ²_n): precision-weighted mean, summed precisions.
    precision = np.sum(1 / variances, axis=0)
    np.testing.assert_allclose(var, 1 / precision, rtol=1e-5)
    np.testing.assert_allclose(mu, np.sum(mus / variances, axis=0) / precision, rtol=1e-5)
    # Accumulated online, one factor at a time (the protocol), it is the same Gaussian.
    post = pearl.Posterior.empty(5)
    for m, v in zip(mus, variances, strict=True):
        post = post.add(jnp.asarray(m), jnp.asarray(v))
    np.testing.assert_allclose(post.gaussian()[0], mu, rtol=1e-5)
    np.testing.assert_allclose(post.gaussian()[1], var, rtol=1e-5)
    # No factor yet (or only zero-weight ones): the prior N(0, I).
    empty = pearl.Posterior.empty(5).add(jnp.ones(5), jnp.ones(5), 0.0)
    np.testing.assert_array_equal(empty.gaussian()[0], 0.0)
    np.testing.assert_array_equal(empty.gaussian()[1], 1.0)


@pytest.mark.parametrize("mu, var", [(0.0, 1.0), (1.3, 0.2), (-2.0, 4.0)])
def test_kl_to_standard_normal_matches_numerical_integration(mu, var):
    x = np.linspace(mu - 12 * math.sqrt(var), mu + 12 * math.sqrt(var), 200_001)
    p = np.exp(-((x - mu) ** 2) / (2 * var)) / math.sqrt(2 * math.pi * var)
    log_q = -(x**2) / 2 - 0.5 * math.log(2 * math.pi)
    numeric = np.trapezoid(p * (np.log(p + 1e-300) - log_q), x)
    got = float(pearl.kl_to_standard_normal(jnp.asarray([mu]), jnp.asarray([var])))
    assert got == pytest.approx(numeric, rel=1e-4, abs=1e-6)
    two = pearl.kl_to_standard_normal(jnp.asarray([mu, mu]), jnp.asarray([var, var]))
    assert float(two) == pytest.approx(2 * got, rel=1e-6)  # summed over latent dimensions


# Buffers and collection (PEARL's rl_algorithm) ---------------------------------------------------

META_TINY = {
    "env": "cartpole_fl_ood", "actor": "pearl", "iterations": 1, "updates_per_iteration": 2,
    "meta_batch": 3, "batch_size": 8, "context_batch": 6, "initial_steps": 30,
    "tasks_per_iteration": 3, "prior_steps": 20, "posterior_steps": 25, "task_buffer_size": 200,
    "critic_hidden": [16], "encoder_hidden": [16], "pearl_hidden": [16], "eval_steps": 40,
    "eval_runs": 2,
}  # fmt: skip


@pytest.fixture(scope="module")
def meta_trainer():
    trainer = Trainer(config_lib.from_mapping(META_TINY))
    state = jax.jit(trainer.init)(jax.random.PRNGKey(0))
    warm = jax.jit(trainer.warmup)(state)
    return trainer, warm


def test_warmup_fills_both_buffers_of_every_training_task(meta_trainer):
    trainer, warm = meta_trainer
    n = trainer.task_set.num_train
    np.testing.assert_array_equal(warm.buffer.size, [30] * n)
    np.testing.assert_array_equal(warm.encoder_buffer.size, [30] * n)
    assert int(warm.env_steps) == 30 * n
    # The tasks really differ: a force of 12 N moves the cart unlike one of 8 N.
    obs = np.asarray(warm.buffer.data.next_obs[:, :30])
    assert not np.allclose(obs[0], obs[1])


def test_an_iteration_clears_the_visited_encoder_buffers_and_refills_them_with_prior_data(
    meta_trainer,
):
    trainer, warm = meta_trainer
    collect = jax.jit(lambda s, k: trainer.task_set.collect_tasks(trainer.actor, s, k))
    state, _ = collect(warm, jax.random.PRNGKey(4))
    rl_size, enc_size = np.asarray(state.buffer.size), np.asarray(state.encoder_buffer.size)
    visited = np.flatnonzero(rl_size > 30)
    assert len(visited) == 3  # distinct tasks
    np.testing.assert_array_equal(rl_size[visited], 30 + 20 + 25)  # prior + posterior
    np.testing.assert_array_equal(enc_size[visited], 20)  # cleared, then prior data only
    others = np.setdiff1d(np.arange(trainer.task_set.num_train), visited)
    np.testing.assert_array_equal(rl_size[others], 30)
    np.testing.assert_array_equal(enc_size[others], 30)
    for t in visited:  # the encoder buffer holds exactly the prior phase of the RL buffer
        np.testing.assert_array_equal(
            state.encoder_buffer.data.obs[t, :20], state.buffer.data.obs[t, 30:50]
        )
    np.testing.assert_array_equal(
        state.encoder_buffer.data.obs[others[0], :30], warm.encoder_buffer.data.obs[others[0], :30]
    )
    assert int(state.env_steps) == int(warm.env_steps) + 3 * 45


def test_one_meta_update_trains_the_encoder_through_the_critic(meta_trainer):
    trainer, warm = meta_trainer
    tau, l_min = trainer.iteration.schedules(jnp.asarray(0))
    new, metrics = jax.jit(trainer.sac.update)(warm, jax.random.PRNGKey(1), tau, l_min)
    assert np.isfinite(float(metrics["kl"])) and float(metrics["kl"]) >= 0
    moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), new.encoder, warm.encoder)
    assert max(jax.tree.leaves(moved)) > 0
    for tree in (new.actor, new.critic):
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(tree))


def _hyper_weight_count(obs: int, act: int, latent: int, trunk, hidden: int = 256) -> int:
    """Weights of HypeRL's hypernetwork, counted by hand: z → trunk[0], two residual blocks (two
    square layers each) per width with a projection between widths, then the six heads."""
    dense = lambda i, o: i * o + o  # noqa: E731
    n = dense(latent, trunk[0])
    for prev, width in zip((trunk[0], *trunk), trunk, strict=False):
        n += (dense(prev, width) if prev != width else 0) + 4 * dense(width, width)
    heads = obs * hidden + hidden + 2 * (hidden * act + act)
    return n + dense(trunk[-1], heads)  # six Dense heads = one of their summed width


@pytest.mark.parametrize(("trunk", "expected_millions"), [((256, 512, 1024), 10.9), ((256,), 1.45)])
def test_hyper_network_has_hyperl_weight_count_and_a_configurable_trunk(trunk, expected_millions):
    """hopper_params' sizes (11 observations, 3 actions, latent 5): HypeRL's trunk gives the
    10.9M weights that make Hyper ~3x PEARL per iteration here; one width of 256 gives ~1.45M."""
    cfg = config_lib.from_mapping(
        {"env": "hopper_params", "actor": "hyper", "hyper_trunk": list(trunk)}
    )
    trainer = Trainer(cfg)
    params = trainer.actor.init(jax.random.PRNGKey(0))
    count = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params))
    obs, act, latent = trainer.env.obs_dim, trainer.env.action_dim, trainer.actor.latent_dim
    assert (obs, act) == (11, 3)
    assert count == _hyper_weight_count(obs, act, latent, trunk)
    assert count / 1e6 == pytest.approx(expected_millions, abs=0.05)
    weights = trainer.actor.generate(params, jnp.ones(latent))
    assert weights["w1"].shape == (obs, 256) and weights["w_mean"].shape == (256, act)
    mean, log_std, _ = trainer.actor.mean_and_log_std(
        trainer.actor.policy(params, weights), None, jnp.ones(obs)
    )
    assert mean.shape == log_std.shape == (act,) and bool(jnp.isfinite(mean).all())


def test_one_hyper_update_moves_the_hypernetwork_and_the_encoder():
    trainer = Trainer(
        config_lib.from_mapping({**META_TINY, "actor": "hyper", "hyper_trunk": [16, 32]})
    )
    state = jax.jit(trainer.warmup)(jax.jit(trainer.init)(jax.random.PRNGKey(0)))
    tau, l_min = trainer.iteration.schedules(jnp.asarray(0))
    new, metrics = jax.jit(trainer.sac.update)(state, jax.random.PRNGKey(1), tau, l_min)
    assert np.isfinite(float(metrics["actor_loss"])) and np.isfinite(float(metrics["kl"]))
    for old_tree, new_tree in ((state.actor, new.actor), (state.encoder, new.encoder)):
        moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), new_tree, old_tree)
        assert max(jax.tree.leaves(moved)) > 0


# The protocol on a probe env ---------------------------------------------------------------


@struct.dataclass
class ProbeParams:
    goal: jax.Array


@struct.dataclass
class ProbeState:
    t: jax.Array


class ProbeEnv(Environment):
    """Reward −(a − g)²: the best action is the task's goal g, whatever the observation, and only
    the transition's next observation (which shows g) tells the tasks apart."""

    name, obs_dim, action_dim, horizon = "probe", 1, 1, 10
    action_low, action_high = np.array([-1.0]), np.array([1.0])

    @property
    def default_params(self):
        return ProbeParams(jnp.asarray(0.0))

    def reset(self, key, params):
        return jnp.zeros(1), ProbeState(jnp.zeros((), jnp.int32))

    def step(self, key, state, action, params):
        t = state.t + 1
        reward = -((action[0] - params.goal) ** 2)
        done = t >= self.horizon
        return jnp.full(1, params.goal), ProbeState(t), reward, jnp.asarray(False), done, {}


class ProbeEncoder:
    """Each transition's factor is N(s'[0], 1e-4): the posterior mean is the goal."""

    latent_dim = 2

    def factors(self, params, t: Transition):
        mu = jnp.stack([t.next_obs[0], jnp.zeros(())])
        return mu, jnp.full(2, 1e-4)


@dataclass(frozen=True)
class ProbeActor(Actor):
    """Acts a = z[0] (deterministically): only a good z scores well."""

    def policy(self, params, part):
        return part  # the task policy is z itself

    def mean_and_log_std(self, policy, mask, obs):
        mean = jnp.arctanh(jnp.clip(policy[:1], -0.999, 0.999))
        return mean, jnp.zeros(1), jnp.zeros(())


def test_protocol_adapts_to_the_task_from_its_own_context():
    env, actor = ProbeEnv(), ProbeActor(config_lib.Config(), 1, 1, 2)
    goals = jnp.asarray([-0.6, 0.1, 0.7])

    def one(goal, key):
        return rollout.adapt_and_evaluate(
            env, actor, ProbeEncoder(), {}, None, ProbeParams(goal), key, 30, 2
        )

    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    out = jax.jit(jax.vmap(one))(goals, keys)
    np.testing.assert_array_equal(out.trajectories, [3, 3, 3])  # 30 steps of 10-step episodes
    # Trajectories 1 and 2 act on prior samples; the 3rd on the posterior of the 20 transitions.
    np.testing.assert_allclose(out.z[:, 0], goals, atol=0.02)
    assert np.all(np.asarray(out.final_return) > -0.1)
    assert np.mean(np.asarray(out.first_return)) < -1.0


# CSP: the exported formula is the generated network at its z -----------------------------------


def test_csp_export_equals_the_generated_network_at_z(tmp_path):
    cfg = config_lib.from_mapping({"env": "cartpole_fl_ood", "layout": "csp"})
    actor = GeneratedSymbolic(
        config_lib.view(PolicyConfig, cfg), obs_dim=4, action_dim=1, latent_dim=5
    )
    params = actor.init(jax.random.PRNGKey(0))
    # Ψ's last bias decides most paths whatever z is: a sparse formula that exports quickly.
    rng = np.random.default_rng(1)
    bias = params["psi"]["params"]["members"]["_TorchDense_2"]["bias"]
    keep = rng.random(bias.shape) < 0.04
    last_inputs = 4 + sum(len(ops) for ops in actor.symbolic.layout.layers)
    keep[:, -last_inputs : -last_inputs + 4] = True  # the output sees the observation directly
    params["psi"]["params"]["members"]["_TorchDense_2"]["bias"] = jnp.where(keep, 8.0, -8.0)
    z = jax.random.normal(jax.random.PRNGKey(2), (5,))
    policy = jax.tree.map(np.asarray, actor.at(params, z))
    mask = actor.eval_mask(policy)
    exprs = ex.network_expressions(actor.symbolic, policy["mean"], policy["probs"])
    source = ex.to_python(exprs, 4, np.array([-1.0]), np.array([1.0]))
    path = tmp_path / "policy.py"
    path.write_text(source)
    module = reference_eval.load_policy(path)
    obs = rng.normal(scale=0.3, size=(32, 4)).astype(np.float32)
    network = jax.vmap(actor.deterministic, (None, None, 0))(policy, mask, obs)
    got = np.array([module.act(o) for o in obs])
    np.testing.assert_allclose(got, np.asarray(network), atol=1e-5)
    assert len(np.unique(np.round(got, 4))) > 1


def test_csp_bias_l1_adds_scale_times_mean_abs_generated_bias():
    """``bias_l1_scale`` on CSP: the extra loss grows by scale · mean |Φ_b(z)|, and its gradient
    reaches Φ_b's params (the generator, not a stored bias)."""
    base = {"env": "cartpole_fl_ood", "layout": "csp"}
    plain = GeneratedSymbolic(
        config_lib.view(PolicyConfig, config_lib.from_mapping(base)),
        obs_dim=4,
        action_dim=1,
        latent_dim=5,
    )
    cfg = config_lib.from_mapping({**base, "bias_l1_scale": 2.0})
    actor = GeneratedSymbolic(
        config_lib.view(PolicyConfig, cfg), obs_dim=4, action_dim=1, latent_dim=5
    )
    assert actor.has_extra_loss
    params = actor.init(jax.random.PRNGKey(0))
    z = jax.random.normal(jax.random.PRNGKey(1), (5,))
    policy = actor.at(params, z)
    biases = np.concatenate([np.asarray(b).ravel() for b in policy["mean"]["b"]])
    assert np.mean(np.abs(biases)) > 1e-3  # Φ_b(z) is not 0 at init
    _, with_l1 = actor.regularizers(policy, jnp.asarray(0.01))
    _, without = plain.regularizers(policy, jnp.asarray(0.01))
    np.testing.assert_allclose(with_l1 - without, 2.0 * np.mean(np.abs(biases)), rtol=1e-5)

    def extra(p):
        return (
            actor.regularizers(actor.at(p, z), 0.01)[1]
            - plain.regularizers(plain.at(p, z), 0.01)[1]
        )

    grads = jax.grad(extra)(params)
    assert any(np.any(np.asarray(g) != 0) for g in jax.tree.leaves(grads["phi_b"]))
    for name in ("phi_w", "psi"):
        assert all(np.all(np.asarray(g) == 0) for g in jax.tree.leaves(grads[name]))


def test_csp_l1_ablation_has_no_selector_every_path_on_and_l1_on_generated_weights():
    """``selector: l1`` on CSP is the paper's CSP_L1: no Ψ, every mask all ones (train, collect,
    export), and L_select's place taken by Σ|Φ_w(z)|, whose gradient reaches Φ_w. (It used to
    be ignored: CSP_l1 trained CSP.)"""
    cfg = config_lib.from_mapping({"env": "cartpole_fl_ood", "layout": "csp", "selector": "l1"})
    actor = GeneratedSymbolic(
        config_lib.view(PolicyConfig, cfg), obs_dim=4, action_dim=1, latent_dim=5
    )
    assert not actor.uses_selector
    params = actor.init(jax.random.PRNGKey(0))
    assert "psi" not in params
    z = jax.random.normal(jax.random.PRNGKey(1), (5,))
    policy = actor.at(params, z)
    ones = [np.ones(np.shape(w)) for w in policy["mean"]["w"]]
    for mask in (
        actor.train_mask(jax.random.PRNGKey(2), policy, 0.5),
        actor.collect_mask(jax.random.PRNGKey(3), policy),
    ):
        for m, o in zip(mask, ones, strict=True):
            np.testing.assert_array_equal(m, o)
    exported = actor.eval_mask(policy)
    for m, w in zip(exported, policy["mean"]["w"], strict=True):
        np.testing.assert_array_equal(np.asarray(m) == 1, np.abs(np.asarray(w)) > 1e-3)
    select, _ = actor.regularizers(policy, jnp.asarray(0.01))
    weights = sum(float(np.sum(np.abs(np.asarray(w)))) for w in policy["mean"]["w"])
    np.testing.assert_allclose(float(select), weights, rtol=1e-5)
    assert float(actor.l0_ratio(policy)) == 1.0
    grads = jax.grad(lambda p: actor.regularizers(actor.at(p, z), 0.01)[0])(params)
    assert any(np.any(np.asarray(g) != 0) for g in jax.tree.leaves(grads["phi_w"]))


# The single-task case after the restructure ------------------------------------------------------


def test_single_task_run_is_the_pre_restructure_one():
    """One iteration of the tiny config from the same key as 76fcfa2 (the last commit before the
    task axis, policy kinds and PEARL machinery) gives its learner; recorded on a 2-core x86 CPU
    there (bitwise equal on that machine; other CPUs may round XLA's kernels differently)."""
    recorded = json.loads((DATA / "single_task_76fcfa2.json").read_text())
    cfg = config_lib.from_mapping({**TINY, **recorded["config"]})
    trainer = Trainer(cfg)
    key = jax.random.split(jax.random.PRNGKey(0), 1)  # 76fcfa2's key for seed 0 of one seed
    state = jax.jit(jax.vmap(trainer.init))(key)
    state, _ = trainer.compiled_chunk(1)(state)
    actor = jax.device_get(state.actor)
    close = {"rtol": 1e-4, "atol": 1e-6}
    np.testing.assert_allclose(
        np.asarray(actor["mean"]["w"][-1]).ravel()[:40], recorded["mean_w_last"], **close
    )
    np.testing.assert_allclose(
        np.asarray(actor["mean"]["b"][0]).ravel(), recorded["mean_b_0"], **close
    )
    np.testing.assert_allclose(
        np.asarray(jax.tree.leaves(state.critic)[1]).ravel()[:40],
        recorded["critic_q1_kernel0"],
        **close,
    )
    assert float(np.asarray(state.log_alpha)[0]) == pytest.approx(recorded["log_alpha"], rel=1e-4)


def test_an_mjx_family_first_built_inside_a_trace_holds_no_tracer():
    """``benchmarks/meta_cost.py`` first touches the trainer's env inside a jitted warm-up: the
    cached MJX model must be concrete arrays, not that trace's tracers (which leaked into the
    next trace as an UnexpectedTracerError before the fix). The MJX model is built on first use
    (the native backend never needs it), so it is first asked for inside the trace here."""
    trainer = Trainer(config_lib.resolve(env="invdoublepend_params", physics="mjx"))
    jax.jit(lambda x: x + trainer.env.obs_dim + trainer.env._mx.nq)(0.0)
    leaves = jax.tree.leaves(trainer.env._mx)
    assert leaves
    assert not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)


@pytest.mark.slow  # the shipped lunarlander_params runs, 7-25 min each on 2 cores
@pytest.mark.parametrize(("actor", "seed"), [("symbolic", 2), ("pearl", 0), ("pearl", 1)])
def test_lunarlander_params_stays_bounded_with_the_shipped_critics(actor, seed, tmp_path):
    """The seeds that blew up late before LayerNorm critics (Q → −2200…−6869, KL → 1248…6870,
    critic loss → 2e5 in one iteration) stay bounded through the whole shipped budget."""
    import subprocess
    import sys

    from espl_jax import rundir

    run_dir = tmp_path / "run"
    subprocess.run(
        [sys.executable, "-m", "espl_jax.train", "--env", "lunarlander_params", "--actor", actor,
         "--seed", str(seed), "--out", str(run_dir), "--no-progress"],
        check=True,
    )  # fmt: skip
    rows = [r for r in rundir.read_metrics(run_dir / rundir.METRICS_FILE) if r["iteration"] >= 10]
    assert max(r["critic_loss"] for r in rows) < 2e4
    assert min(r["q"] for r in rows) > -1000
    assert max(r["kl"] for r in rows) < 200
