"""The report's comparisons: P(X > Y) per pair, and a verdict on each of the paper's claims.

A claim is "X scores higher than Y" (``ReportSpec.claims``, keyed ``"X > Y"``); its verdict
follows from the 95 % CI of P(X > Y) by ``VERDICT_RULE``, so it regenerates with the
numbers and never depends on who reads them. Beside final coverage, the same pairs are
compared on scan speed (``SCAN_SPEED_RULE``), which still separates teams that all end
near 100 %.
"""

from __future__ import annotations

import math
from typing import Any

from rl_scan.reports.stats import (
    fewest_runs_per_task,
    mean_std,
    probability_of_improvement,
    probability_of_improvement_ci,
)
from rl_scan.studies import ReportSpec

REPRODUCED, REVERSED, UNDECIDED = "reproduced", "reversed", "not reproduced"
MIN_RUNS = 3
"""Runs each side needs on every task for a verdict: the bootstrap resamples within tasks,
so with one or two a task its CI of P(X > Y) collapses onto the few pairs there are (one
run each gives the point value as its CI, whatever the number of tasks)."""
TOO_FEW = f"none (fewer than {MIN_RUNS} runs a side per task)"
VERDICT_RULE = (
    "A claim of the paper that X beats Y is **reproduced** if the 95 % CI of P(X > Y) "
    "(final coverage) lies above 0.5, **reversed** if it lies below 0.5, and **not "
    f"reproduced** if it contains 0.5 (these runs do not separate X from Y); with fewer "
    f"than {MIN_RUNS} runs of X or of Y on a task (seeds per scene) there is no verdict.")
SCAN_SPEED_RULE = (
    "Scan speed: the steps an episode of a run's final evaluation takes to reach 95 % "
    "coverage, an episode that never does counted as its whole length (censored), mean ± "
    "sample std over runs; P(X faster than Y) is the probability of improvement on it. The "
    "paper's ablation task is to scan every object \"as quickly as possible\" (Sec. IV-B), "
    "and speed still separates teams whose final coverage is near 100 %.")


def verdict(ci: tuple[float, float], runs: int = MIN_RUNS) -> str:
    """The verdict on "X beats Y" from the CI of P(X > Y); ``runs``: the fewest runs a side
    has on a task (``fewest_runs_per_task``)."""
    if runs < MIN_RUNS:
        return TOO_FEW
    lo, hi = ci
    if lo > 0.5:
        return REPRODUCED
    return REVERSED if hi < 0.5 else UNDECIDED


def improvement_rows(spec: ReportSpec, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """P(X > Y) with its CI for every comparison both of whose conditions have scores,
    with the paper's claim and its verdict where the pair has one."""
    by_cond = {r["condition"]: (r["finals"], r["tasks"]) for r in rows}
    out = []
    for a, b in spec.comparisons:
        if a in by_cond and b in by_cond and by_cond[a][0] and by_cond[b][0]:
            (xa, ta), (xb, tb) = by_cond[a], by_cond[b]
            p = probability_of_improvement(xa, xb, ta, tb)
            if math.isnan(p):  # no common task: no comparison
                continue
            ci = probability_of_improvement_ci(xa, xb, ta, tb)
            claim = spec.claims.get(f"{a} > {b}")
            runs = fewest_runs_per_task(xa, xb, ta, tb)
            out.append({"x": a, "y": b, "p": p, "ci": ci, "claim": claim,
                        "verdict": verdict(ci, runs) if claim else None})
    return out


def improvement_lines(spec: ReportSpec, rows: list[dict[str, Any]]) -> list[str]:
    """The comparison table (Markdown lines; none without a comparison to make)."""
    imp = improvement_rows(spec, rows)
    if not imp:
        return []
    lines = ["", "| probability of improvement | P(X > Y) [95 % CI] | the paper's claim | "
             "verdict |", "|---|---|---|---|"]
    lines += [f"| {i['x']} > {i['y']} | {i['p']:.2f} [{i['ci'][0]:.2f}, {i['ci'][1]:.2f}] | "
              f"{i['claim'] or '(ours: not a claim of the paper)'} | {i['verdict'] or '-'} |"
              for i in imp]
    if any(i["claim"] for i in imp):
        lines += ["", VERDICT_RULE]
    return lines + scan_speed_lines(spec, rows)


def scan_speed_lines(spec: ReportSpec, rows: list[dict[str, Any]]) -> list[str]:
    """The comparisons on scan speed (fewer episode steps to 95 % is better); none where a
    run lacks the figure (reports rebuilt from files that predate it)."""
    by_cond = {r["condition"]: (r.get("scan_steps") or [], r["tasks"]) for r in rows}
    lines = []
    for a, b in spec.comparisons:
        (xa, ta), (xb, tb) = by_cond.get(a, ([], [])), by_cond.get(b, ([], []))
        if not xa or not xb or any(math.isnan(v) for v in xa + xb):
            continue
        faster = ([-v for v in xa], [-v for v in xb], ta, tb)  # fewer steps scores higher
        p = probability_of_improvement(*faster)
        if math.isnan(p):
            continue
        lo, hi = probability_of_improvement_ci(*faster)
        (ma, sa), (mb, sb) = mean_std(xa), mean_std(xb)
        lines.append(f"| {a} vs {b} | {ma:.0f} ± {sa:.0f} | {mb:.0f} ± {sb:.0f} | "
                     f"{p:.2f} [{lo:.2f}, {hi:.2f}] |")
    if not lines:
        return []
    return ["", "| scan speed, X vs Y | X: episode steps to 95 % | Y: episode steps to 95 % "
            "| P(X faster than Y) [95 % CI] |", "|---|---|---|---|", *lines, "",
            SCAN_SPEED_RULE]
