"""The 3D replay: the recording matches the episode, and the HTML renders in headless
Chromium (WebGL through SwiftShader) with the scene drawn."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rl_scan.envs.core import ScanCore
from rl_scan.envs.heuristics import GreedyTeam
from rl_scan.reports.replay import record_episode, replay_figure, write_replay

DATA = Path(__file__).parent / "data"


def _recording(scenario="ablation", max_steps=40):
    core = ScanCore({"scenario": scenario, "max_steps": max_steps})
    return core, record_episode(core, GreedyTeam(core), seed=0)


def test_recording_matches_the_episode():
    core, rec = _recording(str(DATA / "one_box.yaml"))  # all 20 cells scanned: ends early
    world = core.world
    steps = len(rec.paths) - 1
    assert rec.paths.shape == (steps + 1, world.n_robots, 3) and 0 < steps < 40
    np.testing.assert_array_equal(rec.paths[-1], world.pos)
    assert int((rec.scanned_at >= 0).sum()) == world.n_scanned == world.n_cells == 20
    assert rec.scanned_at.max() == steps  # the last cell ended the episode
    assert rec.metrics["coverage"] == 1.0
    fig = replay_figure(rec, every=3)
    assert [int(f.name) for f in fig.frames] == sorted({*range(0, steps + 1, 3), steps})


def test_replay_renders_in_headless_chromium(tmp_path, chromium):
    _, rec = _recording()
    html = write_replay(rec, tmp_path / "replay.html", every=10, title="test")
    dom = chromium.dom(html)
    page = re.sub(r"<script.*?</script>", "", dom, flags=re.S)  # plotly.js itself is inlined
    assert "js-plotly-plot" in page and "gl-container" in page  # plotly drew a 3D scene
    assert "<canvas" in page and "WebGL is not supported" not in page
    pixels = chromium.screenshot(html, tmp_path / "shot.png")
    green = (pixels[:, 1] > 120) & (pixels[:, 0] < 90) & (pixels[:, 2] < 110)
    assert green.sum() > 200  # the unscanned cells are on screen
