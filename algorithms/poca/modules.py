"""POCA's RLModules: one Gaussian actor per robot kind and one centralized critic.

The critic is learner-only (never shipped to env runners) and shared by both kinds. Per
kind it has an observation encoder and an observation+action encoder (entity
embeddings); a residual self-attention block with key masks for absent robots and a
masked mean pool turn the team's entities into one vector, as in ML-Agents'
``MultiAgentNetworkBody``:
  V(s)        from every robot's observation entity;
  b_i(s, a_-i) from robot i's observation entity and the others' observation+action ones.
Slots are fixed per env config (team order: wheeled robots, then quads), so any team mix
works; observation and action vectors are zero-padded to the largest kind.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis import SelfSupervisedLossAPI
from ray.rllib.core.rl_module.torch import TorchRLModule
from torch import nn

from rl_scan.algorithms.poca import columns as C
from rl_scan.algorithms.poca.losses import poca_critic_loss, trust_region_value_loss

CRITIC_ID = "critic"


def mlp(sizes: list[int], activation=nn.ReLU) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), activation()]
    return nn.Sequential(*layers)


class GaussianActor(TorchRLModule):
    """Decentralized actor: MLP encoder (the paper's 3 layers) -> mean; free log-std."""

    def setup(self) -> None:
        hiddens = list(self.model_config.get("hiddens", [256, 256, 128]))
        n_in, n_act = self.observation_space.shape[0], self.action_space.shape[0]
        self.encoder = mlp([n_in, *hiddens])
        self.mean = nn.Linear(hiddens[-1], n_act)
        nn.init.normal_(self.mean.weight, std=0.01)
        nn.init.zeros_(self.mean.bias)
        self.log_std = nn.Parameter(torch.zeros(n_act))

    def _forward(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        mean = self.mean(self.encoder(batch[Columns.OBS]))
        return {Columns.ACTION_DIST_INPUTS: torch.cat(
            [mean, self.log_std.expand_as(mean)], dim=-1)}


class ResidualSelfAttention(nn.Module):
    """LayerNorm -> multi-head self-attention (masked keys) -> residual -> LayerNorm -> pool."""

    def __init__(self, size: int, heads: int):
        super().__init__()
        self.norm_in, self.norm_out = nn.LayerNorm(size), nn.LayerNorm(size)
        self.attention = nn.MultiheadAttention(size, heads, batch_first=True)

    def forward(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        x = self.norm_in(tokens)
        attended, _ = self.attention(x, x, x, key_padding_mask=~present, need_weights=False)
        x = self.norm_out(tokens + attended)
        weights = present.unsqueeze(-1).to(x.dtype)
        return (x * weights).sum(1) / weights.sum(1).clamp(min=1.0)


class POCACritic(TorchRLModule, SelfSupervisedLossAPI):
    """Centralized value V and counterfactual baselines b_i, with its own regression loss.

    ``model_config``: ``slot_kinds`` (kind index per slot), ``obs_dims`` and ``act_dims``
    (per kind), ``hidden`` (entity size), ``heads`` (attention heads).
    """

    def setup(self) -> None:
        cfg = self.model_config
        self.slot_kinds = list(cfg["slot_kinds"])
        self.obs_dims, self.act_dims = list(cfg["obs_dims"]), list(cfg["act_dims"])
        h = int(cfg.get("hidden", 128))
        kinds = range(len(self.obs_dims))
        self.obs_encoders = nn.ModuleList(
            mlp([self.obs_dims[k], h, h]) if self.obs_dims[k] else nn.Identity() for k in kinds)
        self.obs_action_encoders = nn.ModuleList(
            mlp([self.obs_dims[k] + self.act_dims[k], h, h]) if self.obs_dims[k]
            else nn.Identity() for k in kinds)
        self.attention = ResidualSelfAttention(h, int(cfg.get("heads", 4)))
        self.body = mlp([h + 1, h, h])
        self.head = nn.Linear(h, 1)
        self.hidden = h
        self._slots_of = {k: [s for s, sk in enumerate(self.slot_kinds) if sk == k]
                          for k in kinds}

    def _embed(self, encoders: nn.ModuleList, group_obs: torch.Tensor,
               group_act: torch.Tensor | None) -> torch.Tensor:
        tokens = group_obs.new_zeros(*group_obs.shape[:2], self.hidden)
        for k, slots in self._slots_of.items():
            if not slots:
                continue
            x = group_obs[:, slots, :self.obs_dims[k]]
            if group_act is not None:
                x = torch.cat([x, group_act[:, slots, :self.act_dims[k]]], dim=-1)
            tokens[:, slots] = encoders[k](x)
        return tokens

    def _pool_to_value(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        pooled = self.attention(tokens, present)
        count = 2.0 * present.sum(1, keepdim=True).to(pooled.dtype) / present.shape[1] - 1.0
        return self.head(self.body(torch.cat([pooled, count], dim=-1))).squeeze(-1)

    def values_and_baselines(self, group_obs: torch.Tensor, group_act: torch.Tensor,
                             self_idx: torch.Tensor, present: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor]:
        """V(all observations) and b_i(own observation, others' observations and actions)."""
        present = present.bool()
        obs_tokens = self._embed(self.obs_encoders, group_obs, None)
        values = self._pool_to_value(obs_tokens, present)
        oa_tokens = self._embed(self.obs_action_encoders, group_obs, group_act)
        own = nn.functional.one_hot(self_idx.long(), group_obs.shape[1]).bool().unsqueeze(-1)
        baselines = self._pool_to_value(torch.where(own, obs_tokens, oa_tokens), present)
        return values, baselines

    def _forward(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        values, baselines = self.values_and_baselines(
            batch[C.GROUP_OBS], batch[C.GROUP_ACT], batch[C.SELF_IDX], batch[C.GROUP_MASK])
        return {C.VALUES: values, C.BASELINES: baselines}

    def compute_self_supervised_loss(self, *, learner, module_id, config, batch, fwd_out,
                                     **kwargs) -> torch.Tensor:
        eps = float(config.clip_param)
        mask = batch[Columns.LOSS_MASK]
        value_loss = trust_region_value_loss(fwd_out[C.VALUES], batch[C.OLD_VALUES],
                                             batch[C.RETURNS], eps, mask)
        baseline_loss = trust_region_value_loss(fwd_out[C.BASELINES], batch[C.OLD_BASELINES],
                                                batch[C.RETURNS], eps, mask)
        learner.metrics.log_dict({"value_loss": value_loss.detach(),
                                  "baseline_loss": baseline_loss.detach()},
                                 key=module_id, window=1)
        return poca_critic_loss(value_loss, baseline_loss)
