"""Neural networks around the policies: critics, std networks, PEARL's encoder, CSP's generators,
PEARL's and Hyper's policy networks.

All are flax Linen modules used functionally (``init``/``apply`` on explicit params). Sizes are
the paper's (App. C, D) and the reference code's:

- ``TwinQ``: two Q(s, a[, z]) MLPs (SAC's clipped double-Q; 256×2 single-task, 300×3 meta-RL),
  optionally with LayerNorm after each hidden layer, or with CrossQ's batch renormalisation
  (``BatchRenorm``) on the input and after each hidden layer.
- ``MLP``: ReLU MLP; the std network F(s) (64×3, authors' code) and PEARL's context encoder
  (200×3 on (s, a, r[, s']) → μ and pre-softplus σ² of the latent, PEARL ``MlpEncoder``).
- ``EnsembleMLP``: one independent MLP per action dimension (the authors' ``EnsembleMLP``):
  CSP's parameter generator Φ(z) → (w, b) and path-probability generator Ψ(z) → logits
  (z → 64 → 64 → n, uniform ±1/√fan-in init, Ψ's last bias 3.0 so σ(3) ≈ 0.95 of the paths start
  active, paper App. C.2).
- ``HyperNetwork``: Hyper (Sarafian et al. 2021; keynans/HypeRL) — z → 256 → 2 ResBlocks → 512 →
  2 ResBlocks → 1024 → 2 ResBlocks (the widths configurable), with heads that generate the weights
  of a one-hidden-layer (256) policy on s with separate μ and log σ outputs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


class BatchRenorm(nn.Module):
    """Batch renormalisation (Ioffe 2017) as CrossQ uses it (Bhatt et al., ICLR 2024).

    Training (``train=True``): normalise with the batch's statistics over every axis but the
    last, corrected towards the running ones once ``warmup`` training calls have passed:
    x̂ = (x − μ_B)/σ_B · r + d with r = clip(σ_B/σ, 1/r_max, r_max) and
    d = clip((μ_B − μ)/σ, −d_max, d_max), both without gradient (plain batch norm before);
    then the running (μ, σ²) move towards (μ_B, σ²_B) by 1 − ``momentum``. Otherwise normalise
    with the running statistics. The statistics live in the ``batch_stats`` collection, all
    float32 (the step count too) so that a gradient over the whole variable dict is defined
    (and zero for them). r_max 3, d_max 5 and ε 1e-3 are sbx's.
    """

    momentum: float = 0.99
    warmup: int = 100_000
    epsilon: float = 1e-3
    r_max: float = 3.0
    d_max: float = 5.0

    @nn.compact
    def __call__(self, x: jax.Array, train: bool = False) -> jax.Array:
        features = x.shape[-1]
        mean = self.variable("batch_stats", "mean", jnp.zeros, (features,), jnp.float32)
        var = self.variable("batch_stats", "var", jnp.ones, (features,), jnp.float32)
        steps = self.variable("batch_stats", "steps", jnp.zeros, (), jnp.float32)
        scale = self.param("scale", nn.initializers.ones, (features,))
        bias = self.param("bias", nn.initializers.zeros, (features,))
        if train and not self.is_initializing():
            axes = tuple(range(x.ndim - 1))
            batch_mean, batch_var = jnp.mean(x, axes), jnp.var(x, axes)
            batch_std = jnp.sqrt(batch_var + self.epsilon)
            running_std = jnp.sqrt(var.value + self.epsilon)
            r = jax.lax.stop_gradient(
                jnp.clip(batch_std / running_std, 1.0 / self.r_max, self.r_max)
            )
            d = jax.lax.stop_gradient(
                jnp.clip((batch_mean - mean.value) / running_std, -self.d_max, self.d_max)
            )
            x_hat = (x - batch_mean) / batch_std
            x_hat = jnp.where(steps.value >= self.warmup, x_hat * r + d, x_hat)
            m = self.momentum
            mean.value = m * mean.value + (1 - m) * jax.lax.stop_gradient(batch_mean)
            var.value = m * var.value + (1 - m) * jax.lax.stop_gradient(batch_var)
            steps.value = steps.value + 1.0
        else:
            x_hat = (x - mean.value) / jnp.sqrt(var.value + self.epsilon)
        return x_hat * scale + bias


class MLP(nn.Module):
    """ReLU MLP with a linear output layer; optionally LayerNorm before each hidden ReLU
    (``layer_norm``), or batch renormalisation on the input and after each hidden ReLU
    (``renorm``: (momentum, warmup), sbx's CrossQ critic). Without either, the parameters are
    exactly a plain MLP's (Dense_0 … Dense_n)."""

    hidden: Sequence[int]
    out: int
    layer_norm: bool = False
    renorm: tuple[float, int] | None = None

    @nn.compact
    def __call__(self, x: jax.Array, train: bool = False) -> jax.Array:
        def normalise(x):
            if self.renorm is None:
                return x
            momentum, warmup = self.renorm
            return BatchRenorm(momentum, warmup)(x, train)

        x = normalise(x)
        for width in self.hidden:
            x = nn.Dense(width)(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = normalise(nn.relu(x))
        return nn.Dense(self.out)(x)


class TwinQ(nn.Module):
    """Two independent Q(s, a, z) MLPs (clipped double-Q of SAC). Returns shape (..., 2).

    ``z`` is the task latent of meta-RL, (..., latent); single-task runs pass a (0,)-sized z,
    which leaves the inputs (and so the parameters) exactly those of Q(s, a). ``train`` matters
    only with ``renorm`` (batch statistics, which the caller must then mark mutable).
    """

    hidden: Sequence[int]
    layer_norm: bool = False
    renorm: tuple[float, int] | None = None

    @nn.compact
    def __call__(
        self, obs: jax.Array, action: jax.Array, z: jax.Array, train: bool = False
    ) -> jax.Array:
        z = jnp.broadcast_to(z, (*obs.shape[:-1], z.shape[-1]))
        x = jnp.concatenate([obs, action, z], axis=-1)
        q1 = MLP(self.hidden, 1, self.layer_norm, self.renorm, name="q1")(x, train)
        q2 = MLP(self.hidden, 1, self.layer_norm, self.renorm, name="q2")(x, train)
        return jnp.concatenate([q1, q2], axis=-1)


def _fan_in_uniform(fan_in: int):
    """U(−1/√fan_in, 1/√fan_in), torch's and the authors' ``EnsembleLinearLayer`` init."""
    bound = 1.0 / math.sqrt(fan_in)

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


class _TorchDense(nn.Module):
    features: int
    last_bias: float | None = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        init = _fan_in_uniform(x.shape[-1])
        kernel = self.param("kernel", init, (x.shape[-1], self.features))
        if self.last_bias is None:
            bias = self.param("bias", init, (self.features,))
        else:
            bias = self.param("bias", nn.initializers.constant(self.last_bias), (self.features,))
        return x @ kernel + bias


class _GeneratorMLP(nn.Module):
    hidden: Sequence[int]
    out: int
    last_bias: float | None = None

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        for width in self.hidden:
            z = nn.relu(_TorchDense(width)(z))
        return _TorchDense(self.out, self.last_bias)(z)


class EnsembleMLP(nn.Module):
    """``members`` independent MLPs z → hidden → out, one per action dimension: (L,) → (A, out)."""

    members: int
    hidden: Sequence[int]
    out: int
    last_bias: float | None = None

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        ensemble = nn.vmap(
            _GeneratorMLP,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            axis_size=self.members,
        )
        return ensemble(self.hidden, self.out, self.last_bias, name="members")(z)


class _ResBlock(nn.Module):
    """Pre-activation residual block: x + W2 relu(W1 relu(x)) (HypeRL ``ResBlock``)."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        width = x.shape[-1]
        h = nn.Dense(width)(nn.relu(x))
        return x + nn.Dense(width)(nn.relu(h))


class HyperNetwork(nn.Module):
    """z (L,) → the weights of a policy network s → 256 → (μ, log σ) (Sarafian et al. 2021).

    ``trunk``: the residual trunk's widths, two blocks at each (HypeRL's 256, 512, 1024 by
    default; the laptop MuJoCo configs may shrink it, ``Config.hyper_trunk``).

    Returns a dict {"w1": (obs, 256), "b1": (256,), "w_mean": (256, A), "b_mean": (A,),
    "w_log_std": (256, A), "b_log_std": (A,)}. The generated layers are scaled by
    1/√fan-in so the generated policy starts at the scale of a normally initialised one.
    """

    obs_dim: int
    action_dim: int
    hidden: int = 256
    trunk: Sequence[int] = (256, 512, 1024)

    @nn.compact
    def __call__(self, z: jax.Array) -> dict[str, jax.Array]:
        x = nn.Dense(self.trunk[0])(z)
        for width in self.trunk:
            if x.shape[-1] != width:
                x = nn.Dense(width)(x)
            x = _ResBlock()(_ResBlock()(x))
        x = nn.relu(x)
        n, h, a = self.obs_dim, self.hidden, self.action_dim

        def head(name: str, size: int, fan_in: int) -> jax.Array:
            return nn.Dense(size, name=name)(x) / math.sqrt(fan_in)

        return {
            "w1": head("w1", n * h, n).reshape(n, h),
            "b1": head("b1", h, n),
            "w_mean": head("w_mean", h * a, h).reshape(h, a),
            "b_mean": head("b_mean", a, h),
            "w_log_std": head("w_log_std", h * a, h).reshape(h, a),
            "b_log_std": head("b_log_std", a, h),
        }


def generated_policy(weights: dict[str, jax.Array], obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Hyper's generated network on one observation: (μ, log σ), each (A,)."""
    h = nn.relu(obs @ weights["w1"] + weights["b1"])
    return h @ weights["w_mean"] + weights["b_mean"], h @ weights["w_log_std"] + weights[
        "b_log_std"
    ]
