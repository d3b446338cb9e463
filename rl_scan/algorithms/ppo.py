"""The PPO baseline: RLlib's own PPO, one module per robot kind, POCA's actor size.

Independent learners with per-agent critics (no centralized critic): what the paper
compares POCA against with "the same hyperparameters".
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

from rl_scan.algorithms.common import ACTOR_HIDDENS, DECAY_ENDS, configure_scan, linear_decay
from rl_scan.algorithms.optim import FusedAdamPPOTorchLearner
from rl_scan.algorithms.overlap import OverlappedSampling, OverlappedSamplingConfig
from rl_scan.config import check_range
from rl_scan.envs.sim.env_config import EnvConfig


class ScanPPOConfig(OverlappedSamplingConfig, PPOConfig):
    """RLlib's PPOConfig that can also overlap sampling with learning."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or ScanPPO)


class ScanPPO(OverlappedSampling, PPO):
    """RLlib's PPO; with ``overlap_sampling`` off its training step is PPO's own."""

    @classmethod
    def get_default_config(cls) -> ScanPPOConfig:
        return ScanPPOConfig()


def ppo_config(env_config: EnvConfig | dict[str, Any], *, train_batch_size: int,
               minibatch_size: int, num_epochs: int = 3, lr: float = 3e-4, gamma: float = 0.99,
               lambda_: float = 0.95, clip_param: float = 0.2, entropy_coeff: float = 0.005,
               decay_steps: int | None = None, **common: Any) -> PPOConfig:
    """PPOConfig for the scanning env (``common`` goes to ``configure_scan``).

    ``decay_steps``: lr and the entropy weight decay linearly to POCA's ends over that
    many env steps (RLlib's PPO has no clip-range schedule: it stays fixed)."""
    config = configure_scan(ScanPPOConfig(), env_config, **common)
    if decay_steps is not None:
        check_range("decay_steps", decay_steps, 1)
        lr = linear_decay(lr, DECAY_ENDS["lr"], decay_steps)
        entropy_coeff = linear_decay(entropy_coeff, DECAY_ENDS["entropy_coeff"], decay_steps)
    return (config
            .rl_module(model_config=DefaultModelConfig(
                fcnet_hiddens=list(ACTOR_HIDDENS), fcnet_activation="relu",
                vf_share_layers=False))
            .training(learner_class=FusedAdamPPOTorchLearner,
                      train_batch_size_per_learner=train_batch_size,
                      minibatch_size=minibatch_size, num_epochs=num_epochs, lr=lr,
                      gamma=gamma, lambda_=lambda_, clip_param=clip_param,
                      entropy_coeff=entropy_coeff))
