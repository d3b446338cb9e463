"""The report's learning-curve figure: coverage over env steps per condition."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from rl_scan.reports.collect import RunRecord
from rl_scan.reports.stats import sample_std, t_half_width

CONVERGED = 0.80  # the convergence rule's coverage (dotted line)


def _aligned(step: int) -> int:
    """An evaluation's env steps to 3 significant digits: runs overshoot a batch by a few
    steps (780,003 vs 780,000), which would put each at its own point with n = 1 or 2 and
    a t band of 12.7 standard errors."""
    if step <= 0:
        return int(step)
    return int(round(step, 2 - int(math.floor(math.log10(step)))))


def curve_band(runs: list[RunRecord]) -> tuple[np.ndarray, ...]:
    """Steps, mean, std, 95 % CI half-width and run count of coverage at each evaluated
    step (runs of unequal length: the statistics use the runs that reached the step)."""
    curves = [{_aligned(step): c for step, c in r.curve} for r in runs if r.evals]
    steps = sorted(set().union(*[set(c) for c in curves])) if curves else []
    if not steps:
        return (np.array([]),) * 5
    mean, std, half, count = [], [], [], []
    for s in steps:
        v = np.array([c[s] for c in curves if s in c])
        mean.append(v.mean())
        std.append(sample_std(v))
        half.append(t_half_width(v))
        count.append(len(v))
    return tuple(np.array(x) for x in (steps, mean, std, half, count))


PANELS_FROM = 5  # conditions from which each gets its own panel (one plot is unreadable)


def plot_curves(runs: list[RunRecord], title: str, out: Path,
                reference: float | None = None) -> Path:
    """Mean +- std (light) and 95 % CI (dark) of coverage per condition, and each run
    when there are few; one panel per condition when there are many (Table II's 8)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    by_cond: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        by_cond[r.condition].append(r)
    conds = sorted(by_cond)
    panels = len(conds) >= PANELS_FROM
    cols = min(4, len(conds)) if panels else 1
    rows = -(-len(conds) // cols) if panels else 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols + 0.8, 2.6 * rows + 0.9)
                             if panels else (7, 4.2), dpi=110, sharex=True, sharey=True,
                             squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, cond in enumerate(conds):
        ax = axes.flat[i] if panels else axes.flat[0]
        rs, color = by_cond[cond], colors[i % len(colors)]
        steps, mean, std, half, _ = curve_band(rs)
        if not len(steps):
            continue
        ax.plot(steps, mean, color=color, label=f"{cond} (n={len(rs)})", lw=1.8)
        if 1 < len(rs) <= 5:  # few seeds: show each run too
            for r in rs:
                if r.evals:
                    x, y = zip(*r.curve)
                    ax.plot(x, y, color=color, lw=0.6, alpha=0.5)
        ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.15)
        ax.fill_between(steps, mean - half, mean + half, color=color, alpha=0.3)
        if panels:
            ax.set_title(f"{cond} (n={len(rs)})", fontsize=9)
    for i, ax in enumerate(axes.flat):
        if panels and i >= len(conds):
            ax.set_visible(False)
            continue
        if reference is not None and not math.isnan(reference):
            ax.axhline(reference, color="k", ls="--", lw=1, label="scripted greedy team")
        ax.axhline(CONVERGED, color="grey", ls=":", lw=1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(_steps_label))
        ax.tick_params(labelsize=7 if panels else 9, labelbottom=True)
    for ax in axes[-1]:
        ax.set_xlabel("env steps", fontsize=8 if panels else 10)
    for ax in axes[:, 0]:
        ax.set_ylabel("evaluation coverage", fontsize=8 if panels else 10)
    if panels:
        fig.suptitle(f"{title}: mean ± std (light), 95 % CI (dark), each seed (thin); "
                     "dashed: greedy team, dotted: 80 %", fontsize=9)
    else:
        axes[0, 0].set_title(title)
        axes[0, 0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def _steps_label(x: float, _pos=None) -> str:
    return f"{x / 1e6:g}M" if abs(x) >= 1e6 else f"{x / 1e3:g}k" if x else "0"
