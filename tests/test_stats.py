"""espl_jax.stats against scipy and against the exact bootstrap distribution."""

import itertools

import numpy as np
import pytest
from scipy import stats as scipy_stats

from espl_jax import stats


@pytest.mark.parametrize("shape", [(3,), (4,), (5,), (7, 3), (10, 6)])
def test_iqm_is_scipys_quarter_trimmed_mean_over_all_scores(shape):
    x = np.random.default_rng(sum(shape)).normal(size=shape) * 100
    assert stats.iqm(x) == pytest.approx(scipy_stats.trim_mean(x, 0.25, axis=None), rel=1e-12)


def test_iqm_ignores_one_outlier_in_five_runs():
    assert stats.iqm([1.0, 2.0, 3.0, 4.0, -1e6]) == pytest.approx(2.0)
    assert stats.mean([1.0, 2.0, 3.0, 4.0, -1e6]) < -1e5


def test_bootstrap_interval_matches_the_exact_resampling_distribution():
    # Three runs: the 27 equally likely resamples of the mean give its exact distribution.
    x = np.array([-540.0, -58.0, -52.0])
    exact = np.array([np.mean(r) for r in itertools.product(x, repeat=3)])
    low, high = stats.stratified_bootstrap_ci(x, stats.mean, reps=40_000, seed=1)
    # The quantiles of that discrete distribution (each end atom has mass 1/27 > 2.5 %, so
    # the interval is exactly [-540, -52]: one bad seed in three is inside it).
    assert low == np.percentile(exact, 2.5, method="inverted_cdf") == -540.0
    assert high == np.percentile(exact, 97.5, method="inverted_cdf") == -52.0


def test_bootstrap_is_stratified_by_task_and_deterministic():
    # Task 0 has constant scores, task 1 varies: every resample keeps task 0's runs, so the
    # aggregate of task 0's column alone never varies.
    x = np.stack([np.full(5, 7.0), np.arange(5.0)], axis=1)
    low, high = stats.stratified_bootstrap_ci(x, lambda r: float(r[:, 0].mean()), reps=500)
    assert low == high == 7.0
    a = stats.stratified_bootstrap_ci(x, stats.iqm, reps=500, seed=3)
    assert a == stats.stratified_bootstrap_ci(x, stats.iqm, reps=500, seed=3)
    assert a[0] < a[1]


def test_compare_says_win_only_when_the_intervals_do_not_overlap():
    assert stats.compare((5, 9), (1, 4)) == "win"
    assert stats.compare((1, 4), (5, 9)) == "loss"
    assert stats.compare((1, 5), (4, 9)) == "tie"


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError):
        stats.iqm([])
