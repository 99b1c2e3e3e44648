"""espl-jax: efficient symbolic policy learning (ESPL, NeurIPS 2023) in JAX."""

__version__ = "0.1.0"
