"""Gymnasium spaces of the scanning env (per robot kind) and the obs-vector layout.

Every observation entry is scaled into [-1, 1] (rays, normalised positions and
velocities, cos/sin of yaw), so one Box(-1, 1) per kind describes it. Actions are
Box(-1, 1) with 3 dims for wheeled robots and 5 for quads (see ``sim/robots.py``).
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.robots import ACTION_DIMS
from rl_scan.envs.sim.world import observation_layout


def kind_of(agent_id: str) -> str:
    """'wheeled_1' -> 'wheeled' (also the RLlib policy/module id of the agent)."""
    return agent_id.rsplit("_", 1)[0]


def observation_spaces(config: EnvConfig) -> dict[str, spaces.Box]:
    """One observation space per agent id."""
    dims = observation_layout(config).dims
    return {aid: spaces.Box(-1.0, 1.0, (dims[kind_of(aid)],), np.float32)
            for aid in config.team.agent_ids}


def action_spaces(config: EnvConfig) -> dict[str, spaces.Box]:
    """One action space per agent id (wheeled: forward, left, yaw; quad: + up, pitch)."""
    return {aid: spaces.Box(-1.0, 1.0, (ACTION_DIMS[kind_of(aid)],), np.float32)
            for aid in config.team.agent_ids}
