"""Statistics for reports, as rliable (Agarwal et al. 2021) and marl-eval recommend.

Scores are per run (one seed of one condition): e.g. final evaluation coverage.
  * IQM: mean of the middle 50 % of runs: floor(n / 4) runs trimmed from each end, as
    ``scipy.stats.trim_mean(x, 0.25)`` (what rliable uses) does.
  * Stratified bootstrap CI: resample runs with replacement within each task (stratum),
    recompute the statistic, take the 2.5 / 97.5 percentiles.
  * Success rate: Wilson score interval over evaluation episodes (binomial).
  * Probability of improvement P(X > Y): over all run pairs, 1 if x > y, 0.5 if equal,
    averaged (Mann-Whitney U / (n m)), with a bootstrap CI.
"""

from __future__ import annotations

import math

import numpy as np

Z95 = 1.959963984540054


def iqm(scores) -> float:
    """Interquartile mean: drop floor(n/4) runs from each end, average the rest."""
    x = np.sort(np.asarray(scores, dtype=float))
    if len(x) == 0:
        return math.nan
    k = len(x) // 4
    return float(x[k:len(x) - k].mean())


def stratified_bootstrap_ci(strata: list, statistic=iqm, *, reps: int = 2000,
                            level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """CI of ``statistic`` over all runs, resampling runs within each stratum (task)."""
    strata = [np.asarray(s, dtype=float) for s in strata if len(s)]
    if not strata:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    values = np.empty(reps)
    for r in range(reps):
        values[r] = statistic(np.concatenate([rng.choice(s, size=len(s)) for s in strata]))
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def wilson_interval(successes: float, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (episodes that succeeded)."""
    if n <= 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def probability_of_improvement(x, y) -> float:
    """P(X > Y) over all pairs of runs (ties count one half)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) == 0 or len(y) == 0:
        return math.nan
    diff = x[:, None] - y[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def probability_of_improvement_ci(x, y, *, reps: int = 2000, level: float = 0.95,
                                  seed: int = 0) -> tuple[float, float]:
    """Bootstrap CI of P(X > Y), resampling the runs of X and of Y independently."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) == 0 or len(y) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    values = [probability_of_improvement(rng.choice(x, len(x)), rng.choice(y, len(y)))
              for _ in range(reps)]
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def mean_std(values) -> tuple[float, float]:
    """Mean and population std (numpy's default), nan-safe for empty input."""
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    return (float(x.mean()), float(x.std())) if len(x) else (math.nan, math.nan)
