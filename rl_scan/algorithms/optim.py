"""Adam on torch's fused CPU kernel for every rl-scan learner (POCA and the PPO baseline).

RLlib's default ``torch.optim.Adam(params)`` runs the per-tensor for-loop implementation
on CPU; the fused kernel is numerically the same algorithm and about 7x faster per step
on our actors' 1.3 M parameters (4.3 ms -> 0.6 ms, measured on this machine). Both
algorithms use it, so throughput comparisons between them stay like for like.
"""

from __future__ import annotations

import torch
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner


class FusedAdamMixin:
    """Replaces ``TorchLearner.configure_optimizers_for_module`` (same lr handling)."""

    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        params = self.get_parameters(self._module[module_id])
        self.register_optimizer(module_id=module_id,
                                optimizer=torch.optim.Adam(params, fused=True),
                                params=params, lr_or_lr_schedule=config.lr)


class FusedAdamPPOTorchLearner(FusedAdamMixin, PPOTorchLearner):
    """RLlib's PPO learner, unchanged but for the optimizer kernel."""
