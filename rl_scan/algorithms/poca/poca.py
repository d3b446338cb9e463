"""POCA (MA-POCA) as an RLlib algorithm: ``POCAConfig`` / ``POCA``.

Sampling, the learner update and weight sync are PPO's ``training_step`` (new API stack);
POCA differs in its modules (decentralized Gaussian actors per robot kind plus one
learner-only centralized critic) and its learner (group columns, lambda-returns from V,
counterfactual advantages, per-dimension PPO clipping, critic regression).

    config = poca_config({"scenario": "ablation"}, train_batch_size=4000, minibatch_size=1024)
    algo = config.build_algo(); algo.train(); algo.save_to_path("ckpt")
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from ray.rllib.algorithms.algorithm_config import NotProvided
from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.annotations import override

from rl_scan.algorithms.common import ACTOR_HIDDENS, DECAY_ENDS, configure_scan, linear_decay
from rl_scan.algorithms.overlap import OverlappedSampling, OverlappedSamplingConfig
from rl_scan.algorithms.poca.learner import POCATorchLearner
from rl_scan.algorithms.poca.modules import CRITIC_ID, GaussianActor, POCACritic
from rl_scan.config import check_range, fail
from rl_scan.envs.observations import action_spaces, kind_of, observation_spaces
from rl_scan.envs.sim.env_config import EnvConfig, make_env_config
from rl_scan.envs.sim.robots import KINDS


def layout_from_spaces(agent_ids: list[str], observation_spaces: dict, action_spaces: dict,
                       module_of, module_ids: list[str] | None = None,
                       team_reward: bool = False) -> dict[str, Any]:
    """Critic slots for any multi-agent env whose agents all act every step.

    ``module_of(agent_id)`` gives the policy module (robot kind) of an agent; agents of
    one module must be contiguous in ``agent_ids`` and share observation/action sizes.
    """
    modules = module_ids or sorted({module_of(a) for a in agent_ids})
    dims = {module_of(a): (observation_spaces[a].shape[0], action_spaces[a].shape[0])
            for a in agent_ids}
    return {"slots": list(agent_ids), "kinds": list(modules),
            "slot_kinds": [modules.index(module_of(a)) for a in agent_ids],
            "obs_dims": [dims.get(m, (0, 0))[0] for m in modules],
            "act_dims": [dims.get(m, (0, 0))[1] for m in modules],
            "team_reward": team_reward}


def team_layout(env_config: EnvConfig | dict[str, Any]) -> dict[str, Any]:
    """Critic slots of a scanning env config (team order: wheeled robots, then quads)."""
    cfg = make_env_config(env_config)
    return layout_from_spaces(cfg.team.agent_ids, observation_spaces(cfg), action_spaces(cfg),
                              kind_of, list(KINDS), team_reward=cfg.reward_mode == "team")


class POCAConfig(OverlappedSamplingConfig, PPOConfig):
    """PPOConfig with POCA's defaults (paper: beta 0.005, eps 0.2, lambda 0.95, 3 epochs)."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or POCA)
        self.lr = 3e-4
        self.gamma = 0.99
        self.lambda_ = 0.95
        self.clip_param = 0.2
        self.entropy_coeff = 0.005
        self.num_epochs = 3
        self.use_kl_loss = False
        self.poca_team: dict[str, Any] = {}
        self.actor_hiddens = list(ACTOR_HIDDENS)
        self.critic_hidden = 128
        self.critic_heads = 4
        self.value_clip: float | None = None  # None: clip_param, as ML-Agents does
        self.clip_param_schedule: list | None = None  # [[env steps, clip], ...] or None
        self.normalize_returns = True  # the critic predicts in running return units
        self.advantage_baseline = "counterfactual"  # ablation: "value" (G - V for all)
        self.group_reward = "sum"  # ablation: "mean" (the sum over the robots present)
        self.policy_ratio = "per_dimension"  # ablation: "joint" (RLlib's PPO)

    def poca(self, *, team: dict[str, Any] = NotProvided, actor_hiddens=NotProvided,
             critic_hidden: int = NotProvided, critic_heads: int = NotProvided,
             value_clip: float | None = NotProvided,
             normalize_returns: bool = NotProvided, advantage_baseline: str = NotProvided,
             group_reward: str = NotProvided, policy_ratio: str = NotProvided
             ) -> POCAConfig:
        """POCA-specific settings; ``team`` comes from ``team_layout(env_config)``.

        ``value_clip``: how far V and b_i may move from their collection-time values per
        update in the clipped regression (None: ``clip_param``, as ML-Agents; ``inf``: off),
        in units of the running return statistics when ``normalize_returns`` (default).
        Ablations of the issue-14 review: ``advantage_baseline="value"`` gives every robot
        G - V (no counterfactual baseline), ``group_reward="mean"`` divides the group
        reward by the robots present, ``policy_ratio="joint"`` clips the ratio of the joint
        action density instead of each dimension's.
        """
        if policy_ratio is not NotProvided:
            if policy_ratio not in ("per_dimension", "joint"):
                fail("policy_ratio", policy_ratio, "'per_dimension' or 'joint'")
            self.policy_ratio = policy_ratio
        if advantage_baseline is not NotProvided:
            if advantage_baseline not in ("counterfactual", "value"):
                fail("advantage_baseline", advantage_baseline, "'counterfactual' or 'value'")
            self.advantage_baseline = advantage_baseline
        if group_reward is not NotProvided:
            if group_reward not in ("sum", "mean"):
                fail("group_reward", group_reward, "'sum' or 'mean'")
            self.group_reward = group_reward
        if normalize_returns is not NotProvided:
            self.normalize_returns = bool(normalize_returns)
        if value_clip is not NotProvided:
            self.value_clip = None if value_clip is None else float(value_clip)
        if team is not NotProvided:
            self.poca_team = dict(team)
        if actor_hiddens is not NotProvided:
            self.actor_hiddens = list(actor_hiddens)
        if critic_hidden is not NotProvided:
            self.critic_hidden = int(critic_hidden)
        if critic_heads is not NotProvided:
            self.critic_heads = int(critic_heads)
        return self

    @override(PPOConfig)
    def get_default_learner_class(self):
        return POCATorchLearner

    @override(PPOConfig)
    def get_default_rl_module_spec(self) -> RLModuleSpec:
        return RLModuleSpec(module_class=GaussianActor,
                            model_config={"hiddens": self.actor_hiddens})

    def module_specs(self) -> MultiRLModuleSpec:
        """One actor per robot kind in the team and the learner-only critic."""
        team = self.poca_team
        kinds = sorted({team["kinds"][k] for k in team["slot_kinds"]})
        placeholder = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)  # the critic has no agent
        specs = {kind: RLModuleSpec(module_class=GaussianActor,
                                    model_config={"hiddens": self.actor_hiddens})
                 for kind in kinds}
        specs[CRITIC_ID] = RLModuleSpec(
            module_class=POCACritic, learner_only=True, observation_space=placeholder,
            action_space=placeholder,
            model_config={"slot_kinds": team["slot_kinds"], "obs_dims": team["obs_dims"],
                          "act_dims": team["act_dims"], "hidden": self.critic_hidden,
                          "heads": self.critic_heads,
                          "normalize_returns": self.normalize_returns})
        return MultiRLModuleSpec(rl_module_specs=specs)


