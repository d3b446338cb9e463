"""The report's heterogeneity map: where 2 wheeled + 2 quads beat a homogeneous team.

Reads the ``hetero_map.json`` of every ``rl-scan experiment hetero-map`` study under the
results folder (written by ``rl_scan.tuning.hetero``) and draws its grid as a heatmap of
mixed minus best homogeneous time-averaged coverage of the scripted greedy team.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan import results as R

ROW_AXES = ("wheeled_sensor", "quad_speed", "quad_range")  # the heatmap's rows; columns:
COLUMN_AXIS = "flight_time"  # 0 = unlimited


def _label(axis: str, value: Any) -> str:
    if axis == COLUMN_AXIS:
        return "unlimited" if value == 0 else f"{value:g} s"
    if axis == "wheeled_sensor":
        return f"wheeled {value}"
    return f"quad {value:g} m/s" if axis == "quad_speed" else f"range {value:g} m"


def map_grid(data: dict[str, Any]) -> tuple[list[str], list[str], np.ndarray]:
    """Row labels, column labels and the value per cell (NaN: not evaluated yet)."""
    axes = data["axes"]
    rows = list(itertools.product(*[axes[a] for a in ROW_AXES]))
    cols = list(axes[COLUMN_AXIS])
    values = np.full((len(rows), len(cols)), np.nan)
    for p in data["points"]:
        key = tuple(p["params"][a] for a in ROW_AXES)
        if key in rows and p["params"][COLUMN_AXIS] in cols:
            values[rows.index(key), cols.index(p["params"][COLUMN_AXIS])] = p["value"]
    row_labels = [", ".join(_label(a, v) for a, v in zip(ROW_AXES, r)) for r in rows]
    return row_labels, [_label(COLUMN_AXIS, c) for c in cols], values


def plot_map(data: dict[str, Any], title: str, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols, values = map_grid(data)
    limit = max(float(np.nanmax(np.abs(values))), 1e-3)
    fig, ax = plt.subplots(figsize=(2.0 + 1.1 * len(cols), 1.2 + 0.42 * len(rows)), dpi=110)
    image = ax.imshow(values, cmap="RdBu", vmin=-limit, vmax=limit, aspect="auto")
    for (i, j), v in np.ndenumerate(values):
        if not np.isnan(v):
            ax.text(j, i, f"{100 * v:+.1f}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(cols)), cols, fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=7)
    ax.set_xlabel("quad flight time per episode")
    ax.set_title(f"{title}: mixed - best homogeneous team\n(greedy, time-averaged "
                 "coverage, points; blue: the mixed team wins)", fontsize=9)
    fig.colorbar(image, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def hetero_map_lines(results_dir: Path, figures: Path) -> list[str]:
    """The map section of every hetero-map study under ``results_dir`` (none: [])."""
    md: list[str] = []
    for path in sorted(results_dir.rglob(R.HETERO_MAP)):
        data = json.loads(path.read_text())
        name = path.parent.name
        points = data["points"]
        if not points:
            continue
        fig = plot_map(data, name, figures / f"hetero_map_{name}.png")
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
        md.append("")
    return md
