"""A kill switch for the kill-safety tests: a kill at an exact moment cannot be timed from outside.

``kill_point("checkpoint-write:4")`` SIGKILLs the process when the environment variable
``ESPL_JAX_KILL_AT`` names that point. Unset in normal use, where it is one dictionary lookup.
Points:

- ``checkpoint-write:N``: the checkpoint of iteration N is being written, not committed (N = 0:
  the initial state, written before anything else is computed);
- ``warmup``: a meta-RL run's initial collection is done (JAX: still running), nothing of it
  written;
- ``chunk:N``: the chunk that ends at iteration N is running (JAX: dispatched and in flight; host
  envs: stepped), nothing of it written;
- ``export``: a single-task run's final export is half written (expression.txt, policy.py,
  eval.json, but no reference evaluation yet);
- ``protocol``: a meta-RL run's final protocol has run on the test tasks, not yet on the
  training tasks (tasks.json written, eval.json not);
- ``test-task-export``: test_tasks/0/ of a meta-RL run is written, the other test tasks not.
"""

from __future__ import annotations

import os
import signal

ENV_VAR = "ESPL_JAX_KILL_AT"


def kill_point(name: str) -> None:
    if os.environ.get(ENV_VAR) == name:
        os.kill(os.getpid(), signal.SIGKILL)