class POCA(OverlappedSampling, PPO):
    """MA-POCA on RLlib's new API stack (PPO's sampling loop, POCA's learner and modules)."""

    @classmethod
    @override(PPO)
    def get_default_config(cls) -> POCAConfig:
        return POCAConfig()


def poca_config(env_config: EnvConfig | dict[str, Any], *, train_batch_size: int,
                minibatch_size: int, num_epochs: int = 3, lr: float | list = 3e-4,
                gamma: float = 0.99, lambda_: float = 0.95, clip_param: float = 0.2,
                entropy_coeff: float | list = 0.005, decay_steps: int | None = None,
                base: POCAConfig | None = None, **common: Any) -> POCAConfig:
    """POCAConfig (or ``base``, e.g. a subclass) for the scanning env (``common`` goes to
    ``configure_scan``).

    ``decay_steps``: decay lr, the clip range (policy and critic) and beta linearly from
    their values to ML-Agents' ends (``DECAY_ENDS``) over that many env steps."""
    env = make_env_config(env_config)
    config = configure_scan(base if base is not None else POCAConfig(), env, **common)
    config.poca(team=team_layout(env))
    if decay_steps is not None:
        check_range("decay_steps", decay_steps, 1)
        lr = linear_decay(lr, DECAY_ENDS["lr"], decay_steps)
        entropy_coeff = linear_decay(entropy_coeff, DECAY_ENDS["entropy_coeff"], decay_steps)
        config.clip_param_schedule = linear_decay(clip_param, DECAY_ENDS["clip_param"],
                                                  decay_steps)
    return (config
            .rl_module(rl_module_spec=config.module_specs())
            .training(train_batch_size_per_learner=train_batch_size,
                      minibatch_size=minibatch_size, num_epochs=num_epochs, lr=lr,
                      gamma=gamma, lambda_=lambda_, clip_param=clip_param,
                      entropy_coeff=entropy_coeff))
