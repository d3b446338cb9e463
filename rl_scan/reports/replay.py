"""``rl-scan replay``: an interactive 3D HTML replay of one evaluation episode (plotly).

Cells are drawn at their face centres, green until scanned and blue after; each robot's
path grows frame by frame (wheeled robots orange, quads purple). A slider and a play
button step through frames (every ``every``-th env step). The file is self-contained
(plotly.js inlined), so it opens offline.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rl_scan.envs.sim.robots import QUAD

UNSCANNED, SCANNED = "#2e9e44", "#2563eb"
ROBOT_COLOURS = {"wheeled": "#ea7317", "quad": "#8b3fd9"}


@dataclass
class Recording:
    """What a replay needs from an episode."""

    cell_centres: np.ndarray  # (cells, 3) metres
    scanned_at: np.ndarray  # (cells,) env step a cell was scanned, -1 if never
    paths: np.ndarray  # (steps + 1, robots, 3) robot positions from the reset on
    robot_ids: list[str]
    extent: np.ndarray  # arena size (3,) metres
    metrics: dict[str, float]


def record_episode(core, team, seed: int = 0) -> Recording:
    """Play one episode of ``team`` on ``core`` (a ``ScanCore``) and record it."""
    obs = core.reset(seed=seed)
    world = core.world
    scanned_at = np.full(world.n_cells, -1, dtype=np.int64)
    paths = [world.pos.copy()]
    step = 0
    while True:
        obs, _, term, trunc, infos = core.step(team.act(obs))
        step += 1
        newly = (world.cell_state.astype(bool)) & (scanned_at < 0)
        scanned_at[newly] = step
        paths.append(world.pos.copy())
        if term or trunc:
            break
    kinds = ["quad" if k == QUAD else "wheeled" for k in world.kind]
    return Recording(cell_centres=world.cells.centre.copy(), scanned_at=scanned_at,
                     paths=np.array(paths), robot_ids=[f"{k}_{i}" for i, k in enumerate(kinds)],
                     extent=np.asarray(world.grid.extent, dtype=float),
                     metrics=dict(infos[core.agent_ids[0]]["episode_metrics"]))


def replay_figure(rec: Recording, every: int = 5, title: str = ""):
    """The plotly figure: one frame every ``every`` steps (and the last step)."""
    import plotly.graph_objects as go

    n_steps = len(rec.paths) - 1
    frame_steps = sorted(set(range(0, n_steps + 1, every)) | {n_steps})
    kinds = [rid.split("_")[0] for rid in rec.robot_ids]

    def traces(t: int) -> list:
        done = (rec.scanned_at >= 0) & (rec.scanned_at <= t)
        out = []
        for mask, colour, name in ((~done, UNSCANNED, "unscanned cells"),
                                   (done, SCANNED, "scanned cells")):
            c = rec.cell_centres[mask]
            out.append(go.Scatter3d(x=c[:, 0], y=c[:, 1], z=c[:, 2], mode="markers",
                                    name=name, marker={"size": 2.5, "color": colour}))
        for r, (rid, kind) in enumerate(zip(rec.robot_ids, kinds)):
            p = rec.paths[:t + 1, r]
            out.append(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="lines+markers",
                                    name=rid, line={"color": ROBOT_COLOURS[kind], "width": 4},
                                    marker={"size": [0] * (len(p) - 1) + [6],
                                            "color": ROBOT_COLOURS[kind]}))
        return out

    def coverage(t: int) -> float:
        return float(((rec.scanned_at >= 0) & (rec.scanned_at <= t)).mean())

    frames = [go.Frame(data=traces(t), name=str(t),
                       layout={"title": f"{title} step {t}: coverage {coverage(t):.1%}"})
              for t in frame_steps]
    x, y, z = rec.extent
    fig = go.Figure(data=traces(0), frames=frames)
    fig.update_layout(
        title=f"{title} step 0: coverage {coverage(0):.1%}",
        scene={"xaxis": {"range": [0, x]}, "yaxis": {"range": [0, y]},
               "zaxis": {"range": [0, z]}, "aspectmode": "manual",
               "aspectratio": {"x": 1, "y": y / x, "z": z / x}},
        updatemenus=[{"type": "buttons", "showactive": False, "buttons": [
            {"label": "play", "method": "animate",
             "args": [None, {"frame": {"duration": 120}, "fromcurrent": True}]},
            {"label": "pause", "method": "animate",
             "args": [[None], {"frame": {"duration": 0}, "mode": "immediate"}]}]}],
        sliders=[{"currentvalue": {"prefix": "step "}, "steps": [
            {"label": str(t), "method": "animate",
             "args": [[str(t)], {"frame": {"duration": 0}, "mode": "immediate"}]}
            for t in frame_steps]}])
    return fig


def write_replay(rec: Recording, out: str | Path, every: int = 5, title: str = "") -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    replay_figure(rec, every, title).write_html(str(out), include_plotlyjs=True,
                                                full_html=True, auto_play=False)
    return out
