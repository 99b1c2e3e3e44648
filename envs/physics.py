"""The two ways a MuJoCo task is simulated.

``mjx``: MJX inside the compiled program (``envs/mjx.py``): differentiable, fast on an
accelerator. ``native``: MuJoCo's C engine on the host through one callback per step
(``envs/native.py``): fast on a CPU. Both run the same task definition.
"""

from __future__ import annotations

from typing import Any

PHYSICS: tuple[str, ...] = ("mjx", "native")


def with_physics(env: Any, physics: str) -> Any:
    """The MuJoCo task ``env`` (an MJX env of ``envs/mjx.py``) on the chosen backend."""
    if physics not in PHYSICS:
        raise ValueError(f"unknown physics {physics!r}; choose one of {', '.join(PHYSICS)}")
    if physics == "native":
        from espl_jax.envs.native import NativeEnv

        return NativeEnv(env)
    return env
