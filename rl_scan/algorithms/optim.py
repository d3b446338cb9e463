"""The optimizer step of every rl-scan learner (POCA and the PPO baseline).

RLlib's default ``torch.optim.Adam(params)`` runs the per-tensor for-loop implementation
on CPU; the fused kernel is numerically the same algorithm and about 7x faster per step
on our actors' 1.3 M parameters (4.3 ms -> 0.6 ms, measured on this machine). RLlib's
``apply_gradients`` also checks every gradient for NaN/inf twice (once per parameter, once
per optimizer), each check a kernel and a sync; one fused norm over all gradients answers
the same question. Both algorithms use this, so comparisons between them stay like for like.
"""

from __future__ import annotations

import torch
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner


class FusedAdamMixin:
    """Fused Adam per module (same lr handling as RLlib) and one finite check per update."""

    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        params = self.get_parameters(self._module[module_id])
        self.register_optimizer(module_id=module_id,
                                optimizer=torch.optim.Adam(params, fused=True),
                                params=params, lr_or_lr_schedule=config.lr)

    def apply_gradients(self, gradients_dict) -> None:
        """RLlib's ``apply_gradients`` when all gradients are finite, with one check.

        Anything unusual (a non-finite gradient, grad scalers, torch lr schedulers) takes
        RLlib's own path, which zeroes or skips as configured and warns.
        """
        grads = [g for g in gradients_dict.values() if g is not None]
        unusual = self._grad_scalers is not None or self._lr_scheduler_classes is not None
        if unusual or not grads or not torch.isfinite(
                torch.stack(torch._foreach_norm(grads))).all():
            return super().apply_gradients(gradients_dict)
        for pid, grad in gradients_dict.items():
            self._params[pid].grad = grad
        for module_id, optimizer_names in self._module_optimizers.items():
            for optimizer_name in optimizer_names:
                self.get_optimizer(module_id, optimizer_name).step()
        return None


class FusedAdamPPOTorchLearner(FusedAdamMixin, PPOTorchLearner):
    """RLlib's PPO learner, unchanged but for the optimizer kernel."""
