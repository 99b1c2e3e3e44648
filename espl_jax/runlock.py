"""One writer per run directory: an exclusive ``flock`` on ``RUN/.lock`` for as long as a command
writes the run (train, resume, evaluate, analyze).

The kernel drops a flock when its holder dies, ``kill -9`` included, so a lock left by a killed
process never blocks ``--resume``: there is no stale lock to detect or to clean up by hand. The
file only says who holds it: the holder writes its pid and host into it, and empties it when it
lets go (a killed holder leaves its line behind, which the next holder overwrites). The file
itself is never removed: a process that opened it before the removal would lock a file that no
longer has a name, beside a second process locking the new one.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from espl_jax.config import UserError

LOCK_FILE = ".lock"
# A holder writes its line right after it takes the lock; a refusal waits this long for it.
_HOLDER_LINE_WAIT_S = 1.0


@contextlib.contextmanager
def hold(run_dir: str | Path) -> Iterator[None]:
    """Hold ``run_dir``'s lock for the block.

    Raises:
        UserError: another process holds it (the message names its pid and host).
    """
    run_dir = Path(run_dir)
    fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(
                f"{run_dir} is in use by another process ({_holder(fd)}): one process writes a "
                "run directory at a time; wait for it to end, or stop it and --resume"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on host {socket.gethostname()}\n".encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # drops the flock


def _holder(fd: int) -> str:
    """The holder's line ("pid N on host H"), or a placeholder if it has not written it yet."""
    deadline = time.monotonic() + _HOLDER_LINE_WAIT_S
    while True:
        line = os.pread(fd, 256, 0).decode(errors="replace").strip()
        if line or time.monotonic() > deadline:
            return line or "pid unknown"
        time.sleep(0.05)
