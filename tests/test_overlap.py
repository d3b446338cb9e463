"""Sampling overlapped with learning: exactly one update of policy lag, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns

from rl_scan.algorithms.poca import poca_config
from rl_scan.algorithms.ppo import ppo_config
from rl_scan.cli import main
from rl_scan.config import ConfigError
from rl_scan.tuning.driver import make_run_spec

ENV = {"scenario": "test:2", "max_steps": 50}


def test_overlap_needs_remote_runners_and_ppo_s_loop():
    with pytest.raises(ConfigError, match=r"preset\.overlap_sampling=True is invalid: allowed "
                                          r"only with num_env_runners >= 1"):
        make_run_spec("poca", {}, "smoke", preset_overrides={"overlap_sampling": True})
    with pytest.raises(ConfigError, match="overlap_sampling=True is invalid: allowed only with "
                                          "num_env_runners >= 1"):
        poca_config(ENV, train_batch_size=200, minibatch_size=64, overlap_sampling=True)
    with pytest.raises(ConfigError, match="overlap_sampling=True is invalid: allowed False for "
                                          "meta-poca"):
        make_run_spec("meta-poca", {}, "smoke",
                      preset_overrides={"overlap_sampling": True, "num_env_runners": 1})
    assert main(["train", "--algo", "ppo", "--preset", "smoke", "--overlap"]) == 2


def _dist_inputs(algo, weights, module_id: str, obs: np.ndarray) -> torch.Tensor:
    algo.learner_group.set_weights(weights)
    module = algo.learner_group._learner.module[module_id]
    with torch.no_grad():
        return module.forward_inference({Columns.OBS: torch.as_tensor(obs)})[
            Columns.ACTION_DIST_INPUTS]


@pytest.mark.parametrize("build", [ppo_config, poca_config], ids=["ppo", "poca"])
def test_each_batch_is_learned_one_update_after_the_weights_that_sampled_it(ray_session,
                                                                           build):
    algo = build(ENV, train_batch_size=200, minibatch_size=64, num_epochs=1,
                 num_env_runners=1, num_envs_per_env_runner=2, overlap_sampling=True,
                 seed=3).build_algo()
    batches, collect = [], algo._collect_batch

    def keep(*args):
        episodes, metrics = collect(*args)
        batches.append(episodes)
        return episodes, metrics

    algo._collect_batch = keep
    try:
        weights = [algo.learner_group.get_weights()]
        steps = []
        for _ in range(3):
            steps.append(algo.train()["num_env_steps_sampled_lifetime"])
            weights.append(algo.learner_group.get_weights())
        assert steps == [200, 400, 600]  # a whole batch per iteration, nothing dropped
        sampled_by = []
        for episodes in batches:
            agent = next(iter(episodes[0].agent_episodes.values()))
            module_id = "wheeled" if agent.agent_id.startswith("wheeled") else "quad"
            obs = np.asarray(agent.get_observations(slice(0, 4)), np.float32)
            recorded = torch.as_tensor(np.asarray(agent.get_extra_model_outputs(
                Columns.ACTION_DIST_INPUTS, slice(0, 4))))
            matches = [i for i, w in enumerate(weights)
                       if torch.allclose(_dist_inputs(algo, w, module_id, obs), recorded,
                                         atol=1e-5)]
            sampled_by.append(matches)
        # batch 1 and 2 by the initial weights, batch 3 by those after the first update
        assert sampled_by == [[0], [0], [1]]
    finally:
        algo.stop()
