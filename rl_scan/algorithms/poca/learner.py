"""POCA's torch Learner: connector pipeline, clipped policy loss, entropy schedule.

Each policy module's loss also carries the critic's regression loss on the same rows.
RLlib minibatches every module separately and runs until the largest batch has done
``num_epochs``; a separate critic batch (all robots' rows) would silently give the
actors extra epochs. RLlib sums the module losses and steps every module's optimizer,
the critic's included.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.connectors.learner import AddOneTsToEpisodesAndTruncate
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.annotations import override
from ray.rllib.utils.lambda_defaultdict import LambdaDefaultDict
from ray.rllib.utils.schedules.scheduler import Scheduler

from rl_scan.algorithms.optim import FusedAdamMixin
from rl_scan.algorithms.poca.connectors import AddGroupColumns, POCATargets
from rl_scan.algorithms.poca.losses import (
    clipped_policy_loss,
    gaussian_entropy,
    gaussian_logp_per_dim,
    importance_weights,
    masked_mean,
)
from rl_scan.algorithms.poca.modules import CRITIC_ID, TRAIN_TABLE


def actor_loss(fwd_out: dict[str, Any], batch: dict[str, Any], clip_param: float,
               beta: float, joint_ratio: bool = False, importance: bool = False
               ) -> tuple[torch.Tensor, dict[str, Any]]:
    """PPO-clipped policy loss minus beta * entropy. The ratio is taken per action dimension
    (ML-Agents), or of the joint density with ``joint_ratio`` (RLlib's PPO; an ablation).
    With ``importance`` each row is weighed by ``importance_weights`` (rows sampled by
    another policy than the one the ratio is clipped around: MetaPOCA's query rows)."""
    mean, log_std = fwd_out[Columns.ACTION_DIST_INPUTS].chunk(2, dim=-1)
    old_mean, old_log_std = batch[Columns.ACTION_DIST_INPUTS].chunk(2, dim=-1)
    actions = batch[Columns.ACTIONS]
    logp = gaussian_logp_per_dim(actions, mean, log_std)
    old_logp = gaussian_logp_per_dim(actions, old_mean, old_log_std).detach()
    mask = batch[Columns.LOSS_MASK]
    weights = (importance_weights(old_logp.sum(-1), batch[Columns.ACTION_LOGP], mask)
               if importance else None)
    if joint_ratio:
        logp, old_logp = logp.sum(-1, keepdim=True), old_logp.sum(-1, keepdim=True)
    policy_loss = clipped_policy_loss(logp, old_logp, batch[Postprocessing.ADVANTAGES],
                                      clip_param, mask, weights)
    entropy = masked_mean(gaussian_entropy(log_std), mask)
    stats = {"policy_loss": policy_loss.detach(), "entropy": entropy.detach(),
             "entropy_coeff": beta}
    if weights is not None:
        stats["importance_weight"] = masked_mean(weights, mask)
    return policy_loss - beta * entropy, stats


def value_clip(config, clip_param: float) -> float:
    """The critic's clipping range: ``value_clip`` if set, else the policy's current one."""
    return float(config.value_clip if config.value_clip is not None else clip_param)


class POCATorchLearner(FusedAdamMixin, TorchLearner):
    """Learner for POCAConfig (see the package doc for the algorithm)."""

    critic_learns = True
    """False: updates leave the critic as it is (no loss, no gradient, no Adam step);
    MetaPOCA's per-task updates at theta + delta."""

    @override(TorchLearner)
    def build(self) -> None:
        super().build()
        cfg = self.config
        self.entropy_coeff_schedulers = LambdaDefaultDict(lambda module_id: Scheduler(
            fixed_value_or_schedule=cfg.get_config_for_module(module_id).entropy_coeff,
            framework=self.framework, device=self._device))
        # One clip range for every module and the critic (ML-Agents' epsilon), decaying
        # with ``clip_param_schedule`` if set.
        self.clip_scheduler = Scheduler(
            fixed_value_or_schedule=getattr(cfg, "clip_param_schedule", None) or cfg.clip_param,
            framework=self.framework, device=self._device)
        if self._learner_connector is not None:
            team = cfg.poca_team
            self._learner_connector.prepend(AddGroupColumns(
                slots=team["slots"], obs_dim=max(team["obs_dims"]),
                act_dim=max(team["act_dims"]), team_reward=team["team_reward"],
                mean_reward=getattr(cfg, "group_reward", "sum") == "mean"))
            self._learner_connector.prepend(AddOneTsToEpisodesAndTruncate())
            self._learner_connector.append(POCATargets(
                gamma=cfg.gamma, lambda_=cfg.lambda_, minibatch_size=cfg.minibatch_size,
                value_baseline=getattr(cfg, "advantage_baseline", "") == "value"))

    @override(TorchLearner)
    def compute_losses(self, *, fwd_out: dict[str, Any], batch: dict[str, Any]
                       ) -> dict[str, Any]:
        losses = super().compute_losses(fwd_out=fwd_out, batch=batch)
        if not self.critic_learns:
            return losses
        critic = self.module[CRITIC_ID]
        out = critic.loss(critic.minibatches[TRAIN_TABLE].next(),
                          value_clip(self.config, self.current_clip()))
        self.metrics.log_dict({k: v.detach() for k, v in out.items()}, key=CRITIC_ID,
                              window=1)
        losses[CRITIC_ID] = out["critic_loss"]
        return losses

    @override(TorchLearner)
    def compute_loss_for_module(self, *, module_id: str, config, batch: dict[str, Any],
                                fwd_out: dict[str, Any]) -> torch.Tensor:
        beta = self.entropy_coeff_schedulers[module_id].get_current_value()
        loss, stats = actor_loss(fwd_out, batch, self.current_clip(), beta,
                                 joint_ratio=getattr(config, "policy_ratio", "") == "joint",
                                 importance=getattr(config, "query_importance", False))
        self.metrics.log_dict(stats, key=module_id, window=1)
        return loss

    @override(TorchLearner)
    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        super().after_gradient_based_update(timesteps=timesteps)
        from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

        step = timesteps.get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0)
        for module_id in set(self.module.keys()) - {CRITIC_ID}:
            self.entropy_coeff_schedulers[module_id].update(timestep=step)
        self.clip_scheduler.update(timestep=step)
        self.metrics.log_value((CRITIC_ID, "clip_param"), self.current_clip(), window=1)

    def current_clip(self) -> float:
        """The clip range now (``clip_param``, or its schedule's value)."""
        return float(self.clip_scheduler.get_current_value())
