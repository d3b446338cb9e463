"""Hypothesis property tests of the episode invariants over scenarios, teams and actions."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rl_scan.envs.core import ScanCore

TEAMS = [(2, 2), (0, 4), (4, 0), (1, 3), (3, 1)]
SCENARIOS = ["ablation", "train:0", "train:11", "train:512", "test:3"]


@st.composite
def episodes(draw):
    team = draw(st.sampled_from(TEAMS))
    config = {"scenario": draw(st.sampled_from(SCENARIOS)),
              "team": {"wheeled": team[0], "quad": team[1]},
              "comm_scheme": draw(st.integers(1, 7)),
              "reward_mode": draw(st.sampled_from(["individual", "team"])),
              "max_steps": draw(st.integers(5, 40))}
    return config, draw(st.integers(0, 2**31 - 1)), draw(st.integers(0, 2**31 - 1))


@settings(max_examples=25, deadline=None)
@given(episodes())
def test_episode_invariants(case):
    config, seed, action_seed = case
    core = ScanCore(config)
    obs = core.reset(seed=seed)
    w = core.world
    rng = np.random.default_rng(action_seed)
    spaces = core.observation_spaces
    assert all(o.dtype == np.float32 and spaces[a].contains(o) for a, o in obs.items())
    state = w.cell_state.copy()
    scanned, collisions, total_reward = 0, 0, 0.0
    while not core.done:
        # wide actions: out-of-range values must be clipped, not break anything
        acts = {a: rng.uniform(-2, 2, sp.shape) for a, sp in core.action_spaces.items()}
        obs, rew, term, trunc, infos = core.step(acts)
        assert all(spaces[a].contains(o) for a, o in obs.items())
        assert np.all(w.cell_state >= state)  # scanned cells never un-scan
        scanned += int((w.cell_state != state).sum())
        state = w.cell_state.copy()
        hits = int((w.collided != 0).sum())
        collisions += hits
        step_sum = int(w.new_cells.sum()) - hits
        if config["reward_mode"] == "team":
            assert all(r == step_sum for r in rew.values())
        else:
            assert sum(rew.values()) == step_sum
        total_reward += step_sum
    # reward sum over the episode = cells scanned - collisions
    assert total_reward == scanned - collisions == w.n_scanned - collisions
    m = infos[core.agent_ids[0]]["episode_metrics"]
    assert m["coverage"] == w.n_scanned / w.n_cells == m["cells_scanned"] / m["cells_total"]
    assert m["success"] == float(m["coverage"] >= 0.95)
    assert m["collisions"] == collisions
    reached = [m[k] for k in ("steps_to_50", "steps_to_80", "steps_to_95")
               if not math.isnan(m[k])]
    assert reached == sorted(reached)
    assert m["episode_steps"] == core.t == config["max_steps"] or term
