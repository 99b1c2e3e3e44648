"""Host-side evaluation of an exported ``policy.py`` in the reference (gymnasium) environment:
eval.json's ``reference_eval`` (the command line is ``python -m espl_jax.evaluate``)."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np

from espl_jax.config import UserError
from espl_jax.envs.reference import REFERENCE_ENVS, reference_env


def load_policy(path: str | Path) -> ModuleType:
    """Import a generated ``policy.py`` as a module."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no exported policy at {path}")
    spec = importlib.util.spec_from_file_location(f"espl_policy_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as err:
        raise UserError(f"cannot load {path}: {type(err).__name__}: {err}") from None
    if not callable(getattr(module, "act", None)):
        raise UserError(f"{path} has no act(obs) function")
    return module


def has_reference(env_name: str) -> bool:
    """Whether ``env_name`` has a host-side reference env to evaluate a policy.py in."""
    return env_name in REFERENCE_ENVS


def rollout_returns(
    act: Callable[[np.ndarray], np.ndarray],
    env_name: str,
    episodes: int,
    seed: int = 0,
    **env_kwargs,
) -> np.ndarray:
    """Returns of ``episodes`` episodes of ``act`` in the reference env, seeds seed … seed+N−1.

    ``act`` maps an observation to an action in the environment's own units; ``env_kwargs``
    set the reference env's physics (a meta-RL task, e.g. cartpole_fl_ood's force_mag).
    """
    env = reference_env(env_name, **env_kwargs)
    returns = np.zeros(episodes)
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done = False
        while not done:
            action = np.asarray(act(obs), dtype=np.float32)
            obs, reward, terminated, truncated, _ = env.step(action)
            returns[i] += float(reward)
            done = terminated or truncated
    env.close()
    return returns
