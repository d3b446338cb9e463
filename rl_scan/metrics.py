"""Metric names, in one place: the env, callbacks, benchmarks and reports import them."""

COVERAGE = "coverage"  # scanned cells / all cells at episode end (paper: scanning success rate)
SUCCESS = "success"  # 1.0 if coverage >= SUCCESS_COVERAGE else 0.0
SUCCESS_COVERAGE = 0.95
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
