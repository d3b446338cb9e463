"""Metric names, in one place: the env, callbacks, benchmarks and reports import them."""

import math
from typing import Any

import numpy as np

COVERAGE = "coverage"  # scanned cells / all cells at episode end (paper: scanning success rate)
SUCCESS = "success"  # 1.0 if coverage >= SUCCESS_COVERAGE else 0.0
SUCCESS_COVERAGE = 0.95
SPEED_AT = 0.8
"""Learning / adaptation speed is the env steps to this evaluation coverage (``steps_to_reach``)
in every report and in the meta-MRSS protocol."""
STEPS_TO = {0.5: "steps_to_50", 0.8: "steps_to_80", 0.95: "steps_to_95"}  # NaN if not reached
REACHED = {key: "reached_" + key[len("steps_to_"):] for key in STEPS_TO.values()}
"""An evaluation's share of episodes that reached a ``STEPS_TO`` coverage (whose value there
is the mean over those episodes)."""
COLLISIONS = "collisions"  # all robots
COLLISIONS_BY_KIND = {"wheeled": "collisions_wheeled", "quad": "collisions_quad"}
RETURN_BY_KIND = {"wheeled": "return_wheeled", "quad": "return_quad"}  # mean over robots of a kind
EPISODE_STEPS = "episode_steps"
CELLS_SCANNED = "cells_scanned"
CELLS_TOTAL = "cells_total"

EPISODE_METRICS = (COVERAGE, SUCCESS, *STEPS_TO.values(), COLLISIONS,
                   *COLLISIONS_BY_KIND.values(), *RETURN_BY_KIND.values(), EPISODE_STEPS,
                   CELLS_SCANNED, CELLS_TOTAL)


def steps_to_reach(curve: list[tuple[float, float]], target: float) -> float | None:
    """Env steps of the first of two consecutive evaluations at or above ``target`` in a
    curve of (env steps, mean coverage) (None if never): one noisy evaluation of a few
    episodes does not count as reaching it. The reports and the meta-MRSS protocol use it."""
    return next((curve[i][0] for i in range(len(curve) - 1)
                 if curve[i][1] >= target and curve[i + 1][1] >= target), None)


def curve_metrics(entries: list[dict[str, Any]], budget: float,
                  target: float = SPEED_AT) -> dict[str, float]:
    """One adaptation curve's figures, defined up front (the meta-MRSS protocol's summary and
    the report's adaptation table): final coverage, env steps to ``target`` (the first of
    two consecutive evaluations at or above it; ``budget`` if never: censored, with
    ``reached`` 0), the area under the coverage curve over [0, budget] as a fraction (a
    held value before the first and after the last evaluation), final success, and the
    start weights' coverage (evaluation 0, else nan)."""
    if not entries:
        return {"final_coverage": math.nan, "steps_to_80": math.nan, "reached_80": math.nan,
                "auc": math.nan, "success": math.nan, "start_coverage": math.nan}
    steps = [float(e["env_steps"]) for e in entries]
    cover = [float(e.get(COVERAGE, 0.0)) for e in entries]
    first = steps_to_reach(list(zip(steps, cover)), target)
    xs = [0.0, *steps, max(budget, steps[-1])]
    ys = [cover[0], *cover, cover[-1]]
    auc = float(np.trapezoid(ys, xs) / xs[-1]) if xs[-1] > 0 else math.nan
    start = cover[0] if steps[0] == 0 else math.nan
    return {"final_coverage": cover[-1],
            "steps_to_80": float(first) if first is not None else float(budget),
            "reached_80": float(first is not None), "auc": auc,
            "success": float(entries[-1].get(SUCCESS, math.nan)),
            "start_coverage": float(start)}
