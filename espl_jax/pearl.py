"""PEARL's probabilistic context encoder (Rakelly et al. 2019; paper §4, Algorithm 2).

Each context transition c_n = (s, a, r[, s']) is encoded by an MLP into a Gaussian factor
N(μ_n, σ²_n) over the latent z (σ² = softplus of the second half of the output, floored at 1e-7
as in the reference code); the posterior is their product,

    σ² = 1 / Σ_n 1/σ²_n,   μ = σ² Σ_n μ_n/σ²_n,

and the encoder is regularised by KL(q(z|c) ‖ N(0, I)). The product only needs the two sums
Σ 1/σ²_n and Σ μ_n/σ²_n, which is how the evaluation protocol accumulates a context online
(``Posterior``), one transition at a time, without storing it.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
from flax import struct

from espl_jax.networks import MLP
from espl_jax.replay import Transition

VAR_FLOOR = 1e-7  # PEARL's clamp of σ²_n before the product (config posterior_var_floor)


@struct.dataclass
class Posterior:
    """Natural parameters of a product of Gaussian factors: Σ 1/σ²_n and Σ μ_n/σ²_n, (L,) each.

    ``precision == 0`` is "no factors yet"; ``gaussian`` then gives the prior N(0, I).
    """

    precision: jax.Array
    weighted_mean: jax.Array

    @classmethod
    def empty(cls, latent_dim: int) -> Posterior:
        return cls(jnp.zeros(latent_dim), jnp.zeros(latent_dim))

    def add(self, mu: jax.Array, var: jax.Array, weight: jax.Array | float = 1.0) -> Posterior:
        """Multiply in one factor N(μ, σ²) (L,); ``weight`` 0 leaves the posterior unchanged."""
        inv = weight / var
        return Posterior(self.precision + inv, self.weighted_mean + inv * mu)

    def gaussian(self) -> tuple[jax.Array, jax.Array]:
        """(μ, σ²) of the product, or of the prior N(0, I) when no factor was added."""
        empty = self.precision <= 0
        var = jnp.where(empty, 1.0, 1.0 / jnp.where(empty, 1.0, self.precision))
        return jnp.where(empty, 0.0, var * self.weighted_mean), var


def context_features(batch: Transition, use_next_obs: bool) -> jax.Array:
    """(…, 2n + m + 1) encoder input (s, a, r, s') — or (s, a, r) when the dynamics do not differ
    across tasks (PEARL's ``use_next_obs_in_context``, off for cheetah_vel_ood)."""
    parts = [batch.obs, batch.action, batch.reward[..., None]]
    if use_next_obs:
        parts.append(batch.next_obs)
    return jnp.concatenate(parts, axis=-1)


class Encoder:
    """The context encoder: an MLP (200×3 in the paper) to (μ, pre-softplus σ²) per transition."""

    def __init__(
        self,
        hidden: Sequence[int],
        latent_dim: int,
        use_next_obs: bool,
        var_floor: float = VAR_FLOOR,
    ):
        self.latent_dim = latent_dim
        self.use_next_obs = use_next_obs
        self.var_floor = var_floor
        self.net = MLP(tuple(hidden), 2 * latent_dim)

    def init(self, key: jax.Array, feature_dim: int):
        return self.net.init(key, jnp.zeros((feature_dim,)))

    def factors(self, params, context: Transition) -> tuple[jax.Array, jax.Array]:
        """Per-transition factors (μ_n, σ²_n), each (…, L), of a context (…, transition)."""
        out = self.net.apply(params, context_features(context, self.use_next_obs))
        mu, pre_var = out[..., : self.latent_dim], out[..., self.latent_dim :]
        return mu, jnp.maximum(jax.nn.softplus(pre_var), self.var_floor)

    def posterior(self, params, context: Transition) -> tuple[jax.Array, jax.Array]:
        """(μ, σ²) of q(z | c) for a context of N transitions (leading axis N)."""
        mu, var = self.factors(params, context)
        return product_of_gaussians(mu, var)


def product_of_gaussians(mu: jax.Array, var: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Product of N Gaussian factors (N, L) → (μ, σ²) (L,): PEARL's ``_product_of_gaussians``."""
    var = jnp.maximum(var, VAR_FLOOR)
    out_var = 1.0 / jnp.sum(1.0 / var, axis=0)
    return out_var * jnp.sum(mu / var, axis=0), out_var


def kl_to_standard_normal(mu: jax.Array, var: jax.Array) -> jax.Array:
    """KL(N(μ, diag σ²) ‖ N(0, I)) = ½ Σ (σ² + μ² − 1 − log σ²), summed over the last axis."""
    return 0.5 * jnp.sum(var + mu**2 - 1.0 - jnp.log(var), axis=-1)


def sample(key: jax.Array, mu: jax.Array, var: jax.Array) -> jax.Array:
    """z = μ + σ ε, reparameterised (gradients reach μ and σ²)."""
    return mu + jnp.sqrt(var) * jax.random.normal(key, mu.shape, mu.dtype)
