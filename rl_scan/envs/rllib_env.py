"""RLlib ``MultiAgentEnv`` adapter over ``ScanCore``.

Agent ids are ``wheeled_i`` and ``quad_j``; map them to the two policy groups with
``policy_mapping_fn = lambda aid, *a, **k: kind_of(aid)``. All robots act every step.
``env_config`` is an ``EnvConfig`` mapping, plus an optional ``render_mode``
("rgb_array"). The last step's infos carry ``episode_metrics`` for callbacks and the
``scenario`` the episode ran on (MetaPOCA picks its tasks from DR batches by it).
"""

from __future__ import annotations

from typing import Any

from ray.rllib.env.multi_agent_env import MultiAgentEnv

from rl_scan.envs.core import RENDER_MODES, ScanCore, split_render_mode


class ScanMultiAgentEnv(MultiAgentEnv):
    """Multi-robot 3D scanning as an RLlib multi-agent env (new API stack)."""

    metadata = {"render_modes": list(RENDER_MODES)}

    def __init__(self, config: dict[str, Any] | None = None):
        super().__init__()
        env_config, self.render_mode = split_render_mode(config)
        self.core = ScanCore(env_config)
        self.possible_agents = list(self.core.agent_ids)
        self.agents = list(self.possible_agents)
        self.observation_spaces = dict(self.core.observation_spaces)
        self.action_spaces = dict(self.core.action_spaces)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs = self.core.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return obs, {aid: {} for aid in obs}

    def step(self, action_dict: dict[str, Any]):
        obs, rew, terminated, truncated, infos = self.core.step(action_dict)
        terms = {aid: terminated for aid in self.agents}
        truncs = {aid: truncated for aid in self.agents}
        terms["__all__"], truncs["__all__"] = terminated, truncated
        if terminated or truncated:
            self.agents = []
        return obs, rew, terms, truncs, infos

    def set_task(self, scenario: str) -> None:
        """Use ``scenario`` from the next reset on (domain randomisation, MAML tasks)."""
        self.core.set_scenario(scenario)

    def render(self):
        return self.core.render_rgb() if self.render_mode == "rgb_array" else None
