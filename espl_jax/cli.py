"""Shared command-line plumbing: user errors become one readable line and exit code 2."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

from espl_jax.config import UserError


def run_main(main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    try:
        return main(argv)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a path the user gave cannot be read or written (permissions, …)
        where = f": {err.filename}" if err.filename else ""
        print(f"error: {err.strerror or err}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; resume with --resume RUN_DIR", file=sys.stderr)
        return 130


def check_path(value: str | None, name: str) -> None:
    """Refuse an empty path on the command line (None: not given, fine).

    ``Path("")`` is ``.``, the current directory, which the user did not name: ``--out ''``
    would write the run there, ``--resume ''`` resume whatever run it holds.

    Raises:
        UserError: ``value`` is empty.
    """
    if value == "":
        raise UserError(f"{name} is empty: it names no file or directory")


def cache_turned_off() -> bool:
    """Whether ``JAX_COMPILATION_CACHE_DIR`` is empty or "off", the spelling for "no cache"; if
    so, JAX's own reading of the variable (a folder named "off") is undone."""
    chosen = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if chosen is None or chosen.strip() not in ("", "off"):
        return False
    import jax

    jax.config.update("jax_compilation_cache_dir", None)
    return True


def use_compilation_cache() -> str | None:
    """Keep XLA's compiled programs on disk between runs, unless the user chose otherwise.

    Compiling a meta-RL chunk over MJX physics takes minutes on a CPU (the symbolic network,
    the critics and two collection phases of the Newton solver in one program); a second run of
    the same env, actor and budget (another seed, a resume) loads it in seconds. The programs
    are the same bit for bit, so results do not change. ``JAX_COMPILATION_CACHE_DIR`` set by the
    user wins (empty or "off" turns the cache off); else ``$XDG_CACHE_HOME/espl_jax/xla`` (or
    ``~/.cache/espl_jax/xla``). Returns the directory, or None when off.
    """
    import jax

    chosen = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if chosen is not None:
        return None if cache_turned_off() else chosen
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    path = Path(base) / "espl_jax" / "xla"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: compile every time, as JAX does by default
    jax.config.update("jax_compilation_cache_dir", str(path))
    return str(path)
