"""``rl-scan bench mpe``: POCA against RLlib's PPO on PettingZoo MPE ``simple_spread_v3``.

An external check that POCA is POCA and not only tuned to the scanning env: the same
actor size, budget, batch sizes and seeds for both, 3 cooperative agents with continuous
actions (``mpe2``), one policy module shared by the agents. Reports the final mean
episode return (summed over agents, mean of the last 3 iterations) per seed.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from rl_scan import results as R
from rl_scan.reports.stats import sample_std

ENV_NAME = "rl_scan_mpe_simple_spread"
MODULE = "agent"
ALGOS = {  # name -> (algorithm, POCA settings): the ablations of issue 14's review
    "ppo": ("ppo", {}),
    "poca": ("poca", {}),
    "poca-value-baseline": ("poca", {"advantage_baseline": "value"}),
    "poca-mean-reward": ("poca", {"group_reward": "mean"}),
    "poca-joint-ratio": ("poca", {"policy_ratio": "joint"}),
}


def make_mpe_env(config: dict[str, Any] | None = None):
    """simple_spread_v3 (N=3, continuous actions, 25 cycles) wrapped for RLlib."""
    from mpe2 import simple_spread_v3
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    return ParallelPettingZooEnv(simple_spread_v3.parallel_env(
        N=3, continuous_actions=True, max_cycles=25))


def _module(agent_id: str, *args, **kwargs) -> str:
    return MODULE


def mpe_config(algo: str, seed: int, *, train_batch_size: int, minibatch_size: int,
               num_epochs: int, hiddens: list[int], value_clip: float | None = None):
    """The AlgorithmConfig for ``algo`` (a key of ``ALGOS``) on simple_spread."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.tune.registry import register_env

    from rl_scan.algorithms.poca import POCAConfig, layout_from_spaces

    register_env(ENV_NAME, make_mpe_env)
    algo, settings = ALGOS[algo]
    if algo == "poca":
        probe = make_mpe_env().par_env
        ids = sorted(probe.possible_agents)
        config = POCAConfig().poca(
            team=layout_from_spaces(ids, {a: probe.observation_space(a) for a in ids},
                                    {a: probe.action_space(a) for a in ids}, _module),
            actor_hiddens=hiddens, critic_hidden=hiddens[-1], value_clip=value_clip,
            **settings)
        config = config.rl_module(rl_module_spec=config.module_specs())
    else:
        config = PPOConfig().rl_module(model_config=DefaultModelConfig(
            fcnet_hiddens=list(hiddens), fcnet_activation="relu", vf_share_layers=False))
    return (config.environment(ENV_NAME)
            .env_runners(num_env_runners=0, num_envs_per_env_runner=4)
            .learners(num_learners=0)
            .multi_agent(policies={MODULE}, policy_mapping_fn=_module)
            .training(train_batch_size_per_learner=train_batch_size,
                      minibatch_size=minibatch_size, num_epochs=num_epochs, lr=3e-4,
                      gamma=0.99, lambda_=0.95, clip_param=0.2, entropy_coeff=0.005)
            .debugging(seed=seed))


def train_mpe(algo: str, seed: int, env_steps: int, **kwargs) -> list[tuple[int, float]]:
    """(env steps, mean episode return) after each iteration."""
    algorithm = mpe_config(algo, seed, **kwargs).build_algo()
    curve: list[tuple[int, float]] = []
    try:
        while not curve or curve[-1][0] < env_steps:
            result = algorithm.train()
            curve.append((int(result[R.ENV_STEPS]),
                          float(result["env_runners"].get("episode_return_mean", np.nan))))
    finally:
        algorithm.stop()
    return curve


def run_bench_mpe(algos: list[str], seeds: int, env_steps: int, *, train_batch_size=2000,
                  minibatch_size=512, num_epochs=3, hiddens=(64, 64), console=None) -> dict:
    """Train every algorithm on every seed and print final returns side by side."""
    import ray
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    console.print(f"[bold]rl-scan bench mpe[/] simple_spread_v3 (3 agents, continuous): "
                  f"{env_steps:,} env steps per run, seeds 0..{seeds - 1}, load avg "
                  f"{os.getloadavg()[0]:.2f}")
    curves: dict[str, dict[int, list]] = {a: {} for a in algos}
    for algo in algos:
        for seed in range(seeds):
            console.print(f"training {algo} seed {seed} ...")
            curves[algo][seed] = train_mpe(algo, seed, env_steps,
                                           train_batch_size=train_batch_size,
                                           minibatch_size=minibatch_size,
                                           num_epochs=num_epochs, hiddens=list(hiddens))
    final = {a: [float(np.mean([r for _, r in c[-3:]])) for c in curves[a].values()]
             for a in algos}
    first = {a: [c[0][1] for c in curves[a].values()] for a in algos}
    table = Table(title="simple_spread_v3: mean episode return (sum over agents)")
    for col in ("algorithm", "first iteration", "final (last 3 iterations; mean ± sample "
                "std over seeds)", "per seed"):
        table.add_column(col, justify="left" if col == "algorithm" else "right")
    for a in algos:
        table.add_row(a, f"{np.mean(first[a]):.1f}",
                      f"{np.mean(final[a]):.1f} ± {sample_std(final[a]):.1f}",
                      ", ".join(f"{v:.1f}" for v in final[a]))
    console.print(table)
    return {"env_steps": env_steps, "final": final, "first": first,
            "curves": {a: {str(s): c for s, c in cs.items()} for a, cs in curves.items()}}
