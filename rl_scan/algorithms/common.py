"""Settings every rl-scan algorithm shares: env, policy mapping, runners, eval, metrics.

Both POCA and the PPO baseline train one policy module per robot kind present in the
team ("wheeled", "quad") with the same actor size, on ``ScanMultiAgentEnv``.
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.algorithm_config import AlgorithmConfig

from rl_scan.algorithms.callbacks import ScanMetricsCallback
from rl_scan.algorithms.overlap import OverlappedSamplingConfig
from rl_scan.algorithms.registry import DEFAULT_SAMPLER, check_sampler
from rl_scan.config import check_range, fail, to_dict
from rl_scan.envs.observations import kind_of
from rl_scan.envs.rllib_env import ScanMultiAgentEnv
from rl_scan.envs.sim.env_config import EnvConfig, make_env_config

ACTOR_HIDDENS = (256, 256, 128)  # the paper's 3-layer MLP encoder (sizes assumed)

# ML-Agents' linear decays over a run (``learning_rate_schedule``, ``epsilon_schedule``,
# ``beta_schedule``: linear): where each setting ends at 100 % of the budget.
DECAY_ENDS = {"lr": 1e-10, "clip_param": 0.1, "entropy_coeff": 1e-5}


def linear_decay(start: float, end: float, steps: int) -> list[list[float]]:
    """RLlib's schedule format ([[timestep, value], ...], linear in between) from ``start``
    at 0 env steps to ``end`` at ``steps``."""
    return [[0, float(start)], [int(steps), float(end)]]


def policy_mapping(agent_id: str, episode: Any = None, **kwargs: Any) -> str:
    """'quad_1' -> 'quad': one policy module per robot kind."""
    return kind_of(agent_id)


def team_kinds(env_config: EnvConfig | dict[str, Any]) -> list[str]:
    """The robot kinds present in the env's team."""
    team = make_env_config(env_config).team
    return [k for k, n in (("wheeled", team.wheeled), ("quad", team.quad)) if n > 0]


def configure_scan(config: AlgorithmConfig, env_config: EnvConfig | dict[str, Any], *,
                   num_env_runners: int = 0, num_envs_per_env_runner: int = 1,
                   evaluation_interval: int = 0, evaluation_episodes: int = 1,
                   seed: int = 0, sampler: str = DEFAULT_SAMPLER,
                   overlap_sampling: bool = False) -> AlgorithmConfig:
    """Apply the shared settings to an algorithm config (returns the same object).

    A mapping is validated here; the typed config becomes a dict only for RLlib, which
    hands it to every env it creates. ``sampler`` picks the env runner (``SAMPLERS`` in
    the registry): ``fast`` (rl_scan.algorithms.fast_runner) or ``rllib``.
    ``overlap_sampling``: remote runners sample the next batch while this one is learned
    (rl_scan.algorithms.overlap)."""
    env = make_env_config(env_config)
    check_range("num_envs_per_env_runner", num_envs_per_env_runner, 1)
    check_range("num_env_runners", num_env_runners, 0)
    if overlap_sampling:
        if not isinstance(config, OverlappedSamplingConfig):
            fail("overlap_sampling", True, f"False for {type(config).__name__} (it does not "
                                           "use PPO's sampling loop)")
        if num_env_runners < 1:
            fail("overlap_sampling", True, "only with num_env_runners >= 1 (remote runners "
                                           "sample while the training process learns)")
        config.overlap_sampling = True
    runner_cls = None
    if check_sampler(sampler) == "fast":
        from rl_scan.algorithms.fast_runner import FastEnvRunner

        runner_cls = FastEnvRunner
    config = (config
              .environment(ScanMultiAgentEnv, env_config=to_dict(env))
              .env_runners(num_env_runners=num_env_runners,
                           num_envs_per_env_runner=num_envs_per_env_runner,
                           env_runner_cls=runner_cls)
              .learners(num_learners=0)
              # A list, not a set: RLlib builds the modules (and so draws their initial
              # weights) in this order, and a set's order changes with PYTHONHASHSEED.
              .multi_agent(policies=team_kinds(env), policy_mapping_fn=policy_mapping)
              .callbacks(ScanMetricsCallback)
              .debugging(seed=seed))
    if evaluation_interval > 0:
        config = config.evaluation(
            evaluation_interval=evaluation_interval, evaluation_duration=evaluation_episodes,
            evaluation_duration_unit="episodes", evaluation_num_env_runners=0,
            # Sampled actions, as ML-Agents (and so the paper's curves) evaluate: the env
            # clips a Gaussian's samples, so a mean beyond +-1 gets no gradient and
            # mean actions are not the policy that was trained.
            evaluation_config=type(config).overrides(explore=True))
    if runner_cls is not None:
        from rl_scan.algorithms.fast_runner import check_fast_sampler

        check_fast_sampler(config)
    return config
