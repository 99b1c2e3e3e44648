"""Box2D environments (gymnasium's LunarLanderContinuous and BipedalWalker), stepped on the host.

These envs have no JAX implementation: ``envs.make("lunarlander")`` returns a ``HostEnv``, a
static description (sizes, horizon, action bounds, read from the gymnasium spaces) that builds the
gymnasium envs on demand. The trainer steps them through a gymnasium vector env, one env per seed
(:mod:`espl_jax.host`); policy and SAC updates stay in JAX.

* ``lunarlander``: ``gymnasium.make("LunarLander-v3", continuous=True)`` (gymnasium 1.x's id of
  LunarLanderContinuous; 8 observations, 2 actions in [-1, 1], 1000-step limit).
* ``bipedalwalker``: ``gymnasium.make("BipedalWalker-v3")`` (24 observations, 4 actions in [-1, 1],
  1600-step limit).

gymnasium (and Box2D) is imported only when an env is built, so ``from espl_jax import envs``
stays cheap.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from espl_jax.envs.base import action_center_half_range, to_env_units


class HostEnv:
    """A gymnasium env stepped on the host: the metadata the trainer and the exporter need.

    Attributes:
        name: registry name, e.g. ``"lunarlander"``.
        env_id: the gymnasium id; ``kwargs`` are passed to ``gymnasium.make``.
        obs_dim: size of the observation vector (from the observation space).
        action_dim: size of the action vector (from the action space).
        horizon: time limit (``max_episode_steps``); truncation happens there.
        action_low: numpy float array (action_dim,), lower action bound in the env's own units.
        action_high: numpy float array (action_dim,), upper action bound in the env's own units.

    Unlike ``envs.Environment`` there is no ``reset``/``step`` in JAX; ``make_env`` and
    ``make_vector_env`` build the gymnasium envs. Actions from the policy are normalized to
    [-1, 1]; ``to_env_action`` maps them to the env's units (as ``Environment.scale_action``).
    """

    def __init__(self, name: str, env_id: str, horizon: int | None = None, **kwargs: Any):
        """Builds the description by making the env once and reading its spaces.

        Args:
            name: registry name.
            env_id: gymnasium id.
            horizon: time limit; None keeps the registered ``max_episode_steps``.
            **kwargs: forwarded to ``gymnasium.make`` (e.g. ``continuous=True``).
        """
        import gymnasium

        self.name = name
        self.env_id = env_id
        self.kwargs = kwargs
        registered = gymnasium.spec(env_id).max_episode_steps
        self.horizon = int(registered if horizon is None else horizon)
        env = self.make_env()
        try:
            obs_space, action_space = env.observation_space, env.action_space
            self.obs_dim = int(np.prod(obs_space.shape))
            self.action_dim = int(np.prod(action_space.shape))
            self.action_low = np.asarray(action_space.low, np.float64).reshape(-1)
            self.action_high = np.asarray(action_space.high, np.float64).reshape(-1)
        finally:
            env.close()

    def make_env(self, **kwargs: Any):
        """One gymnasium env with this description's time limit; actions in the env's units.

        ``kwargs`` (e.g. ``render_mode``) are forwarded to ``gymnasium.make``.
        """
        import gymnasium

        return gymnasium.make(
            self.env_id, max_episode_steps=self.horizon, **{**self.kwargs, **kwargs}
        )

    def make_vector_env(self, num_envs: int):
        """``num_envs`` envs in a ``SyncVectorEnv`` with same-step autoreset.

        On a step that ends an episode the returned observation is already the reset one; the
        true final observation is in ``info["final_obs"][i]`` (``info["_final_obs"]`` marks them).
        """
        import gymnasium

        return gymnasium.vector.SyncVectorEnv(
            [self.make_env for _ in range(num_envs)],
            autoreset_mode=gymnasium.vector.AutoresetMode.SAME_STEP,
        )

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        """Normalized actions (..., action_dim) in [-1, 1] to float32 actions in env units.

        Non-finite entries (a diverged actor) become 0 so Box2D is never fed NaN; the trainer
        still stops on the non-finite losses.
        """
        center, half_range = action_center_half_range(self.action_low, self.action_high)
        action = np.nan_to_num(np.asarray(action, np.float64))
        return to_env_units(action, center, half_range).astype(np.float32)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, id={self.env_id!r})"


def lunarlander(**kwargs: Any) -> HostEnv:
    return HostEnv("lunarlander", "LunarLander-v3", continuous=True, **kwargs)


def bipedalwalker(**kwargs: Any) -> HostEnv:
    return HostEnv("bipedalwalker", "BipedalWalker-v3", **kwargs)
