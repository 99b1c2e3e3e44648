"""espl-jax: efficient symbolic policy learning (ESPL, NeurIPS 2023) in JAX.

``espl_jax.load(path)`` reads a run directory, ``espl_jax.train(env=..., **overrides)`` trains
one; both return an :class:`espl_jax.api.Run`. Importing the package is cheap: JAX and the
trainer load on first use.
"""

import sys
import types

__version__ = "0.1.0"


def load(path):
    """The run in directory ``path``: :func:`espl_jax.api.load`."""
    from espl_jax import api

    return api.load(path)


class _CallableModule(types.ModuleType):
    """``espl_jax.train`` is the command-line module (``python -m espl_jax.train``, and
    ``from espl_jax import train`` gives its ``main``) and, called, :func:`espl_jax.api.train`."""

    def __call__(self, env=None, **kwargs):
        from espl_jax import api

        return api.train(env, **kwargs)


class _Package(types.ModuleType):
    # Importing a submodule sets it as an attribute of its package: the train module, however
    # it is first imported, becomes callable here.
    def __setattr__(self, name, value):
        if name == "train" and type(value) is types.ModuleType:
            value.__class__ = _CallableModule
        super().__setattr__(name, value)


def __getattr__(name):
    if name == "train":  # first use: import the module (which _Package makes callable)
        import importlib

        return importlib.import_module("espl_jax.train")
    raise AttributeError(f"module 'espl_jax' has no attribute {name!r}")


sys.modules[__name__].__class__ = _Package
