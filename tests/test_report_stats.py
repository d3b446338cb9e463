"""Report statistics against hand-computed values (IQM, Wilson, rliable's probability of
improvement and its stratified bootstrap, t-interval bands)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rl_scan.reports.stats import (
    iqm,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap_ci,
    wilson_interval,
)


def test_iqm_trims_a_quarter_from_each_end():
    assert iqm([1, 2, 3, 4]) == 2.5  # drops 1 and 4
    assert iqm([10, 0, 5, 6, 7, 100, 1, 2]) == pytest.approx((2 + 5 + 6 + 7) / 4)
    assert iqm([3.0]) == 3.0


def test_wilson_interval_by_hand():
    # 8 of 10, z = 1.96: centre (0.8 + 1.9208/10) / 1.38416 = 0.71673,
    # half 1.96 * sqrt(0.016 + 0.009604) / 1.38416 = 0.22660
    lo, hi = wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-3) and hi == pytest.approx(0.9433, abs=1e-3)
    assert wilson_interval(0, 5)[0] == 0.0 and math.isnan(wilson_interval(0, 0)[0])


def test_probability_of_improvement_counts_pairs_and_ties():
    # pairs (x, y): (3,1) (3,3) (3,5) (4,1) (4,3) (4,5) -> 1 + .5 + 0 + 1 + 1 + 0 = 3.5 / 6
    assert probability_of_improvement([3, 4], [1, 3, 5]) == pytest.approx(3.5 / 6)


def test_probability_of_improvement_is_rliables_per_task_average():
    """A non-degenerate 3-task fixture (ties included): our per-task average equals
    rliable's, and differs from pooling all runs first (what reports did before)."""
    from rliable.metrics import probability_of_improvement as rliable_poi

    rng = np.random.default_rng(3)
    x = np.round(rng.uniform(0.2, 1.0, (4, 3)), 1)  # (runs, tasks)
    y = np.round(rng.uniform(0.0, 0.9, (5, 3)), 1)
    y[:, 2] += 0.4  # Y is better on the last task
    tasks_x, tasks_y = np.tile([0, 1, 2], 4), np.tile([0, 1, 2], 5)
    ours = probability_of_improvement(x.ravel(), y.ravel(), tasks_x, tasks_y)
    assert ours == pytest.approx(rliable_poi(x, y), abs=1e-12)
    assert abs(ours - probability_of_improvement(x.ravel(), y.ravel())) > 0.01
    lo, hi = probability_of_improvement_ci(x.ravel(), y.ravel(), tasks_x, tasks_y)
    assert lo <= ours <= hi
    # tasks only one side ran are left out; none in common: no comparison
    assert probability_of_improvement([1.0, 0.0], [0.5], ["a", "b"], ["a"]) == 1.0
    assert math.isnan(probability_of_improvement([1.0], [0.5], ["a"], ["b"]))


@pytest.mark.parametrize("n", [8, 15])
def test_iqm_equals_scipy_trim_mean(n):
    from scipy.stats import trim_mean

    x = np.random.default_rng(n).normal(size=n)
    assert iqm(x) == pytest.approx(trim_mean(x, 0.25), abs=1e-12)


def test_curve_band_is_the_t_interval_of_the_mean():
    from rl_scan.reports.stats import t_half_width

    # 3 seeds: std (ddof 1) of (0.5, 0.6, 0.7) is 0.1; t(0.975, 2) = 4.3027
    assert t_half_width([0.5, 0.6, 0.7]) == pytest.approx(4.302653 * 0.1 / math.sqrt(3),
                                                          rel=1e-5)
    assert t_half_width([0.5]) == 0.0


def test_stratified_bootstrap_keeps_strata_apart():
    # each stratum is constant, so every resample has the same runs: a zero-width CI
    lo, hi = stratified_bootstrap_ci([[0.2, 0.2], [0.9, 0.9]], statistic=lambda x: x.mean())
    assert lo == pytest.approx(0.55) and hi == pytest.approx(0.55)
    # one run a stratum: nothing to resample, so no CI (not a zero-width one)
    assert all(math.isnan(v) for v in stratified_bootstrap_ci([[0.2], [0.9], [0.5, 0.6]]))
