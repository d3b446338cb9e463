"""PettingZoo ``ParallelEnv`` adapter over ``ScanCore`` (same ids, spaces and dynamics)."""

from __future__ import annotations

import functools
from typing import Any

from pettingzoo import ParallelEnv

from rl_scan.envs.core import RENDER_MODES, ScanCore, split_render_mode


class ScanParallelEnv(ParallelEnv):
    """Multi-robot 3D scanning as a PettingZoo parallel env."""

    metadata = {"render_modes": list(RENDER_MODES), "name": "rl_scan_v0",
                "is_parallelizable": True}

    def __init__(self, config: dict[str, Any] | None = None, render_mode: str | None = None):
        config = dict(config or {})
        if render_mode is not None:
            config["render_mode"] = render_mode
        env_config, self.render_mode = split_render_mode(config)
        self.core = ScanCore(env_config)
        self.possible_agents = list(self.core.agent_ids)
        self.agents: list[str] = []

    @functools.cache  # noqa: B019 - spaces must be the same objects
    def observation_space(self, agent: str):
        return self.core.observation_spaces[agent]

    @functools.cache  # noqa: B019
    def action_space(self, agent: str):
        return self.core.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.core.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return obs, {aid: {} for aid in obs}

    def step(self, actions: dict[str, Any]):
        obs, rew, terminated, truncated, infos = self.core.step(actions)
        terms = {aid: terminated for aid in self.agents}
        truncs = {aid: truncated for aid in self.agents}
        if terminated or truncated:
            self.agents = []
        return obs, rew, terms, truncs, infos

    def render(self):
        return self.core.render_rgb() if self.render_mode == "rgb_array" else None

    def close(self):
        pass
