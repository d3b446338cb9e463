"""POCA's learner connector pieces.

``AddGroupColumns`` (early, after ``AddOneTsToEpisodesAndTruncate``) copies every robot's
observation and action at each step into each agent row, plus the row's own slot and the
group reward, so that every row is self-contained: RLlib minibatches each module's rows
independently, so cross-agent inputs cannot be joined later (notes/rllib-2.60.md 3.2).
``POCATargets`` (last, after ``NumpyToTensor``) runs the critic without gradients and
computes lambda-returns of the group reward bootstrapped from V and the counterfactual
advantages; the critic later learns on the same policy rows.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

from rl_scan.algorithms.poca import columns as C
from rl_scan.algorithms.poca.losses import lambda_returns, standardize
from rl_scan.algorithms.poca.modules import CRITIC_ID


class AddGroupColumns(ConnectorV2):
    """Group observation/action/mask, own slot and group reward for every agent row."""

    def __init__(self, input_observation_space=None, input_action_space=None, *,
                 slots: list[str], obs_dim: int, act_dim: int, team_reward: bool = False):
        super().__init__(input_observation_space, input_action_space)
        self.slot_of = {aid: i for i, aid in enumerate(slots)}
        self.obs_dim, self.act_dim, self.team_reward = obs_dim, act_dim, team_reward

    def group_arrays(self, ma_episode) -> dict[str, np.ndarray]:
        """The per-step group arrays of one multi-agent episode chunk."""
        agents = ma_episode.agent_episodes
        lengths = {len(sa) for sa in agents.values()}
        if len(lengths) != 1:
            raise ValueError("POCA needs every robot to act at every step; episode "
                             f"{ma_episode.id_} has agent chunks of lengths {sorted(lengths)}")
        n, slots = lengths.pop(), len(self.slot_of)
        # float16 halves the bytes RLlib copies while batching these replicated rows; all
        # observation entries lie in [-1, 1] (3 significant digits are plenty for a critic).
        obs = np.zeros((n, slots, self.obs_dim), np.float16)
        act = np.zeros((n, slots, self.act_dim), np.float32)
        present = np.zeros((n, slots), np.float32)
        rew = np.zeros(n, np.float32)
        for aid, sa in agents.items():
            s = self.slot_of[aid]
            o = np.asarray(sa.get_observations(slice(0, n)), np.float32)
            a = np.asarray(sa.get_actions(slice(0, n)), np.float32)
            obs[:, s, :o.shape[1]] = o
            act[:, s, :a.shape[1]] = np.clip(a, -1.0, 1.0)  # what the env applied
            present[:, s] = 1.0
            r = np.asarray(sa.get_rewards(slice(0, n)), np.float32)
            # individual rewards sum to the group reward; in team mode all agents hold it
            rew = np.maximum(rew, r) if self.team_reward else rew + r
        return {C.GROUP_OBS: obs, C.GROUP_ACT: act, C.GROUP_MASK: present, C.GROUP_REW: rew}

    def __call__(self, *, rl_module, batch: dict[str, Any], episodes, explore=None,
                 shared_data=None, **kwargs) -> Any:
        groups = {ma.id_: self.group_arrays(ma) for ma in episodes}
        # The same iteration order as RLlib's own pieces keeps every column row-aligned.
        for sa in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            group, n = groups[sa.multi_agent_episode_id], len(sa)
            for column, values in group.items():
                self.add_n_batch_items(batch, column, values[:n], n, sa)
            self.add_n_batch_items(batch, C.SELF_IDX, np.full(n, self.slot_of[sa.agent_id]),
                                   n, sa)
        return batch


class POCATargets(ConnectorV2):
    """Lambda-returns from V and advantages = returns - b_i, per policy row."""

    def __init__(self, input_observation_space=None, input_action_space=None, *,
                 gamma: float, lambda_: float):
        super().__init__(input_observation_space, input_action_space)
        self.gamma, self.lambda_ = gamma, lambda_

    def __call__(self, *, rl_module, batch: dict[str, Any], episodes, **kwargs) -> Any:
        critic = rl_module[CRITIC_ID]
        for module_id in [m for m in batch if m != CRITIC_ID]:
            rows = batch[module_id]
            with torch.no_grad():
                values, baselines = critic.values_and_baselines(
                    rows[C.GROUP_OBS], rows[C.GROUP_ACT], rows[C.SELF_IDX], rows[C.GROUP_MASK])
            np_ = {k: rows[k].cpu().numpy() for k in (C.GROUP_REW, Columns.TERMINATEDS,
                                                       Columns.TRUNCATEDS, Columns.LOSS_MASK)}
            returns = lambda_returns(values.cpu().numpy(), np_[C.GROUP_REW],
                                     np_[Columns.TERMINATEDS], np_[Columns.TRUNCATEDS],
                                     self.gamma, self.lambda_)
            advantages = standardize(returns - baselines.cpu().numpy(), np_[Columns.LOSS_MASK])
            device = values.device
            rows[Postprocessing.ADVANTAGES] = torch.as_tensor(advantages, device=device)
            rows[C.RETURNS] = torch.as_tensor(returns, device=device)
            rows[C.OLD_VALUES], rows[C.OLD_BASELINES] = values, baselines
        return batch
