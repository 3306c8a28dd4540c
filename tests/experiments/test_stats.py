"""Aggregate statistics: IQM, stratified-bootstrap CIs and performance profiles (rliable's methods)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as scipy_stats

from eabc.experiments import stats


@pytest.mark.parametrize("n", [7, 10, 13])
def test_iqm_equals_scipy_trim_mean_with_fractional_quartile_boundaries(n):
    x = np.random.default_rng(n).normal(50, 20, n)
    assert 0.25 * n != int(0.25 * n)
    assert stats.iqm(x) == pytest.approx(scipy_stats.trim_mean(x, 0.25))
    assert stats.iqm(x) != pytest.approx(x.mean())
    tasks = [x[:3], x[3:]]  # pooled over tasks of different sizes
    assert stats.iqm(tasks) == pytest.approx(scipy_stats.trim_mean(x, 0.25))


def test_bootstrap_ci_contains_the_estimate_narrows_with_runs_and_is_reproducible():
    rng = np.random.default_rng(1)
    small, large = rng.normal(50, 10, (5, 3)), rng.normal(50, 10, (100, 3))
    widths = []
    for scores in (small, large):
        for statistic in (stats.iqm, stats.aggregate_mean):
            low, high = stats.stratified_bootstrap_ci(scores, statistic, reps=500)
            assert low <= statistic(scores) <= high
        low, high = stats.stratified_bootstrap_ci(scores, stats.aggregate_mean, reps=500)
        widths.append(high - low)
    assert widths[1] < widths[0] / 2
    again = stats.stratified_bootstrap_ci(small, stats.iqm, reps=500)
    assert again == stats.stratified_bootstrap_ci(small, stats.iqm, reps=500)
    assert again != stats.stratified_bootstrap_ci(small, stats.iqm, reps=500, seed=1)
    tighter = stats.stratified_bootstrap_ci(small, stats.iqm, reps=500, alpha=0.5)
    assert again[0] <= tighter[0] <= tighter[1] <= again[1]


def test_bootstrap_resamples_runs_within_each_task():
    # Constant within each task: any resample within tasks has the same mean; pooling would not.
    matrix = np.array([[1.0, 5.0], [1.0, 5.0], [1.0, 5.0]])
    assert stats.stratified_bootstrap_ci(matrix, stats.aggregate_mean, reps=300) == (3.0, 3.0)
    assert stats.stratified_bootstrap_ci(matrix, np.mean, reps=300) == (3.0, 3.0)
    ragged = [np.full(2, 1.0), np.full(5, 5.0)]  # tasks with different numbers of seeds
    iqm = scipy_stats.trim_mean(np.concatenate(ragged), 0.25)
    assert stats.stratified_bootstrap_ci(ragged, stats.iqm, reps=300) == (iqm, iqm)
    spread = [np.array([1.0, 9.0]), np.full(5, 5.0)]  # a task with spread gives a spread
    low, high = stats.stratified_bootstrap_ci(spread, stats.aggregate_mean, reps=300)
    assert low < high
    shapes = set()
    stats.stratified_bootstrap_ci(matrix, lambda s: shapes.add(s.shape) or 0.0, reps=3)
    stats.stratified_bootstrap_ci(ragged, lambda s: shapes.add(tuple(map(len, s))) or 0.0, reps=3)
    assert shapes == {(3, 2), (2, 5)}


def test_performance_profile_is_the_hand_computed_step_function():
    tasks = [np.array([10.0, 20.0, 30.0]), np.array([40.0, 50.0])]
    taus = [0.0, 15.0, 20.0, 25.0, 45.0, 60.0]
    # task 1 above tau: 3/3, 2/3, 1/3 (20 is not above 20), 1/3, 0, 0; task 2: 1, 1, 1, 1, 1/2, 0
    expected = [1.0, (2 / 3 + 1) / 2, (1 / 3 + 1) / 2, (1 / 3 + 1) / 2, 0.25, 0.0]
    np.testing.assert_allclose(stats.performance_profile(tasks, taus), expected)
    fine = np.linspace(-10, 110, 241)
    profile = stats.performance_profile(tasks, fine)
    assert np.all(np.diff(profile) <= 0) and profile[0] == 1.0 and profile[-1] == 0.0
    assert len(np.unique(profile)) == 6  # one step down at each distinct score


def test_bad_scores_give_clear_errors():
    with pytest.raises(ValueError, match="at least one run"):
        stats.stratified_bootstrap_ci([np.ones(3), np.array([])], np.mean)
    with pytest.raises(ValueError, match="finite"):
        stats.iqm([1.0, np.nan])
