"""Actions for all agents of all acting worlds: one forward pass per module per step.

Does what RLlib's default env-to-module and module-to-env pipelines do for a batch of
Box observations, without per-agent Python: the module's forward_exploration (or
forward_inference when not exploring), sampling from its action distribution (the
deterministic one when not exploring), log-probabilities, and the env actions
unsquashed (``normalize_actions``) or clipped (``clip_actions``) to the action space.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.utils.metrics import WEIGHTS_SEQ_NO
from ray.rllib.utils.spaces.space_utils import clip_action, unsquash_action

from rl_scan.algorithms.fast_runner.team import TeamSlots


@dataclass
class ModuleActions:
    """One module's batch: what the episodes store and what the envs get."""

    actions: np.ndarray
    for_env: np.ndarray
    outputs: dict[str, np.ndarray]
    """Every other model output (e.g. action_dist_inputs, action_logp) and the weights'
    sequence number, as the stock runner stores them in the episodes."""


class BatchedPolicy:
    """Acts with a runner's MultiRLModule on batched observations."""

    def __init__(self, module, team: TeamSlots, *, normalize_actions: bool,
                 clip_actions: bool):
        self.module, self.team = module, team
        self.normalize, self.clip = normalize_actions, clip_actions

    def act(self, obs: dict[str, np.ndarray], *, explore: bool, t: int,
            weights_seq_no: int) -> dict[str, ModuleActions]:
        out = {}
        for mid, rows in obs.items():
            module = self.module[mid]
            batch = {Columns.OBS: torch.from_numpy(rows)}
            with torch.no_grad():
                fwd = (module.forward_exploration(batch, t=t) if explore
                       else module.forward_inference(batch))
                if Columns.ACTIONS not in fwd:
                    dist_cls = (module.get_exploration_action_dist_cls() if explore
                                else module.get_inference_action_dist_cls())
                    dist = dist_cls.from_logits(fwd[Columns.ACTION_DIST_INPUTS])
                    if not explore:
                        dist = dist.to_deterministic()
                    fwd[Columns.ACTIONS] = dist.sample()
                    if Columns.ACTION_LOGP not in fwd:
                        fwd[Columns.ACTION_LOGP] = dist.logp(fwd[Columns.ACTIONS])
            outputs = {k: v.numpy() for k, v in fwd.items()}
            actions = outputs.pop(Columns.ACTIONS)
            outputs[WEIGHTS_SEQ_NO] = np.full(len(actions), weights_seq_no)
            out[mid] = ModuleActions(actions, self._for_env(mid, actions), outputs)
        return out

    def _for_env(self, mid: str, actions: np.ndarray) -> np.ndarray:
        """NormalizeAndClipActions on a batch: the same arithmetic, row by row."""
        space = self.team.modules[mid].action_space
        if self.normalize:
            return unsquash_action(actions, space)
        if self.clip:
            return clip_action(actions, space)
        return actions
