"""Aggregate returns over seeds the way the field reports them now (Agarwal et al., "Deep RL at
the Edge of the Statistical Precipice", NeurIPS 2021; google-research/rliable).

- ``iqm``: the interquartile mean, the mean of the middle 50 % of the runs (rliable's
  ``aggregate_iqm``: ``scipy.stats.trim_mean(x, 0.25)`` over all runs and tasks). With fewer
  than 4 runs nothing is trimmed and it is the mean.
- ``stratified_bootstrap_ci``: a percentile confidence interval of any aggregate, from
  bootstrap resamples drawn with replacement *within each task* (stratum), so every task keeps
  its number of runs (rliable's ``StratifiedBootstrap`` with the percentile method).
- ``compare``: the issue's verdict for two methods: "win" when one interval lies wholly above
  the other's, "loss" when below, "tie" when they overlap.

Scores are a (runs, tasks) matrix; one task (one family) is a vector of runs.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def _matrix(scores) -> np.ndarray:
    x = np.asarray(scores, np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"scores must be (runs,) or (runs, tasks) with runs > 0, got {x.shape}")
    return x


def iqm(scores) -> float:
    """Interquartile mean over all runs and tasks: int(n/4) values trimmed from each end of
    the n sorted scores (``scipy.stats.trim_mean(x, 0.25, axis=None)``, as rliable)."""
    x = np.sort(_matrix(scores), axis=None)
    cut = int(0.25 * x.size)
    return float(np.mean(x[cut : x.size - cut]))


def mean(scores) -> float:
    return float(np.mean(_matrix(scores)))


def stratified_bootstrap_ci(
    scores,
    aggregate: Callable[[np.ndarray], float] = iqm,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """(low, high) percentile interval of ``aggregate`` over ``reps`` stratified resamples.

    Each resample draws, for every task separately, as many runs as the task has, uniformly
    with replacement from that task's runs; ``aggregate`` sees the resampled (runs, tasks)
    matrix. Deterministic for a fixed ``seed``.
    """
    x = _matrix(scores)
    runs, tasks = x.shape
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, runs, size=(reps, runs, tasks))
    resampled = np.take_along_axis(x[None], idx, axis=1)  # (reps, runs, tasks)
    values = np.array([aggregate(r) for r in resampled])
    tail = (1.0 - confidence) / 2.0 * 100.0
    low, high = np.percentile(values, [tail, 100.0 - tail])
    return float(low), float(high)


def compare(a: tuple[float, float], b: tuple[float, float]) -> str:
    """ "win" if interval ``a`` lies above ``b``, "loss" if below, else "tie"."""
    if a[0] > b[1]:
        return "win"
    if a[1] < b[0]:
        return "loss"
    return "tie"
