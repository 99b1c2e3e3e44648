"""The critic options (config ``critic``, ``critic_layer_norm``): CrossQ's batch renormalisation
against a numpy reference, CrossQ's critic loss and update against their definitions, and that
the default critic is still the plain twin-Q MLP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TINY_MLP

from espl_jax import config as config_lib
from espl_jax import replay
from espl_jax.learner import Trainer
from espl_jax.networks import BatchRenorm, TwinQ
from espl_jax.policies import MLPActor, PolicyConfig
from espl_jax.sac import SAC, SACConfig, TrainState
from espl_jax.task_sets import SingleTask


def _renorm_reference(x, mean, var, steps, momentum, warmup, eps=1e-3, r_max=3.0, d_max=5.0):
    """numpy batch renormalisation (Ioffe 2017, Algorithm 1) with scale 1 and bias 0."""
    mu_b, var_b = x.mean(0), x.var(0)
    std_b, std = np.sqrt(var_b + eps), np.sqrt(var + eps)
    x_hat = (x - mu_b) / std_b
    if steps >= warmup:
        r = np.clip(std_b / std, 1 / r_max, r_max)
        d = np.clip((mu_b - mean) / std, -d_max, d_max)
        x_hat = x_hat * r + d
    return x_hat, momentum * mean + (1 - momentum) * mu_b, momentum * var + (1 - momentum) * var_b


@pytest.mark.parametrize("steps", [0.0, 5.0])  # before and after the warm-up of 5 updates
def test_batch_renorm_matches_numpy(steps):
    rng = np.random.default_rng(0)
    x = rng.normal(2.0, 3.0, size=(64, 3)).astype(np.float32)
    module = BatchRenorm(momentum=0.9, warmup=5)
    variables = module.init(jax.random.PRNGKey(0), jnp.zeros((3,)))
    mean, var = np.array([0.5, -1.0, 4.0]), np.array([2.0, 0.1, 30.0])  # far from the batch's
    variables["batch_stats"].update(
        mean=jnp.asarray(mean, jnp.float32),
        var=jnp.asarray(var, jnp.float32),
        steps=jnp.asarray(steps, jnp.float32),
    )
    y, updated = module.apply(variables, jnp.asarray(x), train=True, mutable=["batch_stats"])
    want, want_mean, want_var = _renorm_reference(x.astype(np.float64), mean, var, steps, 0.9, 5)
    np.testing.assert_allclose(y, want, atol=2e-5)
    stats = updated["batch_stats"]
    np.testing.assert_allclose(stats["mean"], want_mean, rtol=1e-5)
    np.testing.assert_allclose(stats["var"], want_var, rtol=1e-5)
    assert float(stats["steps"]) == steps + 1
    # Evaluation mode uses the running statistics and changes nothing.
    y_eval = module.apply(variables, jnp.asarray(x))
    np.testing.assert_allclose(y_eval, (x - mean) / np.sqrt(var + 1e-3), rtol=1e-5, atol=1e-5)


def test_the_default_critic_is_a_plain_twin_mlp_and_the_options_add_their_layers():
    args = (jax.random.PRNGKey(0), jnp.zeros(4), jnp.zeros(1), jnp.zeros(0))
    plain = TwinQ((8, 8)).init(*args)
    assert set(plain) == {"params"}
    assert sorted(plain["params"]["q1"]) == ["Dense_0", "Dense_1", "Dense_2"]
    norm = TwinQ((8, 8), layer_norm=True).init(*args)
    assert sorted(norm["params"]["q1"]) == [
        "Dense_0", "Dense_1", "Dense_2", "LayerNorm_0", "LayerNorm_1",
    ]  # fmt: skip
    # The plain layers are initialised exactly as without the option.
    np.testing.assert_array_equal(
        norm["params"]["q1"]["Dense_1"]["kernel"], plain["params"]["q1"]["Dense_1"]["kernel"]
    )
    crossq = TwinQ((8, 8), renorm=(0.99, 100)).init(*args)
    assert sorted(crossq["batch_stats"]["q2"]) == [
        "BatchRenorm_0",
        "BatchRenorm_1",
        "BatchRenorm_2",
    ]


# The update's view of a single task (its batches, its (0,) latent): no env needed.
ONE_TASK = SingleTask(env=None, steps_per_iteration=0, buffer_capacity=0, exploration_correlation=0)


def _crossq_state(**overrides):
    cfg = config_lib.from_mapping(
        {"actor": "mlp", "critic": "crossq", "critic_hidden": [16, 16], "std_hidden": [8],
         "mlp_actor_hidden": [8], "crossq_warmup": 0, **overrides}
    )  # fmt: skip
    actor = MLPActor(config_lib.view(PolicyConfig, cfg), obs_dim=4, action_dim=1)
    sac = SAC(config_lib.view(SACConfig, cfg), actor, ONE_TASK)
    learner = sac.init_learner(jax.random.PRNGKey(0))
    learner["log_alpha"] = jnp.asarray(-0.7)
    state = TrainState(
        **learner, buffer=None, encoder_buffer=None, rollout=None, key=None,
        iteration=None, env_steps=None, episodes=None,
    )  # fmt: skip
    rng = np.random.default_rng(1)
    size = 32
    batch = replay.Transition(
        jnp.asarray(rng.normal(size=(1, size, 4)), jnp.float32),
        jnp.asarray(rng.uniform(-1, 1, size=(1, size, 1)), jnp.float32),
        jnp.asarray(rng.normal(size=(1, size)), jnp.float32),
        jnp.asarray(rng.normal(size=(1, size, 4)), jnp.float32),
        jnp.asarray(rng.uniform(size=(1, size)) < 0.2),
    )
    return sac, state, batch


def test_crossq_loss_is_the_joint_pass_without_a_target_network():
    gamma = 0.9
    sac, state, batch = _crossq_state(gamma=gamma)
    key = jax.random.PRNGKey(3)
    loss, (_, _, stats) = jax.jit(sac.critic_loss)(state.critic, None, state, batch, None, key)

    # The definition, written out: the next actions from the same keys, then one forward pass
    # of the critics in training mode over [(s, a); (s', a')].
    k_mask, k_act = jax.random.split(key)
    size = batch.reward.shape[1]
    keys = jax.random.split(k_act, size)
    a2, log_prob, _ = jax.vmap(sac.actor.sample, (0, None, None, 0))(
        keys, state.actor, None, batch.next_obs[0]
    )
    q_all, updated = sac.critic.apply(
        state.critic,
        jnp.concatenate([batch.obs[0], batch.next_obs[0]]),
        jnp.concatenate([batch.action[0], a2]),
        jnp.zeros((0,)),
        train=True,
        mutable=["batch_stats"],
    )
    q, q2 = np.asarray(q_all[:size], np.float64), np.asarray(q_all[size:], np.float64)
    soft_next = q2.min(-1) - np.exp(-0.7) * np.asarray(log_prob)
    y = np.asarray(batch.reward[0]) + gamma * (1 - np.asarray(batch.terminated[0])) * soft_next
    np.testing.assert_allclose(loss, np.sum(np.mean((q - y[:, None]) ** 2, 0)), rtol=1e-5)
    jax.tree.map(
        lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5), stats, updated["batch_stats"]
    )
    assert abs(gamma * soft_next).max() > 1e-3  # the bootstrap term matters


def test_crossq_update_keeps_running_statistics_and_no_target_network():
    sac, state, batch = _crossq_state()
    buffer = replay.insert(replay.init(1, 64, 4, 1), jnp.zeros((1,), jnp.int32), batch)
    state = state.replace(buffer=buffer)
    new, metrics = jax.jit(sac.update)(state, jax.random.PRNGKey(5), 1.0, 0.0)
    assert np.isfinite(float(metrics["critic_loss"]))
    # The critic moved; its statistics are the forward pass's (steps counted once per update);
    # the target network, which CrossQ does not have, did not move.
    stats = new.critic["batch_stats"]["q1"]["BatchRenorm_0"]
    assert float(stats["steps"]) == 1.0
    assert not np.allclose(stats["mean"], 0.0)
    jax.tree.map(np.testing.assert_array_equal, new.target_critic, state.target_critic)
    kernel = ("params", "q1", "Dense_0", "kernel")
    before = state.critic[kernel[0]][kernel[1]][kernel[2]][kernel[3]]
    after = new.critic[kernel[0]][kernel[1]][kernel[2]][kernel[3]]
    assert not np.array_equal(before, after)


def test_a_tiny_run_trains_with_the_critic_options():
    # Both options at once: one compile instead of two (they touch different layers).
    cfg = config_lib.from_mapping({**TINY_MLP, "critic": "crossq", "critic_layer_norm": True})
    trainer = Trainer(cfg)
    state, metrics = trainer.compiled_chunk(cfg.iterations)(trainer.init_seeds())
    assert np.all(np.isfinite(np.asarray(metrics["critic_loss"])))
    assert int(np.asarray(state.iteration).max()) == cfg.iterations
