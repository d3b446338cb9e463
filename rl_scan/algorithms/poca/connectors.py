"""POCA's learner connector pieces.

``AddGroupColumns`` (early, after ``AddOneTsToEpisodesAndTruncate``) builds this update's
group table (every robot's observation and action at each step, stored once) and gives
every agent row its step in that table, its own slot and the group reward. RLlib
minibatches each module's rows independently, so each row must find its team's data on
its own (docs/library-facts.md); an index does that without copying the team's
observations into every robot's row.
``POCATargets`` (last, after ``NumpyToTensor``) runs the critic without gradients once per
step and computes lambda-returns of the group reward bootstrapped from V and the
counterfactual advantages; the critic then learns on the group table itself.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

from rl_scan.algorithms.poca import columns as C
from rl_scan.algorithms.poca.losses import explained_variance, lambda_returns, standardize
from rl_scan.algorithms.poca.modules import CRITIC_ID, TRAIN_TABLE
from rl_scan.results import EV_BASELINE, EV_VALUE


class AddGroupColumns(ConnectorV2):
    """Group observation/action/mask, own slot and group reward for every agent row."""

    def __init__(self, input_observation_space=None, input_action_space=None, *,
                 slots: list[str], obs_dim: int, act_dim: int, team_reward: bool = False,
                 mean_reward: bool = False):
        super().__init__(input_observation_space, input_action_space)
        self.slot_of = {aid: i for i, aid in enumerate(slots)}
        self.obs_dim, self.act_dim, self.team_reward = obs_dim, act_dim, team_reward
        self.mean_reward = mean_reward  # ablation: the group reward over the robots present

    def group_arrays(self, ma_episode) -> dict[str, np.ndarray]:
        """The per-step group arrays of one multi-agent episode chunk."""
        agents = ma_episode.agent_episodes
        lengths = {len(sa) for sa in agents.values()}
        if len(lengths) != 1:
            raise ValueError("POCA needs every robot to act at every step; episode "
                             f"{ma_episode.id_} has agent chunks of lengths {sorted(lengths)}")
        n, slots = lengths.pop(), len(self.slot_of)
        obs = np.zeros((n, slots, self.obs_dim), np.float32)
        act = np.zeros((n, slots, self.act_dim), np.float32)
        present = np.zeros((n, slots), np.float32)
        rew = None
        for aid, sa in agents.items():
            s = self.slot_of[aid]
            o = np.asarray(sa.get_observations(slice(0, n)), np.float32)
            a = np.asarray(sa.get_actions(slice(0, n)), np.float32)
            obs[:, s, :o.shape[1]] = o
            act[:, s, :a.shape[1]] = np.clip(a, -1.0, 1.0)  # what the env applied
            present[:, s] = 1.0
            r = np.asarray(sa.get_rewards(slice(0, n)), np.float32)
            if rew is None:
                rew = r.copy()
            elif not self.team_reward:
                rew += r  # individual rewards sum to the group reward
            elif not np.array_equal(rew, r):  # in team mode every robot holds it
                raise ValueError(f"reward_mode='team' but robot {aid} of episode "
                                 f"{ma_episode.id_} got rewards that differ from its team's")
        if self.mean_reward:
            rew = rew / np.maximum(present.sum(axis=1), 1.0)
        return {"obs": obs, "act": act, "present": present, "rew": rew}

    def __call__(self, *, rl_module, batch: dict[str, Any], episodes, explore=None,
                 shared_data=None, **kwargs) -> Any:
        groups, offsets, start = [], {}, 0
        for ma in episodes:
            groups.append(self.group_arrays(ma))
            offsets[ma.id_] = start
            start += len(groups[-1]["rew"])
        table = {k: np.concatenate([g[k] for g in groups]) for k in ("obs", "act", "present",
                                                                   "rew")}
        shared_data[C.GROUP_TABLE] = table
        # The same iteration order as RLlib's own pieces keeps every column row-aligned.
        for sa in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            n, first = len(sa), offsets[sa.multi_agent_episode_id]
            rows = np.arange(first, first + n)
            self.add_n_batch_items(batch, C.GROUP_ROW, rows, n, sa)
            self.add_n_batch_items(batch, C.GROUP_REW, table["rew"][rows], n, sa)
            self.add_n_batch_items(batch, C.SELF_IDX, np.full(n, self.slot_of[sa.agent_id]),
                                   n, sa)
        return batch


TARGET_CHUNK = 256  # steps per no-grad critic pass: cache-sized blocks run ~25% faster


class GroupMinibatches:
    """The critic's minibatches of table steps: each step once per pass, reshuffled per pass.

    RLlib's iterator passes ``num_epochs`` times over the largest module batch in
    minibatches of ``minibatch_size`` rows; a step minibatch of
    ``ceil(steps * minibatch_size / largest_module_rows)`` makes the critic pass over the
    steps as many times in as many minibatches.
    """

    def __init__(self, steps: torch.Tensor, size: int):
        self.steps, self.size = steps, max(1, size)
        self._order, self._pos = steps[:0], 0

    def next(self) -> torch.Tensor:
        if len(self.steps) == 0:
            return self.steps
        parts, need = [], self.size
        while need:
            if self._pos >= len(self._order):
                self._order = self.steps[torch.randperm(len(self.steps))]
                self._pos = 0
            part = self._order[self._pos:self._pos + need]
            self._pos += len(part)
            need -= len(part)
            parts.append(part)
        return torch.cat(parts)


class POCATargets(ConnectorV2):
    """Lambda-returns from V and advantages = returns - b_i, per policy row.

    Also hands the critic this update's group table with its targets and its minibatch
    schedule (``critic.minibatches``), under ``table_key``.
    """

    def __init__(self, input_observation_space=None, input_action_space=None, *,
                 gamma: float, lambda_: float, minibatch_size: int | None = None,
                 table_key: str = TRAIN_TABLE, value_baseline: bool = False):
        super().__init__(input_observation_space, input_action_space)
        self.gamma, self.lambda_, self.minibatch_size = gamma, lambda_, minibatch_size
        self.table_key = table_key
        self.value_baseline = value_baseline  # ablation: advantages G - V, no b_i

    def __call__(self, *, rl_module, batch: dict[str, Any], episodes, shared_data=None,
                 metrics=None, **kwargs) -> Any:
        critic = rl_module[CRITIC_ID]
        device = next(critic.parameters()).device
        table = {k: torch.as_tensor(v, device=device)
                 for k, v in shared_data[C.GROUP_TABLE].items()}
        with torch.no_grad():  # once per step for all robots, not once per agent row
            heads = [critic.group_heads(critic.encode(table["obs"][i:i + TARGET_CHUNK]),
                                        table["act"][i:i + TARGET_CHUNK],
                                        table["present"][i:i + TARGET_CHUNK])
                     for i in range(0, len(table["obs"]), TARGET_CHUNK)]
        # the critic predicts in normalised units; targets are built in return units
        step_values = critic.denormalize(torch.cat([v for v, _ in heads]))
        step_baselines = critic.denormalize(torch.cat([b for _, b in heads]))
        step_returns = step_values.clone()
        step_valid = torch.zeros(len(step_values), dtype=torch.bool, device=device)
        largest = 0
        for module_id in [m for m in batch if m != CRITIC_ID]:
            rows = batch[module_id]
            r = rows[C.GROUP_ROW].long()
            values, baselines = step_values[r], step_baselines[r, rows[C.SELF_IDX].long()]
            np_ = {k: rows[k].cpu().numpy() for k in (C.GROUP_REW, Columns.TERMINATEDS,
                                                       Columns.TRUNCATEDS, Columns.LOSS_MASK)}
            returns = lambda_returns(values.cpu().numpy(), np_[C.GROUP_REW],
                                     np_[Columns.TERMINATEDS], np_[Columns.TRUNCATEDS],
                                     self.gamma, self.lambda_)
            valid = np_[Columns.LOSS_MASK].astype(bool)
            if metrics is not None:  # how much of the return b_i explains, per kind
                metrics.log_value((module_id, EV_BASELINE), explained_variance(
                    returns[valid], baselines.cpu().numpy()[valid]), window=1)
            reference = values if self.value_baseline else baselines
            advantages = standardize(returns - reference.cpu().numpy(), np_[Columns.LOSS_MASK])
            rows[Postprocessing.ADVANTAGES] = torch.as_tensor(advantages, device=device)
            rows[C.RETURNS] = torch.as_tensor(returns, device=device)
            rows[C.OLD_VALUES], rows[C.OLD_BASELINES] = values, baselines
            # every robot of a step has the same group return and loss mask
            step_returns[r] = rows[C.RETURNS]
            step_valid[r] = rows[Columns.LOSS_MASK].bool()
            largest = max(largest, len(r))
        steps = step_valid.nonzero().squeeze(1)
        if metrics is not None:
            metrics.log_value((CRITIC_ID, EV_VALUE), explained_variance(
                step_returns[steps].cpu().numpy(), step_values[steps].cpu().numpy()), window=1)
        # The critic regresses in normalised units, the statistics now including this
        # batch's returns (its outputs are rescaled to match, so old = current at start).
        critic.update_return_stats(step_returns[steps])
        critic.set_group_table(self.table_key, obs=table["obs"], act=table["act"],
                               present=table["present"],
                               returns=critic.normalize(step_returns),
                               old_values=critic.normalize(step_values),
                               old_baselines=critic.normalize(step_baselines))
        size = (math.ceil(len(steps) * self.minibatch_size / largest)
                if self.minibatch_size and largest else len(steps))
        critic.minibatches[self.table_key] = GroupMinibatches(steps, size)
        return batch
