"""The densely connected symbolic network (ESPL paper §3.1, Fig. 1, App. A).

One network per action dimension. Layer ``l`` computes ``y_l = W_l x + b_l`` (Eq. 1) and feeds
the rows of ``y_l`` to its operators in order, each operator consuming ``arity`` consecutive rows
(Eq. 2). With dense links (§3.1, "Dense connectivity") layer ``l`` sees
``x = [s, x_1, ..., x_{l-1}]``; the last linear layer maps ``[s, x_1, ..., x_L]`` to one pre-tanh
output per action dimension.

The layout is data: a tuple of operator names per layer. Parameters of all action dimensions are
stacked on a leading axis and the forward is ``vmap``-ed over it, so one compiled function serves
any number of action dimensions.

Parameter pytree (``A`` action dims, ``L`` operator layers, final linear layer last)::

    {"w": [ (A, rows_1, in_1), ..., (A, rows_L, in_L), (A, 1, in_out) ],
     "b": [ (A, rows_1),       ..., (A, rows_L),       (A, 1)         ]}

Only the weights ``w`` are masked by the path selector; biases are never masked (authors' code).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import groupby

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax.operators import get_operator

Params = dict[str, list[jax.Array]]

ARRANGED_LAYERS: tuple[tuple[str, ...], ...] = (
    ("mul",) * 3,
    ("div",) * 3,
    ("log", "log", "exp", "exp", "sin", "sin", "cos", "cos"),
    ("log", "log", "exp", "exp", "sin", "sin", "cos", "cos"),
    ("mul", "div", "log", "exp"),
    ("mul", "div", "log", "exp"),
)


@dataclass(frozen=True)
class Layout:
    """Operator names per layer and whether layers are densely linked.

    Attributes:
        layers: one tuple of operator names per layer, in evaluation order.
        dense: if True, each layer sees the observation and all earlier layer outputs; otherwise
            only the previous layer's output (the "plain" structure of §3.1).
    """

    layers: tuple[tuple[str, ...], ...]
    dense: bool = True

    def __post_init__(self) -> None:
        if not self.layers or any(not ops for ops in self.layers):
            raise ValueError("a layout needs at least one layer and one operator per layer")
        for ops in self.layers:
            for name in ops:
                get_operator(name)  # raises a readable error for unknown names


# CSP's layouts (the authors' ``sym_arch.py``): 39·n + 379 weights per action dimension, and a
# five-layer variant with one ``cond`` operator per layer for cheetah_vel_ood (App. C.2).
CSP_LAYERS: tuple[tuple[str, ...], ...] = (
    ("mul",) * 3,
    ("mul",) * 3,
    ("div",) * 3,
    ("log", "exp", "sin", "sin", "sin", "cos", "cos", "cos"),
    ("mul", "div", "log", "exp"),
    ("mul", "div", "log", "exp"),
)
CSP_COND_LAYERS: tuple[tuple[str, ...], ...] = (
    ("mul",) * 3 + ("cond",),
    ("mul",) * 3 + ("cond",),
    ("div",) * 3 + ("cond",),
    ("log", "exp", "sin", "sin", "sin", "cos", "cos", "cos", "cond"),
    ("mul", "div", "log", "exp", "cond"),
)

LAYOUTS: dict[str, Layout] = {
    # The paper's arranged operators, used for every experiment (Fig. 1): 41·n + 496 weights.
    "arranged": Layout(ARRANGED_LAYERS),
    # Ablation ESPL_d: dense links, unarranged — every layer holds the same operator set.
    "dense": Layout((("mul", "div", "log", "exp", "sin", "cos"),) * 5),
    # Ablation ESPL_p: no dense links; identity units carry values to the next layer.
    "plain": Layout(tuple(("identity", "identity", *ops) for ops in ARRANGED_LAYERS), dense=False),
    "csp": Layout(CSP_LAYERS),
    "csp_cond": Layout(CSP_COND_LAYERS),
}


def get_layout(name: str) -> Layout:
    """Look a named layout up; unknown names raise ValueError listing the known layouts."""
    try:
        return LAYOUTS[name]
    except KeyError:
        raise ValueError(
            f"unknown network layout {name!r}; known layouts: {', '.join(sorted(LAYOUTS))}"
        ) from None


@dataclass(frozen=True)
class SymbolicNetwork:
    """A symbolic network for ``action_dim`` outputs of ``obs_dim`` observations.

    Frozen and hashable, so it can be closed over or passed as a static argument to ``jit``.
    """

    layout: Layout
    obs_dim: int
    action_dim: int

    @property
    def layer_shapes(self) -> tuple[tuple[int, int], ...]:
        """(rows, inputs) of each linear map, operator layers first, the output layer last."""
        shapes = []
        in_dim = self.obs_dim
        for ops in self.layout.layers:
            rows = sum(get_operator(name).arity for name in ops)
            shapes.append((rows, in_dim))
            in_dim = in_dim + len(ops) if self.layout.dense else len(ops)
        shapes.append((1, in_dim))
        return tuple(shapes)

    @property
    def num_weights(self) -> int:
        """Maskable weights (paths) per action dimension; 41·n + 496 for the arranged layout."""
        return sum(rows * cols for rows, cols in self.layer_shapes)

    @property
    def num_biases(self) -> int:
        """Unmasked biases per action dimension; 41 for the arranged layout."""
        return sum(rows for rows, _ in self.layer_shapes)

    def init(self, key: jax.Array) -> Params:
        """Draw w and b from U(-1/√10, 1/√10), as the authors' implementation does.

        Args:
            key: PRNG key.

        Returns:
            The parameter pytree described in the module docstring.
        """
        bound = 1.0 / jnp.sqrt(10.0)
        keys = jax.random.split(key, 2 * len(self.layer_shapes))
        w, b = [], []
        for i, (rows, cols) in enumerate(self.layer_shapes):
            shape_w, shape_b = (self.action_dim, rows, cols), (self.action_dim, rows)
            w.append(jax.random.uniform(keys[2 * i], shape_w, minval=-bound, maxval=bound))
            b.append(jax.random.uniform(keys[2 * i + 1], shape_b, minval=-bound, maxval=bound))
        return {"w": w, "b": b}

    def apply(
        self, params: Params, mask: list[jax.Array], obs: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Evaluate the masked network on one observation (Eq. 1–2 with w_m = w ⊗ m, §3.2).

        Args:
            params: {"w": [...], "b": [...]} as built by ``init``.
            mask: one array per entry of ``params["w"]`` with the same shape (binary, or
                straight-through during training).
            obs: observation, shape (obs_dim,).

        Returns:
            pre_tanh_action: shape (action_dim,).
            penalty: scalar, the sum of every operator's penalty term over all action dimensions
                (L_penalty, Eq. 3).
        """
        masked_w = [w * m for w, m in zip(params["w"], mask, strict=True)]
        out, penalty = jax.vmap(self._apply_one, in_axes=(0, 0, None))(masked_w, params["b"], obs)
        return out[:, 0], jnp.sum(penalty)

    def _apply_one(
        self, ws: list[jax.Array], bs: list[jax.Array], obs: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """One action dimension: ws[i] (rows, in), bs[i] (rows,), obs (obs_dim,)."""
        x = obs
        penalty = jnp.zeros((), obs.dtype)
        for ops, w, b in zip(self.layout.layers, ws[:-1], bs[:-1], strict=True):
            y = w @ x + b
            outputs, row = [], 0
            # Consecutive identical operators are evaluated as one vectorized call.
            for name, run in groupby(ops):
                op = get_operator(name)
                count = len(list(run))
                args = y[row : row + count * op.arity].reshape(count, op.arity).T
                value, op_penalty = op.fn(*args)
                outputs.append(value)
                penalty = penalty + jnp.sum(op_penalty)
                row += count * op.arity
            layer_out = jnp.concatenate(outputs)
            x = jnp.concatenate([x, layer_out]) if self.layout.dense else layer_out
        return ws[-1] @ x + bs[-1], penalty


def live_paths(network: SymbolicNetwork, weights: list[np.ndarray]) -> np.ndarray:
    """Paths that reach the output, per action dimension: the paper's "selected paths" (App. F).

    A path is a non-zero (masked) weight whose row feeds an operator whose output is used,
    directly or through later operators, by the final linear layer; weights into operators
    whose output nothing uses do not count.

    Args:
        network: a densely linked network (the "plain" layout counts every non-zero weight).
        weights: the masked weights, one (A, rows, cols) array per layer as in ``params["w"]``.

    Returns:
        int array (A,).
    """
    weights = [np.asarray(w) != 0 for w in weights]
    if not network.layout.dense:
        return np.sum([w.reshape(w.shape[0], -1).sum(1) for w in weights], axis=0)
    counts = []
    widths = [len(ops) for ops in network.layout.layers]
    offsets = network.obs_dim + np.concatenate([[0], np.cumsum(widths)[:-1]])
    for a in range(network.action_dim):
        live = weights[-1][a, 0].copy()  # inputs of the output layer that it uses
        count = int(live.sum())
        for layer in reversed(range(len(widths))):
            rows = 0
            for k, name in enumerate(network.layout.layers[layer]):
                arity = get_operator(name).arity
                if live[offsets[layer] + k]:
                    used = weights[layer][a, rows : rows + arity]  # (arity, inputs)
                    count += int(used.sum())
                    live[: used.shape[1]] |= used.any(axis=0)
                rows += arity
        counts.append(count)
    return np.asarray(counts)
