"""The report's heterogeneity map: where 2 wheeled + 2 quads beat a homogeneous team.

Reads the ``hetero_map.json`` of every ``rl-scan experiment hetero-map`` study under the
results folder (written by ``rl_scan.tuning.hetero``) and draws its grid as a heatmap of
mixed minus best homogeneous time-averaged coverage of the scripted greedy team. Trained
points: every ``team`` ablation study in the same results whose EnvConfig (its ``--set``
overrides) is a grid point's is marked on that cell with its trained teams' difference
(final coverage, mean over seeds) and tabled with P(mixed > best homogeneous).
"""

from __future__ import annotations

import itertools
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan import results as R
from rl_scan.reports.collect import Collection
from rl_scan.reports.stats import probability_of_improvement, probability_of_improvement_ci
from rl_scan.studies import TEAM_HOMOGENEOUS as HOMOGENEOUS
from rl_scan.studies import TEAM_MIXED as MIXED

ROW_AXES = ("wheeled_sensor", "quad_speed", "quad_range")  # the heatmap's rows; columns:
COLUMN_AXIS = "flight_time"  # 0 = unlimited


def _label(axis: str, value: Any) -> str:
    if axis == COLUMN_AXIS:
        return "unlimited" if value == 0 else f"{value:g} s"
    if axis == "wheeled_sensor":
        return f"wheeled {value}"
    return f"quad {value:g} m/s" if axis == "quad_speed" else f"range {value:g} m"


def _rows_cols(data: dict[str, Any]) -> tuple[list[tuple], list]:
    axes = data["axes"]
    return list(itertools.product(*[axes[a] for a in ROW_AXES])), list(axes[COLUMN_AXIS])


def cell(data: dict[str, Any], params: dict[str, Any]) -> tuple[int, int] | None:
    """A point's (row, column) in the heatmap (None: outside the map's axes)."""
    rows, cols = _rows_cols(data)
    key = tuple(params[a] for a in ROW_AXES)
    if key not in rows or params[COLUMN_AXIS] not in cols:
        return None
    return rows.index(key), cols.index(params[COLUMN_AXIS])


def map_grid(data: dict[str, Any]) -> tuple[list[str], list[str], np.ndarray]:
    """Row labels, column labels and the value per cell (NaN: not evaluated yet)."""
    rows, cols = _rows_cols(data)
    values = np.full((len(rows), len(cols)), np.nan)
    for p in data["points"]:
        if (at := cell(data, p["params"])) is not None:
            values[at] = p["value"]
    row_labels = [", ".join(_label(a, v) for a, v in zip(ROW_AXES, r)) for r in rows]
    return row_labels, [_label(COLUMN_AXIS, c) for c in cols], values


def env_key(env: dict[str, Any]) -> str:
    """An EnvConfig's settings but its team and scenario: equal keys = the same map point
    (the map's greedy scenes are not the trained study's)."""
    from rl_scan.config import to_dict
    from rl_scan.envs.sim.env_config import make_env_config

    settings = to_dict(make_env_config(env))
    for key in ("team", "scenario"):
        settings.pop(key)
    return json.dumps(settings, sort_keys=True)


def _team_finals(runs: Collection, group: str) -> tuple[dict[str, list[float]], dict[str, str]]:
    """Final coverages per team of a team study, and the teams it borrowed (from which
    study: ``reports.borrow``)."""
    finals, borrowed = defaultdict(list), {}
    for r in runs.runs:
        if r.group == group and r.evals:
            finals[r.condition].append(r.final_coverage)
            if r.borrowed_from:
                borrowed[r.condition] = r.borrowed_from[0]
    return finals, borrowed


def trained_points(data: dict[str, Any], runs: Collection) -> list[dict[str, Any]]:
    """The team studies run at a point of this map: per study its point, the mean final
    coverage of the mixed and of the best homogeneous team (a homogeneous team it did not
    train is borrowed, ``reports.borrow``), and P(mixed > it)."""
    points = {env_key(p["env"]): p for p in data["points"] if "env" in p}
    out = []
    for group, kind in sorted(runs.kinds.items()):
        point = points.get(env_key(runs.envs.get(group, {}))) if kind == "study:team" else None
        if point is None:
            continue
        finals, borrowed = _team_finals(runs, group)
        homo = {c: float(np.mean(finals[c])) for c in HOMOGENEOUS if c in finals}
        if MIXED not in finals or not homo:
            continue
        steps = max(int(r.evals[-1]["env_steps"]) for r in runs.runs
                    if r.group == group and r.evals and not r.borrowed_from)
        best = max(homo, key=homo.get)
        out.append({"group": group, "params": point["params"], "greedy": point["value"],
                    "env_steps": steps, "mixed": float(np.mean(finals[MIXED])),
                    "best_homo": best, "homo": homo[best],
                    "value": float(np.mean(finals[MIXED])) - homo[best],
                    "seeds": {c: len(v) for c, v in finals.items()}, "borrowed": borrowed,
                    "p": probability_of_improvement(finals[MIXED], finals[best]),
                    "ci": probability_of_improvement_ci(finals[MIXED], finals[best])})
    return out


