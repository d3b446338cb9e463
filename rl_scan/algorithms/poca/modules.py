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
RETURN_STATS_RATE = 0.1  # EMA weight of each update's returns in the normalisation
RETURN_VAR_MIN = 1e-4  # floor of the return variance (std >= 0.01)
TRAIN_TABLE = "train"  # the group table of a plain POCA update


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
    than ``nn.MultiheadAttention`` on CPU. ``project`` and ``attend`` are separate so that
    token sequences assembled from the same tokens (the baselines') share one projection.
    """

    def __init__(self, size: int, heads: int):
        super().__init__()
        if size % heads:
            raise ValueError(f"critic hidden={size} must be divisible by heads={heads}")
        self.heads, self.head_dim = heads, size // heads
        self.norm_in, self.norm_out = nn.LayerNorm(size), nn.LayerNorm(size)
        self.qkv, self.out = nn.Linear(size, 3 * size), nn.Linear(size, size)

    def project(self, tokens: torch.Tensor) -> torch.Tensor:
        """Per-token query, key and value, (..., 3 * size)."""
        return self.qkv(self.norm_in(tokens))

    def attend(self, tokens: torch.Tensor, qkv: torch.Tensor,
               present: torch.Tensor) -> torch.Tensor:
        """Pooled output for token sequences (b, n, size) and their projections."""
        b, n, size = tokens.shape
        q, k, v = qkv.view(b, n, 3, self.heads, self.head_dim).unbind(2)
        logits = torch.einsum("bqhd,bkhd->bhqk", q, k) / self.head_dim ** 0.5
        logits = logits.masked_fill(~present[:, None, None, :], -1e6)  # ML-Agents' mask value
        attended = torch.einsum("bhqk,bkhd->bqhd", logits.softmax(-1), v).reshape(b, n, size)
        x = self.norm_out(tokens + self.out(attended))
        weights = present.unsqueeze(-1).to(x.dtype)
        return (x * weights).sum(1) / weights.sum(1).clamp(min=1.0)

    def forward(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        return self.attend(tokens, self.project(tokens), present)

    def attend_each_own(self, own: torch.Tensor, other: torch.Tensor, own_qkv: torch.Tensor,
                        other_qkv: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """Pooled output of every sequence i = (slot i: ``own``, other slots: ``other``).

        Equal to ``attend`` on each of the n sequences, (b, n, size) -> (b, n, size), but
        never builds the n x n token sequences: the logits are picked from the four
        own/other products and the values split into "other" plus slot i's correction.
        """
        b, n, size = own.shape
        h, d = self.heads, self.head_dim
        qo, ko, vo = own_qkv.view(b, n, 3, h, d).unbind(2)
        qx, kx, vx = other_qkv.view(b, n, 3, h, d).unbind(2)
        eye = torch.eye(n, dtype=torch.bool, device=own.device)

        def products(q, k):  # (b, 1, h, query, key)
            return torch.einsum("bqhd,bkhd->bhqk", q, k).unsqueeze(1)

        query_is_i = eye[None, :, None, :, None]  # (1, i, 1, query, 1)
        key_is_i = eye[None, :, None, None, :]  # (1, i, 1, 1, key)
        logits = torch.where(query_is_i,
                             torch.where(key_is_i, products(qo, ko), products(qo, kx)),
                             torch.where(key_is_i, products(qx, ko), products(qx, kx)))
        logits = logits / d ** 0.5
        logits = logits.masked_fill(~present[:, None, None, None, :], -1e6)
        weights = logits.softmax(-1)  # (b, i, h, query, key)
        attended = (torch.einsum("bihqk,bkhd->biqhd", weights, vx)
                    + torch.einsum("bihq,bihd->biqhd", torch.diagonal(weights, dim1=1, dim2=4)
                                   .permute(0, 3, 1, 2), vo - vx))
        tokens = other.unsqueeze(1) + eye[None, :, :, None] * (own - other).unsqueeze(1)
        x = self.norm_out(tokens + self.out(attended.reshape(b, n, n, size)))
        mask = present[:, None, :, None].to(x.dtype)
        return (x * mask).sum(2) / mask.sum(2).clamp(min=1.0)


class POCACritic(TorchRLModule):
    """Centralized value V and counterfactual baselines b_i, and their regression loss.

    It works on the update's group table (one row per env step, every robot's observation
    and action): one pass gives V and every robot's baseline for a step, sharing the
    observation encodings and attention projections among them. Its loss runs on group
    minibatches sized so that it sees every step ``num_epochs`` times per update, like the
    actors see their rows (see ``learner.py``).

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
        # Return normalisation (PopArt): V and b_i are predicted in units of running
        # return statistics, EMA of the first and second moment; a checkpoint without
        # them loads as mean 0, second moment 1 (no normalisation).
        self.normalize_returns = bool(cfg.get("normalize_returns", True))
        self.return_stats_frozen = False  # MetaPOCA: at theta + delta, theta's statistics
        self.register_buffer("return_moments", torch.tensor([0.0, 1.0]))
        self.register_buffer("return_stats_set", torch.tensor(False))
        self._tables: dict[str, dict[str, torch.Tensor]] = {}
        self.minibatches: dict[str, Any] = {}  # per table: its GroupMinibatches
        # Slots of one kind are contiguous (team order): each kind's slots are one slice,
        # and the kinds' outputs concatenate in slot order (no scatter into a zero tensor).
        self._slots_of = {}
        for k in kinds:
            idx = [s for s, sk in enumerate(self.slot_kinds) if sk == k]
            if idx and idx != list(range(idx[0], idx[-1] + 1)):
                raise ValueError(f"slots of kind {k} must be contiguous: {self.slot_kinds}")
            self._slots_of[k] = slice(idx[0], idx[-1] + 1) if idx else None
        self._kind_blocks = sorted(((sl, k) for k, sl in self._slots_of.items() if sl),
                                   key=lambda block: block[0].start)

    def return_scale(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) of the returns the outputs are normalised by."""
        m1, m2 = self.return_moments
        return m1, torch.sqrt(torch.clamp(m2 - m1 * m1, min=RETURN_VAR_MIN))

    def normalize(self, returns: torch.Tensor) -> torch.Tensor:
        mean, std = self.return_scale()
        return (returns - mean) / std

    def denormalize(self, outputs: torch.Tensor) -> torch.Tensor:
        mean, std = self.return_scale()
        return outputs * std + mean

    @torch.no_grad()
    def update_return_stats(self, returns: torch.Tensor, rate: float = RETURN_STATS_RATE
                            ) -> None:
        """Move the statistics towards ``returns`` (the first batch sets them) and rescale
        the output layer so that every de-normalised output stays what it was (PopArt,
        van Hasselt et al. 2016): the trust region around the old predictions holds."""
        if not self.normalize_returns or self.return_stats_frozen or returns.numel() == 0:
            return
        returns = returns.double()
        batch = torch.stack([returns.mean(), (returns * returns).mean()]).float()
        first = not bool(self.return_stats_set)
        old_mean, old_std = (t.clone() for t in self.return_scale())  # not views
        self.return_moments.copy_(batch if first else
                                  (1 - rate) * self.return_moments + rate * batch)
        self.return_stats_set.fill_(True)
        new_mean, new_std = self.return_scale()
        self.head.weight.mul_(old_std / new_std)
        self.head.bias.copy_((old_std * self.head.bias + old_mean - new_mean) / new_std)

    def encode(self, group_obs: torch.Tensor) -> torch.Tensor:
        """Each slot's observation encoding (the big matmul), (steps, slots, hidden)."""
        return torch.cat([self.obs_encoders[str(k)](group_obs[:, sl, :self.obs_dims[k]].float())
                          for sl, k in self._kind_blocks], dim=1)

    def group_heads(self, enc: torch.Tensor, group_act: torch.Tensor, present: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """V per step (steps,) and every slot's baseline b_i (steps, slots).

        V attends over all observation entities; b_i over robot i's observation entity and
        the others' observation+action entities, so b_i never sees robot i's own action.
        """
        present = present.bool()
        obs_tokens = torch.cat([self.obs_embeddings[str(k)](enc[:, sl])
                                for sl, k in self._kind_blocks], dim=1)
        oa_tokens = torch.cat([self.obs_action_embeddings[str(k)](torch.cat(
            [enc[:, sl], group_act[:, sl, :self.act_dims[k]].float()], -1))
            for sl, k in self._kind_blocks], dim=1)
        obs_qkv = self.attention.project(obs_tokens)
        pooled_v = self.attention.attend(obs_tokens, obs_qkv, present)
        # One sequence per robot i: i's observation entity, the others' obs+action ones.
        pooled_b = self.attention.attend_each_own(obs_tokens, oa_tokens, obs_qkv,
                                                  self.attention.project(oa_tokens), present)
        count = 2.0 * present.sum(1, keepdim=True).to(enc.dtype) / present.shape[1] - 1.0
        pooled = torch.cat([pooled_v.unsqueeze(1), pooled_b], dim=1)  # (steps, 1 + slots, h)
        out = self.head(self.body(torch.cat(
            [pooled, count.unsqueeze(1).expand(-1, pooled.shape[1], -1)], dim=-1))).squeeze(-1)
        return out[:, 0], out[:, 1:]

    def values_and_baselines(self, group_obs: torch.Tensor, group_act: torch.Tensor,
                             self_idx: torch.Tensor, present: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per row: V(all observations) and b_i(own observation, others' obs and actions)."""
        values, baselines = self.group_heads(self.encode(group_obs), group_act, present)
        return values, baselines.gather(1, self_idx.long().unsqueeze(1)).squeeze(1)

    def set_group_table(self, key: str = TRAIN_TABLE, **table: torch.Tensor) -> None:
        """One update's per-step team data and targets, under ``key``.

        Keys of ``table``: ``obs``, ``act``, ``present`` and, once targets exist,
        ``returns``, ``old_values``, ``old_baselines``. Several tables live side by side
        (meta-learning keeps a task's support and query data). Transient: not a parameter,
        not checkpointed.
        """
        self._tables[key] = table

    def table(self, key: str = TRAIN_TABLE) -> dict[str, torch.Tensor]:
        return self._tables[key]

    def _forward(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """V and b_i for steps ``batch[GROUP_ROW]`` of table ``batch[TABLE_KEY]``.

        Reads only its batch and parameters, so ``torch.func.functional_call`` with other
        (e.g. meta-adapted) parameters works.
        """
        t, steps = self._tables[batch.get(C.TABLE_KEY, TRAIN_TABLE)], batch[C.GROUP_ROW]
        values, baselines = self.group_heads(self.encode(t["obs"][steps]), t["act"][steps],
                                             t["present"][steps])
        return {C.VALUES: values, C.BASELINES: baselines}

    def loss(self, steps: torch.Tensor, epsilon: float,
             key: str = TRAIN_TABLE) -> dict[str, torch.Tensor]:
        """Value and baseline regression on table steps, with this module's parameters."""
        out = self._forward({C.GROUP_ROW: steps, C.TABLE_KEY: key})
        return self.loss_from_outputs(out, steps, epsilon, key)

    def loss_from_outputs(self, out: dict[str, torch.Tensor], steps: torch.Tensor,
                          epsilon: float, key: str = TRAIN_TABLE) -> dict[str, torch.Tensor]:
        """ML-Agents' clipped value and baseline regression of ``_forward`` outputs.

        The value loss averages over steps, the baseline loss over (step, present robot):
        the same weights as averaging both over every robot's row, as ML-Agents does.
        """
        t = self._tables[key]
        present = t["present"][steps].bool()
        returns = t["returns"][steps]
        value_loss = trust_region_value_loss(out[C.VALUES], t["old_values"][steps], returns,
                                             epsilon, torch.ones_like(returns))
        baseline_loss = trust_region_value_loss(
            out[C.BASELINES], t["old_baselines"][steps], returns.unsqueeze(1).expand_as(present),
            epsilon, present)
        return {"value_loss": value_loss, "baseline_loss": baseline_loss,
                "critic_loss": poca_critic_loss(value_loss, baseline_loss)}
