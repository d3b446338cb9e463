"""What the MetaPOCA tests share: a standalone meta-learner and runner (no Ray) on a short
scanning env, its episodes, and the outer update run without building an algorithm."""

from __future__ import annotations

import copy
import random

import numpy as np
import torch
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

from rl_scan.algorithms.maml import meta_poca_config
from rl_scan.algorithms.maml.meta_poca import set_task
from rl_scan.algorithms.poca.modules import CRITIC_ID

ENV = {"max_steps": 12}
TRAINING = dict(num_envs_per_env_runner=2, train_batch_size=64, minibatch_size=16,
                num_epochs=2, lr=1e-3, seed=0)


def meta_setup(**meta):
    config = meta_poca_config(ENV, **{"tasks": 2, "support_steps": 24, "query_steps": 24,
                                      "task_pool": 5, **meta}, **TRAINING)
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    return config, runner, learner


def sample(runner, scenario: str, steps: int = 24) -> list:
    set_task(runner, scenario)
    return runner.sample(num_timesteps=steps, force_reset=True)


def state_copy(learner) -> dict:
    return {k: t.detach().clone() for k, t in learner.float_state().items()}


def seeded(seed: int = 0) -> None:
    """Same minibatch shuffles in two learners' updates."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def outer_update(config, learner, tasks) -> None:
    """MetaPOCA's outer update on ``tasks`` with theta's batch = their support batches (as
    ``sampling='per_task'`` has it; it reads only the algorithm's config and timesteps,
    so no algorithm is built)."""
    from types import SimpleNamespace

    from rl_scan.algorithms.maml.meta_poca import MetaPOCA

    algo = SimpleNamespace(config=config, _timesteps=dict, iteration=0)
    algo._task_streams = lambda *key: MetaPOCA._task_streams(algo, *key)
    MetaPOCA._outer_update(algo, learner, [e for t in tasks for e in t.support], tasks)


def make_tasks(learner, runner, scenarios=("train:0", "train:1"), adapted_query=False) -> list:
    """Tasks with support and query batches and the inner update's delta; the query
    sampled by the adapted actors with ``adapted_query`` (as MetaPOCA samples it), else by
    theta."""
    from rl_scan.algorithms.maml.meta_poca import MetaPOCA, Task

    theta = {mid: copy.deepcopy(runner.module[mid].state_dict())
             for mid in runner.module.keys() if mid != CRITIC_ID}
    tasks = []
    for scenario in scenarios:
        support = sample(runner, scenario)
        delta, adapted, _ = learner.adapt(support, {})
        if adapted_query:
            MetaPOCA._load_actors(runner, adapted)
        tasks.append(Task(scenario, support, sample(runner, scenario), delta))
        MetaPOCA._load_actors(runner, theta)
    return tasks

