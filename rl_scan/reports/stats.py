"""Statistics for reports, as rliable (Agarwal et al. 2021) and marl-eval recommend.

Scores are per run (one seed of one condition): e.g. final evaluation coverage.
  * IQM: mean of the middle 50 % of runs: floor(n / 4) runs trimmed from each end, as
    ``scipy.stats.trim_mean(x, 0.25)`` (what rliable uses) does.
  * Stratified bootstrap CI: resample runs with replacement within each task (stratum),
    recompute the statistic, take the 2.5 / 97.5 percentiles.
  * Success rate: Wilson score interval over evaluation episodes (binomial).
  * Probability of improvement P(X > Y): per task over all run pairs, 1 if x > y, 0.5 if
    equal (Mann-Whitney U / (n m)), averaged over tasks, with a stratified bootstrap CI.
  * Learning-curve band: the t interval of the mean over seeds (n - 1 degrees of freedom).
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
    """CI of ``statistic`` over all runs, resampling runs within each stratum (task); none
    (nan) if a stratum has a single run, whose resamples are all alike (5 scenes x 1 seed
    would give a zero-width CI that only says nothing was resampled)."""
    strata = [np.asarray(s, dtype=float) for s in strata if len(s)]
    if not strata or min(len(s) for s in strata) < 2:
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


def _pairwise_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y) over all pairs of runs of one task (ties count one half)."""
    diff = x[:, None] - y[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def _tasks(x, y, tasks_x, tasks_y) -> list[tuple[np.ndarray, np.ndarray]]:
    """(X's runs, Y's runs) per task both have (one task if no labels are given)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    tasks_x = np.zeros(len(x), int) if tasks_x is None else np.asarray(tasks_x)
    tasks_y = np.zeros(len(y), int) if tasks_y is None else np.asarray(tasks_y)
    common = sorted(set(tasks_x.tolist()) & set(tasks_y.tolist()), key=str)
    return [(x[tasks_x == t], y[tasks_y == t]) for t in common]


def probability_of_improvement(x, y, tasks_x=None, tasks_y=None) -> float:
    """P(X > Y) as rliable defines it: per task, over all pairs of X's and Y's runs on that
    task (Mann-Whitney U / (n m), ties one half), averaged over the tasks both ran.
    ``tasks_x``/``tasks_y`` label each run's task (default: all one task)."""
    pairs = _tasks(x, y, tasks_x, tasks_y)
    if not pairs or any(len(a) == 0 or len(b) == 0 for a, b in pairs):
        return math.nan
    return float(np.mean([_pairwise_improvement(a, b) for a, b in pairs]))


def fewest_runs_per_task(x, y, tasks_x=None, tasks_y=None) -> int:
    """The fewest runs X or Y has on a task both ran (0 if none): the stratified bootstrap
    resamples within tasks, so one run a task (e.g. 5 scenes x 1 seed) gives a collapsed
    CI however many tasks there are."""
    pairs = _tasks(x, y, tasks_x, tasks_y)
    return min((min(len(a), len(b)) for a, b in pairs), default=0)


def probability_of_improvement_ci(x, y, tasks_x=None, tasks_y=None, *, reps: int = 2000,
                                  level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Stratified bootstrap CI of P(X > Y): each task's runs of X and of Y are resampled
    independently, within their task."""
    pairs = _tasks(x, y, tasks_x, tasks_y)
    if not pairs or any(len(a) == 0 or len(b) == 0 for a, b in pairs):
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    values = [np.mean([_pairwise_improvement(rng.choice(a, len(a)), rng.choice(b, len(b)))
                       for a, b in pairs]) for _ in range(reps)]
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def t_half_width(values, level: float = 0.95) -> float:
    """Half-width of the t confidence interval of the mean (n - 1 degrees of freedom):
    with 3 seeds t = 4.30, not the normal 1.96."""
    from scipy.stats import t

    x = np.asarray(values, dtype=float)
    if len(x) < 2:
        return 0.0
    return float(t.ppf(0.5 + level / 2, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x)))


def sample_std(values) -> float:
    """Sample std (n - 1 in the denominator) of the finite values; 0 for one value."""
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    return float(x.std(ddof=1)) if len(x) > 1 else (0.0 if len(x) else math.nan)


def mean_std(values) -> tuple[float, float]:
    """Mean and sample std (``sample_std``), nan-safe for empty input."""
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    return (float(x.mean()), sample_std(x)) if len(x) else (math.nan, math.nan)
