"""MetaPOCA's ``sampling='shared'`` layout: theta samples DR's batch (episodes continued),
the tasks are whole episodes of it, each query runs on a one-env side runner with the
task's scene, and every charged env step is learned from.

Real Ray, the real env runners and learner (local mode).
"""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch
from meta_learners import TRAINING

from rl_scan.algorithms.callbacks import episode_scenario
from rl_scan.algorithms.maml import meta_poca_config
from rl_scan.algorithms.poca import poca_config

ENV = {"max_steps": 12, "scenario": "train:*"}


@pytest.mark.parametrize("outer, at_theta", [("maml", 60), ("maml_dr", 60 + 2 * 12)])
def test_shared_layout_learns_theta_on_the_whole_batch_and_queries_the_tasks_scenes(
        ray_session, outer, at_theta):
    config = meta_poca_config(ENV, tasks=2, support_steps=60, query_steps=12,
                              sampling="shared", outer=outer, **TRAINING)
    algo = config.build_algo()
    main, side = algo.env_runner, algo._query_runner()
    batches: dict[str, list] = {"main": [], "side": []}

    def recording(runner, name):
        real = runner.sample

        def sample(**kwargs):
            episodes = real(**kwargs)
            batches[name].append(episodes)
            return episodes
        return sample

    main.sample, side.sample = recording(main, "main"), recording(side, "side")
    learner = algo.learner_group._learner
    updates: list[int] = []  # env steps of every learner update, in order
    real_update = learner.update

    def recording_update(**kwargs):
        updates.append(sum(e.env_steps() for e in kwargs["episodes"]))
        return real_update(**kwargs)

    learner.update = recording_update
    result = algo.train()
    algo.stop()

    assert [sum(e.env_steps() for e in b) for b in batches["main"]] == [60]
    assert [sum(e.env_steps() for e in b) for b in batches["side"]] == [12, 12]
    assert result["env_runners"]["num_env_steps_sampled_lifetime"] == 60 + 2 * 12
    # 2 inner updates on one whole episode each, theta's on the whole batch (with
    # maml_dr the queries too: every charged step), the MAML term's 2 query updates at
    # theta + delta_i
    assert updates == [12, 12, at_theta, 12, 12]
    batch = batches["main"][0]
    whole = {episode_scenario(e) for e in batch if e.is_done and e.env_t_started == 0}
    queried = [episode_scenario(q) for b in batches["side"] for q in b]
    assert all(s is not None and s.startswith("train:") and s != "train:*" for s in queried)
    assert set(queried) <= whole  # each query ran on its task's scene
    # 30 steps per env: two whole episodes and a chunk that the next batch continues
    assert any(not e.is_done for e in batch)
    assert main.env.unwrapped.envs[0].unwrapped.core.scenario_name == "train:*"


def test_building_the_side_runner_leaves_the_process_random_streams_as_they_were(
        ray_session):
    config = meta_poca_config(ENV, tasks=2, support_steps=60, query_steps=12,
                              sampling="shared", **TRAINING)
    algo = config.build_algo()
    random.seed(11)
    np.random.seed(11)
    torch.manual_seed(11)
    expected = random.random(), np.random.random(), torch.rand(1).item()
    random.seed(11)
    np.random.seed(11)
    torch.manual_seed(11)
    algo._query_runner()  # RLlib's EnvRunner reseeds all three when built
    drawn = random.random(), np.random.random(), torch.rand(1).item()
    algo.stop()
    assert drawn == expected


def test_without_the_maml_term_theta_is_drs_tensor_for_tensor(ray_session):
    """The task work (inner updates, queries, the MAML term) draws from its own random
    streams, so with no MAML term theta samples and learns exactly what POCA on the same
    batches (DR) does; with the term it moves elsewhere."""
    meta = dict(tasks=2, support_steps=60, query_steps=12, sampling="shared", outer="maml")
    configs = {"dr": poca_config(ENV, **{**TRAINING, "train_batch_size": 60}),
               "no_term": meta_poca_config(ENV, maml_weight=0.0, **meta, **TRAINING),
               "term": meta_poca_config(ENV, maml_weight=1.0, **meta, **TRAINING)}
    theta = {}
    for name, config in configs.items():
        algo = config.build_algo()
        for _ in range(2):
            algo.train()
        module = algo.learner_group._learner.module
        theta[name] = {(mid, key): t.clone() for mid in module.keys()
                       for key, t in module[mid].state_dict().items()}
        algo.stop()
    assert theta["no_term"].keys() == theta["dr"].keys()
    assert all(torch.equal(t, theta["dr"][k]) for k, t in theta["no_term"].items())
    assert not all(torch.equal(t, theta["dr"][k]) for k, t in theta["term"].items())