def plot_map(data: dict[str, Any], title: str, out: Path,
             trained: list[dict[str, Any]] = ()) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols, values = map_grid(data)
    limit = max(float(np.nanmax(np.abs(values))), 1e-3)
    fig, ax = plt.subplots(figsize=(2.0 + 1.1 * len(cols), 1.2 + 0.42 * len(rows)), dpi=110)
    image = ax.imshow(values, cmap="RdBu", vmin=-limit, vmax=limit, aspect="auto")
    marks = {}
    for t in trained:  # the study with the most runs at a point is the one drawn
        i, j = cell(data, t["params"])  # a trained point is a point of the map
        if (i, j) not in marks or sum(t["seeds"].values()) > sum(marks[i, j]["seeds"].values()):
            marks[i, j] = t
    for (i, j), v in np.ndenumerate(values):
        if not np.isnan(v):
            text = f"{100 * v:+.1f}"
            if (i, j) in marks:
                text += f"\nT {100 * marks[i, j]['value']:+.1f}"
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=2))
            ax.text(j, i, text, ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(cols)), cols, fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=7)
    ax.set_xlabel("quad flight time per episode")
    ax.set_title(f"{title}: mixed - best homogeneous team\n(greedy, time-averaged "
                 "coverage, points; blue: the mixed team wins;\nT: trained POCA, final "
                 "coverage)" if marks else f"{title}: mixed - best homogeneous team\n"
                 "(greedy, time-averaged coverage, points; blue: the mixed team wins)",
                 fontsize=9)
    fig.colorbar(image, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def hetero_map_lines(results_dir: Path, figures: Path, runs: Collection) -> list[str]:
    """The map section of every hetero-map study under ``results_dir`` (none: []), with
    the team studies among ``runs`` that trained at its points."""
    md: list[str] = []
    for path in sorted(results_dir.rglob(R.HETERO_MAP)):
        data = json.loads(path.read_text())
        name = path.parent.name
        points = data["points"]
        if not points:
            continue
        trained = trained_points(data, runs)
        fig = plot_map(data, name, figures / f"hetero_map_{name}.png", trained)
        wins = [p for p in points if p["value"] > 0]
        best = max(points, key=lambda p: p["value"])
        md += [f"## Heterogeneity map: {name}", "",
               f"The scripted greedy team as 2 wheeled + 2 quads, 4 quads and 4 wheeled on "
               f"{len(data['scenes'])} scenes ({data['scenes'][0]} ..) at {len(points)} grid "
               "points of the parameters the paper leaves open. Value: the mixed team's "
               "time-averaged coverage (mean over the episode of the coverage reached) "
               "minus the better homogeneous team's. The greedy team is privileged and "
               "scripted: the map says where heterogeneity can pay, trained teams say "
               "whether learning finds it.", "",
               f"![hetero map {name}](figures/{fig.name})", "",
               f"The mixed team wins at **{len(wins)} of {len(points)}** points; largest "
               f"margin {100 * best['value']:+.1f} points at "
               + ", ".join(f"{k}={v}" for k, v in best["params"].items()) + ".", "",
               "| " + " | ".join(data["axes"]) + " | mixed | 4 quads | 4 wheeled | "
               "mixed - best homo | final coverage mixed / quads / wheeled |",
               "|" + "---|" * (len(data["axes"]) + 5)]
        for p in points:
            m, f = p["mean"], p["final"]
            md.append("| " + " | ".join(str(p["params"][a]) for a in data["axes"])
                      + f" | {100 * m['mixed']:.1f} | {100 * m['quads']:.1f} | "
                      f"{100 * m['wheeled']:.1f} | {100 * p['value']:+.1f} | "
                      f"{100 * f['mixed']:.1f} / {100 * f['quads']:.1f} / "
                      f"{100 * f['wheeled']:.1f} |")
        md += _trained_lines(trained) + [""]
    return md


def _trained_lines(trained: list[dict[str, Any]]) -> list[str]:
    if not trained:
        return []
    lines = ["", "Trained points (boxed, T): `rl-scan ablate team` studies run at a point "
             "(POCA on the study's scene, final coverage of each run's last evaluation, mean "
             "over seeds; best homo = the better homogeneous team; one the study did not train is "
             "taken from the study that trained it where its own robots' settings are the "
             "same, marked \"from\"). P(mixed > best homo) is over the pairs of runs, with "
             "a bootstrap CI.", "",
             "| study | point | env steps | seeds per team | mixed % | best homo % | "
             "trained mixed - best homo | P(mixed > best homo) [95 % CI] | greedy |",
             "|---|---|---|---|---|---|---|---|---|"]
    for t in trained:
        point = ", ".join(f"{v}" for v in t["params"].values())
        seeds = ", ".join(f"{c}: {n}" + (f" (from {t['borrowed'][c]})"
                                          if c in t["borrowed"] else "")
                          for c, n in sorted(t["seeds"].items()))
        lines.append(f"| {t['group']} | {point} | {t['env_steps']:,} | {seeds} | "
                     f"{100 * t['mixed']:.1f} | {100 * t['homo']:.1f} ({t['best_homo']}) | "
                     f"{100 * t['value']:+.1f} | {t['p']:.2f} [{t['ci'][0]:.2f}, "
                     f"{t['ci'][1]:.2f}] | {100 * t['greedy']:+.1f} |")
    return lines
