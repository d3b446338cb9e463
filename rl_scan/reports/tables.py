"""The tables a report shows beside a group's condition table, where its runs have the
figures: adaptation of pre-trained weights (meta-MRSS protocol), each run's best checkpoint
re-evaluated, POCA's critic diagnostics and MetaPOCA's meta-training diagnostics."""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

import numpy as np

from rl_scan import results as R
from rl_scan.metrics import SPEED_AT, curve_metrics
from rl_scan.reports.collect import RunRecord
from rl_scan.reports.stats import mean_std, wilson_interval
from rl_scan.studies import ReportSpec


def fmt(x: float, pct: bool = True) -> str:
    """A figure for a table: percent with one decimal, or a count with thousands
    separators; a dash for none."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{100 * x:.1f}" if pct else f"{x:,.0f}"


def adaptation_lines(runs: list[RunRecord], rows: list[dict[str, Any]],
                     spec: ReportSpec) -> list[str]:
    """For runs that adapt pre-trained weights (``spec.speed_ratio``): per condition the
    coverage before adaptation (the evaluation at 0 env steps) and the area under the
    coverage curve (``metrics.curve_metrics``), then the ratio of the spec's two conditions'
    censored env steps to SPEED_AT (the condition table's figures) against its goal."""
    if spec.speed_ratio is None:
        return []
    by_cond: dict[str, list[dict[str, float]]] = defaultdict(list)
    for r in runs:
        if r.evals:
            by_cond[r.condition].append(curve_metrics(r.evals, r.evals[-1]["env_steps"]))
    if not by_cond:
        return []
    lines = ["", "Adaptation (mean ± sample std over runs): coverage of the pre-trained "
             "weights before adaptation (the evaluation at 0 env steps; a dash for scratch "
             "training, which has none) and the area under the coverage curve over the "
             "adaptation budget.", "",
             "| condition | coverage % before adaptation | area under the curve % |",
             "|---|---|---|"]
    lines += [f"| {cond} | {_pm([m['start_coverage'] for m in ms])} | "
              f"{_pm([m['auc'] for m in ms])} |" for cond, ms in sorted(by_cond.items())]
    x, y, goal = spec.speed_ratio
    speed = {r["condition"]: r["speed"] for r in rows}
    if not math.isnan(speed.get(x, math.nan)) and speed.get(y, math.nan) > 0:
        ratio = speed[x] / speed[y]
        lines += ["", f"{x} / {y} env steps to {SPEED_AT:.0%} (the censored means above): "
                  f"**{ratio:.2f}**, the goal is at most {goal:.2f}: "
                  f"{'met' if ratio <= goal else 'not met'}."]
    return lines


def _pm(values: list[float]) -> str:
    """Mean ± sample std in percent of the non-nan values, a dash if none."""
    mean, std = mean_std(values)
    return "-" if math.isnan(mean) else f"{fmt(mean)} ± {fmt(std)}"


def best_checkpoint_table(runs: list[RunRecord]) -> list[str]:
    """Secondary numbers: each run's best kept checkpoint re-evaluated (evaluate --best)."""
    rows = [r for r in runs if r.best_eval]
    if not rows:
        return []
    lines = ["", "Secondary (not the headline): each run's best kept checkpoint, chosen by its "
             "training-time evaluation and re-evaluated on more episodes with "
             "`rl-scan evaluate RUN --best`. Choosing the best is biased upwards; the "
             "headline above uses final checkpoints.", "",
             "| run | condition | checkpoint at env steps | training-time eval % | "
             "re-evaluated coverage % (mean ± std) | success % [95 % CI] (episodes) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        b = r.best_eval
        cov, succ = b.get("coverage", []), b.get("success", [])
        mean, std = mean_std(cov)
        wins = int(sum(succ))
        lo, hi = wilson_interval(wins, len(succ))
        lines.append(f"| {r.path.name} | {r.condition} | {int(b.get('env_steps', 0)):,} | "
                     f"{fmt(b.get('eval_coverage', math.nan))} | {fmt(mean)} ± {fmt(std)} | "
                     f"{fmt(wins / len(succ) if succ else math.nan)} [{fmt(lo)}, {fmt(hi)}] "
                     f"({len(succ)}) |")
    return lines


EV_GOAL = 0.5  # issue 14: the critic's V should explain half of the returns' variance


def critic_lines(runs: list[RunRecord]) -> list[str]:
    """POCA's critic diagnostics per condition: explained variance of V and of each kind's
    b_i at the last iteration (mean over runs), and when V first explained half."""
    by_cond: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        if r.critic:
            by_cond[r.condition].append(r)
    if not by_cond:
        return []
    names = sorted({n for rs in by_cond.values() for r in rs for n in r.critic},
                   key=lambda n: (n != "V", n))
    lines = ["", "Critic diagnostics (POCA): explained variance of V and of each kind's "
             "baseline b_i against the returns of each update, at the last iteration (mean "
             f"over runs), and the env steps when V first explained {EV_GOAL:.0%} of their "
             "variance.", "",
             "| condition | " + " | ".join(f"EV {n}" for n in names)
             + f" | env steps to EV V >= {EV_GOAL} (reached) |",
             "|---|" + "---|" * (len(names) + 1)]
    for cond, rs in sorted(by_cond.items()):
        finals = [np.mean([r.critic[n][-1][1] for r in rs if n in r.critic] or [math.nan])
                  for n in names]
        reached = [next((s for s, v in r.critic.get("V", []) if v >= EV_GOAL), math.nan)
                   for r in rs]
        hit = [x for x in reached if not math.isnan(x)]
        lines.append(f"| {cond} | " + " | ".join(f"{x:.2f}" for x in finals)
                     + f" | {fmt(float(np.mean(hit)) if hit else math.nan, False)} "
                       f"({len(hit)}/{len(rs)}) |")
    return lines


def meta_lines(runs: list[RunRecord]) -> list[str]:
    """MetaPOCA's meta-training diagnostics per run (its META_FILE): the adaptation gain
    and the inner update's step over the last half of its meta-iterations."""
    rows = [(r, R.adaptation_gain(r.meta)) for r in runs if r.meta]
    if not rows:
        return []
    return ["", "Meta-training diagnostics (MetaPOCA), over the last half of each run's "
            "meta-iterations: adaptation gain = coverage of the query episodes (adapted "
            "weights) - coverage of the support episodes (meta weights), in points; ||delta|| = "
            "how far the inner update moved the parameters; cos = the mean cosine between "
            "the tasks' deltas of an iteration (near 1: every scene adapted the same way).",
            "",
            "| run | meta-iterations (last half) | adaptation gain | ‖delta‖ | cos |",
            "|---|---|---|---|---|",
            *(f"| {r.path.name} | {g['iterations']} | {100 * g['gain']:+.1f} | "
              f"{g['delta_norm']:.3g} | {_fmt_cos(g['delta_cosine'])} |" for r, g in rows)]


def _fmt_cos(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.2f}"
