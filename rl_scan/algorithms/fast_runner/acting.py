"""Actions for all agents of all acting worlds: one forward pass per module per step.

Does what RLlib's default env-to-module and module-to-env pipelines do for a batch of
Box observations, without per-agent Python: the module's forward_exploration (or
forward_inference when not exploring), sampling from its action distribution (the
deterministic one when not exploring), log-probabilities, and the env actions
unsquashed (``normalize_actions``) or clipped (``clip_actions``) to the action space.

``TorchRLModule.forward_exploration`` puts the module in eval mode and back on every call,
a recursive walk over its layers that cost a third of an 8-row forward pass here; so
``modules_in_eval_mode`` does it once per ``sample()`` and the policy calls the hooks
those methods call (``_forward_exploration`` / ``_forward_inference``).

Exploring with RLlib's diagonal Gaussian (the default for Box actions, POCA's and PPO's),
``gaussian_sample`` draws from the same distribution in numpy: a dozen torch dispatches
on 8-row tensors (from_logits, sample, logp) cost ~120 us per module per step, the numpy
version ~17 us. The noise still comes from torch's generator, so ``torch.manual_seed``
decides the batch; log-probabilities agree with ``TorchDiagGaussian.logp`` to float32
rounding. Any other distribution, and greedy actions, go through the module's own.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.distribution.torch.torch_distribution import TorchDiagGaussian
from ray.rllib.utils.metrics import WEIGHTS_SEQ_NO

from rl_scan.algorithms.fast_runner.team import TeamSlots


@dataclass
class ModuleActions:
    """One module's batch: what the episodes store and what the envs get."""

    actions: np.ndarray
    for_env: np.ndarray
    outputs: dict[str, np.ndarray]
    """Every other model output (e.g. action_dist_inputs, action_logp) and the weights'
    sequence number, as the stock runner stores them in the episodes."""


HALF_LOG_2PI = 0.5 * np.log(2.0 * np.pi)


def gaussian_sample(dist_inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(actions, logp) of ``TorchDiagGaussian.from_logits(dist_inputs)``: mean and log std
    are the two halves of the inputs; standard normal noise from torch's generator."""
    mean, log_std = np.split(dist_inputs, 2, axis=-1)
    noise = torch.randn(mean.shape).numpy()
    actions = mean + np.exp(log_std) * noise
    logp = (-0.5 * noise * noise - log_std - HALF_LOG_2PI).sum(-1)
    return actions.astype(np.float32), logp.astype(np.float32)


@contextmanager
def modules_in_eval_mode(modules):
    """Torch modules in eval mode inside the block, as RLlib samples with them."""
    torch_modules = [m for m in modules if isinstance(m, torch.nn.Module)]
    training = [m.training for m in torch_modules]
    for m in torch_modules:
        m.eval()
    try:
        yield
    finally:
        for m, was_training in zip(torch_modules, training):
            m.train(was_training)


class BatchedPolicy:
    """Acts with a runner's MultiRLModule on batched observations (inside
    ``modules_in_eval_mode`` and ``torch.inference_mode``: outputs only become numpy)."""

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
            fwd = (module._forward_exploration(batch, t=t) if explore
                   else module._forward_inference(batch))
            if Columns.ACTIONS in fwd:
                outputs = {k: v.numpy() for k, v in fwd.items()}
            else:
                outputs = self._sample(module, fwd, explore)
            actions = outputs.pop(Columns.ACTIONS)
            outputs[WEIGHTS_SEQ_NO] = np.full(len(actions), weights_seq_no)
            out[mid] = ModuleActions(actions, self._for_env(mid, actions), outputs)
        return out

    @staticmethod
    def _sample(module, fwd: dict, explore: bool) -> dict[str, np.ndarray]:
        """The model outputs plus actions (and their logp) from the module's distribution,
        as RLlib's GetActions connector makes them, all as numpy."""
        dist_cls = (module.get_exploration_action_dist_cls() if explore
                    else module.get_inference_action_dist_cls())
        if explore and dist_cls is TorchDiagGaussian and Columns.ACTION_LOGP not in fwd:
            outputs = {k: v.numpy() for k, v in fwd.items()}
            outputs[Columns.ACTIONS], outputs[Columns.ACTION_LOGP] = gaussian_sample(
                outputs[Columns.ACTION_DIST_INPUTS])
            return outputs
        dist = dist_cls.from_logits(fwd[Columns.ACTION_DIST_INPUTS])
        if not explore:
            dist = dist.to_deterministic()
        fwd[Columns.ACTIONS] = dist.sample()
        if Columns.ACTION_LOGP not in fwd:
            fwd[Columns.ACTION_LOGP] = dist.logp(fwd[Columns.ACTIONS])
        return {k: v.numpy() for k, v in fwd.items()}

    def _for_env(self, mid: str, actions: np.ndarray) -> np.ndarray:
        """NormalizeAndClipActions on a batch: RLlib's ``unsquash_action`` (or
        ``clip_action``) arithmetic for a bounded float Box, in the same order of
        operations (so the same bits), without its per-call structure walk (~40 us)."""
        space = self.team.modules[mid].action_space
        if self.normalize:
            return np.clip(space.low + (actions + 1.0) * (space.high - space.low) / 2.0,
                           space.low, space.high)
        if self.clip:
            return np.clip(actions, space.low, space.high)
        return actions
