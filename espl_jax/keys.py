"""Named random-key streams: every salt and seed offset a run draws randomness with, in one table.

Where a run's randomness comes from:

- Seed keys: seed i of ``--seeds S --seed K`` is ``PRNGKey(K + i)``, the key of a one-seed
  ``--seed K+i`` run (``seed_keys``). ``Trainer.init`` splits it, and every training iteration
  splits ``TrainState.key`` again (positional ``jax.random.split``, not listed here).
- Task draws: ``split(PRNGKey(task_seed))`` gives the training and test tasks
  (``envs/tasks.py``, ``TaskFamily.split_keys``).
- Salted streams: a consumer outside the training iteration folds a salt into a key
  (``jax.random.fold_in(key, SALT)``), so it never draws what training draws. A salt must stay
  distinct from the others folded into the same key, and must never change: changing one changes
  every run's results (``benchmarks/bitwise_params.py`` checks they do not).

Salts folded into each seed's ``TrainState.key`` (``salted``), one stream each:

    name           salt  stream                                                    module
    PROGRESS_EVAL  1     evaluation episodes after each chunk (metrics.jsonl)      run
    SELECTION      2     single-task: the episodes the best seed is chosen on;     run, meta_report
                         meta-RL: PEARL's protocol on training tasks (chooses it)
    REPORT         3     single-task: the reported final episodes (eval.json);     run, meta_report
                         meta-RL: PEARL's protocol on the test tasks
    (retired)      4, 5  the gymnasium env seeds of the former host collectors     RETIRED_SALTS
                         (``espl_jax/host.py``, ``host_meta.py``); not to be reused

Salts folded into a sub-key (a different key from the above, so the values may repeat):

    POSTERIOR_DRAW 1     meta-RL collection: a phase's z draws and masks, folded   task_sets
                         into the trajectory's collection key
    ENCODER        1     PEARL's encoder init, and the critic loss's z sample      sac

``sac.py`` writes ``ENCODER``'s salt as the literal ``1`` (it is left to its own change).

Offsets added to ``config.seed`` for fresh keys of the meta-RL end-of-run report (``offset_key``):

    FRESH_EPISODES_OFFSET  10_000  fresh episodes of each test task's adapted formula   meta_report
    COEFFICIENTS_OFFSET    20_000  the protocol on the coefficient figure's task grid   meta_report

Gymnasium episode seeds (``env.reset(seed=first + i)``), not JAX keys:

    REFERENCE_FIRST_EPISODE  0       a run's own evaluation of policy.py (eval.json's
                                     ``reference_eval``; meta-RL ``policy_py_return``):
                                     run, meta_report
    EVALUATE_FIRST_EPISODE   10_000  ``python -m espl_jax.evaluate``'s default ``--seed``,
                                     episodes the run's own evaluation did not see: evaluate

The benchmarks (``benchmarks/*.py``) draw their own fixed keys (``PRNGKey(0)`` … ``PRNGKey(7)``)
for timing and diagnostics outside a run; they are not run streams and are not listed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

PROGRESS_EVAL = 1
SELECTION = 2
REPORT = 3
RETIRED_SALTS = (4, 5)

POSTERIOR_DRAW = 1
ENCODER = 1

FRESH_EPISODES_OFFSET = 10_000
COEFFICIENTS_OFFSET = 20_000

REFERENCE_FIRST_EPISODE = 0
EVALUATE_FIRST_EPISODE = 10_000


def seed_keys(seed: int, seeds: int) -> jax.Array:
    """[S, 2]: the keys of seeds ``seed`` … ``seed + seeds − 1``, each ``PRNGKey(seed + i)``."""
    return jnp.stack([jax.random.PRNGKey(int(s)) for s in seed + np.arange(seeds)])


def salted(state_keys: jax.Array, salt: int) -> jax.Array:
    """[S, 2]: the salted stream ``fold_in(key, salt)`` of each seed's key ``state_keys`` [S, 2]."""
    return jax.vmap(jax.random.fold_in, (0, None))(state_keys, salt)


def offset_key(seed: int, offset: int) -> jax.Array:
    """A fresh key ``PRNGKey(seed + offset)``, independent of the run's training keys."""
    return jax.random.PRNGKey(seed + offset)
