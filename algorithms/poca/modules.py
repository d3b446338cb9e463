"""POCA's RLModules: one Gaussian actor per robot kind and one centralized critic.

The critic is learner-only (never shipped to env runners) and shared by both kinds. Per
kind it encodes each robot's observation once; an observation entity embedding and an
observation+action entity embedding are taken from that encoding (as ML-Agents'
``MultiAgentNetworkBody`` does); a residual self-attention block with key masks for
absent robots and a masked mean pool turn the team's entities into one vector:
  V(s)        from every robot's observation entity;
  b_i(s, a_-i) from robot i's observation entity and the others' observation+action ones.
Slots are fixed per env config (team order: wheeled robots, then quads), so any team mix
works; observation and action vectors are zero-padded to the largest kind.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.columns import Columns
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
    """LayerNorm -> multi-head self-attention (masked keys) -> residual -> LayerNorm -> pool.

    Written out with einsum: with a handful of entities per row it is several times faster
    than ``nn.MultiheadAttention`` on CPU.
    """

    def __init__(self, size: int, heads: int):
        super().__init__()
        if size % heads:
            raise ValueError(f"critic hidden={size} must be divisible by heads={heads}")
        self.heads, self.head_dim = heads, size // heads
        self.norm_in, self.norm_out = nn.LayerNorm(size), nn.LayerNorm(size)
        self.qkv, self.out = nn.Linear(size, 3 * size), nn.Linear(size, size)

    def forward(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        b, n, size = tokens.shape
        q, k, v = self.qkv(self.norm_in(tokens)).view(b, n, 3, self.heads,
                                                       self.head_dim).unbind(2)
        logits = torch.einsum("bqhd,bkhd->bhqk", q, k) / self.head_dim ** 0.5
        logits = logits.masked_fill(~present[:, None, None, :], -1e6)  # ML-Agents' mask value
        attended = torch.einsum("bhqk,bkhd->bqhd", logits.softmax(-1), v).reshape(b, n, size)
        x = self.norm_out(tokens + self.out(attended))
        weights = present.unsqueeze(-1).to(x.dtype)
        return (x * weights).sum(1) / weights.sum(1).clamp(min=1.0)


class POCACritic(TorchRLModule):
    """Centralized value V and counterfactual baselines b_i, and their regression loss.

    Its loss is computed on each policy minibatch's rows (by the learner), so the critic
    and the actors see the same rows and the same number of epochs.

    ``model_config``: ``slot_kinds`` (kind index per slot), ``obs_dims`` and ``act_dims``
    (per kind), ``hidden`` (entity size), ``heads`` (attention heads).
    """

    def setup(self) -> None:
        cfg = self.model_config
        self.slot_kinds = list(cfg["slot_kinds"])
        self.obs_dims, self.act_dims = list(cfg["obs_dims"]), list(cfg["act_dims"])
        h = int(cfg.get("hidden", 128))
        kinds = range(len(self.obs_dims))
        present = [k for k in kinds if self.obs_dims[k]]
        self.obs_encoders = nn.ModuleDict(
            {str(k): mlp([self.obs_dims[k], h, h]) for k in present})
        self.obs_embeddings = nn.ModuleDict({str(k): nn.Linear(h, h) for k in present})
        self.obs_action_embeddings = nn.ModuleDict(
            {str(k): nn.Linear(h + self.act_dims[k], h) for k in present})
        self.attention = ResidualSelfAttention(h, int(cfg.get("heads", 4)))
        self.body = mlp([h + 1, h, h])
        self.head = nn.Linear(h, 1)
        self.hidden = h
        # Slots of one kind are contiguous (team order): slicing them makes views, not copies.
        self._slots_of = {}
        for k in kinds:
            idx = [s for s, sk in enumerate(self.slot_kinds) if sk == k]
            if idx and idx != list(range(idx[0], idx[-1] + 1)):
                raise ValueError(f"slots of kind {k} must be contiguous: {self.slot_kinds}")
            self._slots_of[k] = slice(idx[0], idx[-1] + 1) if idx else None

    def encode(self, group_obs: torch.Tensor) -> torch.Tensor:
        """Each slot's observation encoding (the big matmul), (rows, slots, hidden)."""
        group_obs = group_obs.float()
        enc = group_obs.new_zeros(*group_obs.shape[:2], self.hidden)
        for k, slots in self._slots_of.items():
            if slots is not None:
                enc[:, slots] = self.obs_encoders[str(k)](group_obs[:, slots, :self.obs_dims[k]])
        return enc

    def heads(self, enc: torch.Tensor, group_act: torch.Tensor, self_idx: torch.Tensor,
              present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """V from observation entities; b_i with robot i's entity action-free."""
        present = present.bool()
        obs_tokens, oa_tokens = torch.zeros_like(enc), torch.zeros_like(enc)
        for k, slots in self._slots_of.items():
            if slots is None:
                continue
            key = str(k)
            obs_tokens[:, slots] = self.obs_embeddings[key](enc[:, slots])
            oa_tokens[:, slots] = self.obs_action_embeddings[key](
                torch.cat([enc[:, slots], group_act[:, slots, :self.act_dims[k]].float()], -1))
        values = self._pool_to_value(obs_tokens, present)
        own = nn.functional.one_hot(self_idx.long(), enc.shape[1]).bool().unsqueeze(-1)
        baselines = self._pool_to_value(torch.where(own, obs_tokens, oa_tokens), present)
        return values, baselines

    def _pool_to_value(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        pooled = self.attention(tokens, present)
        count = 2.0 * present.sum(1, keepdim=True).to(pooled.dtype) / present.shape[1] - 1.0
        return self.head(self.body(torch.cat([pooled, count], dim=-1))).squeeze(-1)

    def values_and_baselines(self, group_obs: torch.Tensor, group_act: torch.Tensor,
                             self_idx: torch.Tensor, present: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor]:
        """V(all observations) and b_i(own observation, others' observations and actions)."""
        return self.heads(self.encode(group_obs), group_act, self_idx, present)

    def set_group_table(self, obs: torch.Tensor, act: torch.Tensor,
                        present: torch.Tensor) -> None:
        """This update's per-step team data; rows refer to it by ``GROUP_ROW``.

        One row per env step (not per agent row): the team's observations are stored once
        instead of once per robot. Transient (not a parameter, not checkpointed).
        """
        self._table = (obs, act, present)

    def _forward(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        obs, act, present = self._table
        row = batch[C.GROUP_ROW]
        values, baselines = self.values_and_baselines(obs[row], act[row], batch[C.SELF_IDX],
                                                      present[row])
        return {C.VALUES: values, C.BASELINES: baselines}

    def loss(self, rows: dict[str, Any], epsilon: float) -> dict[str, torch.Tensor]:
        """Value and baseline regression on policy rows (ML-Agents' clipped form)."""
        out = self._forward(rows)
        mask = rows[Columns.LOSS_MASK]
        value_loss = trust_region_value_loss(out[C.VALUES], rows[C.OLD_VALUES],
                                             rows[C.RETURNS], epsilon, mask)
        baseline_loss = trust_region_value_loss(out[C.BASELINES], rows[C.OLD_BASELINES],
                                                rows[C.RETURNS], epsilon, mask)
        return {"value_loss": value_loss, "baseline_loss": baseline_loss,
                "critic_loss": poca_critic_loss(value_loss, baseline_loss)}
