"""The probabilistic path selector (ESPL paper §3.2, Algorithm 1) and its L1 ablation.

One probability ``p_i`` per maskable weight, stored in a pytree shaped like ``params["w"]``.
``p`` starts at exactly 1.0 and is projected back onto [0, 1] after every optimizer step
(App. C.1); it is never clipped inside a loss, so its gradient at the boundary is the full one
(``jnp.clip`` would pass only half of it at a tie, unlike ``torch.clamp``).

- Training: a gumbel-sigmoid relaxation with a straight-through hard threshold at 0.5 (Eq. 4).
- Collection: one Bernoulli(p) mask per collection iteration.
- Export and deterministic evaluation: ``p > 0.5`` with weights ``|w| <= 1e-3`` dropped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Tree = list[jax.Array]

# Floor of p and 1 − p inside log(p / (1 − p)), as in the authors' code: the logit stays finite
# (≈ ±46) at p ∈ {0, 1}. Written as a max, not ``1 - p + eps``: under jit XLA may fold that sum to
# exactly 0 at p = 1 (the eps is below float32 resolution of 1), giving log(0) and NaN gradients.
LOGIT_EPS = 1e-20
# Weights this small are dropped from the exported formula (and from the deterministic policy).
EXPORT_WEIGHT_THRESHOLD = 1e-3
# Temperature reached at the end of the schedule (Table 5, "target temperature").
TARGET_TEMPERATURE = 0.2


def init_probs(weights: Tree) -> Tree:
    """p = 1.0 for every weight: all paths start active."""
    return jax.tree.map(jnp.ones_like, weights)


def project_probs(probs: Tree) -> Tree:
    """Clip p back onto [0, 1] after an optimizer step (App. C.1)."""
    return jax.tree.map(lambda p: jnp.clip(p, 0.0, 1.0), probs)


def gumbel_sigmoid_mask(key: jax.Array, probs: Tree, tau: jax.Array | float) -> Tree:
    """Relaxed binary mask with a straight-through hard threshold (Eq. 4 and the ST trick).

    m_gs = sigmoid((log(p / (1 - p)) + g1 - g0) / tau) with g0, g1 ~ Gumbel(0, 1); the difference of
    two Gumbels is a standard logistic variable, which is what is sampled here.
    m = 1[m_gs >= 0.5] + (m_gs - stop_gradient(m_gs)): binary forward, sigmoid gradient backward.

    Args:
        key: PRNG key.
        probs: probabilities, a pytree of arrays in [0, 1].
        tau: temperature > 0.

    Returns:
        A pytree of masks shaped like ``probs`` with values in {0, 1}.
    """
    leaves, treedef = jax.tree.flatten(probs)
    keys = jax.random.split(key, len(leaves))
    masks = []
    for k, p in zip(keys, leaves, strict=True):
        soft = jax.nn.sigmoid((_logit(p) + jax.random.logistic(k, p.shape, p.dtype)) / tau)
        hard = (soft >= 0.5).astype(p.dtype)
        # Parenthesised so the forward value is exactly the hard mask: (s - sg(s)) == 0.
        masks.append(hard + (soft - jax.lax.stop_gradient(soft)))
    return jax.tree.unflatten(treedef, masks)


def soft_gumbel_sigmoid_mask(key: jax.Array, probs: Tree, tau: jax.Array | float) -> Tree:
    """The relaxed mask m_gs itself, without the straight-through threshold (the authors' CSP
    code, ``hard_gum=False``): values in (0, 1), gradients through every path."""
    leaves, treedef = jax.tree.flatten(probs)
    keys = jax.random.split(key, len(leaves))
    masks = [
        jax.nn.sigmoid((_logit(p) + jax.random.logistic(k, p.shape, p.dtype)) / tau)
        for k, p in zip(keys, leaves, strict=True)
    ]
    return jax.tree.unflatten(treedef, masks)


def _logit(p: jax.Array) -> jax.Array:
    return jnp.log(jnp.maximum(p, LOGIT_EPS)) - jnp.log(jnp.maximum(1.0 - p, LOGIT_EPS))


def bernoulli_mask(key: jax.Array, probs: Tree) -> Tree:
    """m_i ~ Bernoulli(p_i): the mask used to collect data (§3.2, Algorithm 1 line 4)."""
    leaves, treedef = jax.tree.flatten(probs)
    keys = jax.random.split(key, len(leaves))
    masks = [jax.random.bernoulli(k, p).astype(p.dtype) for k, p in zip(keys, leaves, strict=True)]
    return jax.tree.unflatten(treedef, masks)


def deterministic_mask(
    probs: Tree, weights: Tree, weight_threshold: float = EXPORT_WEIGHT_THRESHOLD
) -> Tree:
    """The mask of the exported formula: p > 0.5 and |w| > threshold.

    The deterministic policy evaluated in JAX uses this same mask, so the printed formula is the
    policy that ran.
    """
    return jax.tree.map(
        lambda p, w: ((p > 0.5) & (jnp.abs(w) > weight_threshold)).astype(w.dtype),
        probs,
        weights,
    )


def ones_mask(weights: Tree) -> Tree:
    """All paths on: the mask of the L1 ablation, which has no selector."""
    return jax.tree.map(jnp.ones_like, weights)


def count(tree: Tree) -> int:
    """Number of entries in a pytree of arrays (N in L_select)."""
    return sum(leaf.size for leaf in jax.tree.leaves(tree))


def expected_l0(probs: Tree) -> jax.Array:
    """E_m~Bern(p) ||m||_0 = Σ p_i (§3.2)."""
    return sum(jnp.sum(p) for p in jax.tree.leaves(probs))


def select_loss(probs: Tree, l_min_fraction: jax.Array | float) -> jax.Array:
    """L_select = max(Σ p − l_min · N, 0), l_min a fraction of all N weights (Eq. 5)."""
    return jax.nn.relu(expected_l0(probs) - l_min_fraction * count(probs))


def l1_loss(weights: Tree) -> jax.Array:
    """Σ |w|: the L1 penalty that replaces the selector in the ESPL_l1 ablation (§4.5)."""
    return sum(jnp.sum(jnp.abs(w)) for w in jax.tree.leaves(weights))


def _progress(t: jax.Array | float, t_s: float) -> jax.Array:
    """1 − min(t, t_s) / t_s: 1 at the start of the schedule, 0 from t_s on."""
    return 1.0 - jnp.minimum(jnp.asarray(t, jnp.float32), t_s) / t_s


def temperature(
    t: jax.Array | float, t_s: float, tau_target: float = TARGET_TEMPERATURE
) -> jax.Array:
    """τ = (1 − τ_t)(1 − min(t, t_s)/t_s) + τ_t (Algorithm 1, line 3): linear from 1 to τ_t."""
    return (1.0 - tau_target) * _progress(t, t_s) + tau_target


def l_min_schedule(t: jax.Array | float, t_s: float, l_target: float) -> jax.Array:
    """l_min = l_t + (1 − l_t)(1 − min(t, t_s)/t_s)² (Algorithm 1, line 8), a fraction of N."""
    return l_target + (1.0 - l_target) * _progress(t, t_s) ** 2
