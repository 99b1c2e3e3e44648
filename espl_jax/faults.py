"""A kill switch for the kill-safety tests: a kill at an exact moment cannot be timed from outside.

``kill_point("checkpoint-write")`` SIGKILLs the process when the environment variable
``ESPL_JAX_KILL_AT`` names that point. Unset in normal use, where it is one dictionary lookup.
Points: ``checkpoint-write:N`` (the checkpoint of iteration N is being written, not committed) and
``export`` (the final export is half written: expression.txt, policy.py, eval.json, but no
reference evaluation yet).
"""

from __future__ import annotations

import os
import signal

ENV_VAR = "ESPL_JAX_KILL_AT"


def kill_point(name: str) -> None:
    if os.environ.get(ENV_VAR) == name:
        os.kill(os.getpid(), signal.SIGKILL)
