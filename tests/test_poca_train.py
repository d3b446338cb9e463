"""POCA training smoke: trains through Tune, checkpoints restore bit-identical weights."""

from __future__ import annotations

import json
import math

import torch
from ray.rllib.algorithms.algorithm import Algorithm

from rl_scan import results as R
from rl_scan.algorithms.poca import POCA, poca_config
from rl_scan.tuning.launch import train


def _weights(algo):
    learner = algo.learner_group._learner
    return {m: {k: v.detach().clone() for k, v in learner.module[m].state_dict().items()}
            for m in learner.module.keys()}


def test_poca_trains_checkpoints_and_restores(ray_session, tmp_path):
    algo = poca_config({"max_steps": 30}, train_batch_size=200, minibatch_size=128,
                       num_epochs=1, num_envs_per_env_runner=2).build_algo()
    start = _weights(algo)
    for _ in range(2):
        result = algo.train()
    learners = result["learners"]
    for module_id in ("wheeled", "quad"):
        for key in ("total_loss", "policy_loss", "entropy"):
            assert math.isfinite(learners[module_id][key]), (module_id, key)
    for key in ("total_loss", "critic_loss", "value_loss", "baseline_loss"):
        assert math.isfinite(learners["critic"][key]), key
    trained = _weights(algo)
    for m in start:
        assert any(not torch.equal(start[m][k], trained[m][k]) for k in start[m]), m
    algo.save_to_path(str(tmp_path / "ckpt"))
    algo.stop()
    restored = Algorithm.from_checkpoint(str(tmp_path / "ckpt"))
    assert isinstance(restored, POCA)
    again = _weights(restored)
    for m in trained:
        for k in trained[m]:
            assert torch.equal(trained[m][k], again[m][k]), (m, k)
    assert restored.train()["training_iteration"] == 3  # training continues after restore
    restored.stop()


def test_poca_smoke_preset_through_tune(ray_session, tmp_path):
    run_dir = train("poca", {"scenario": "test:2"}, "smoke", results_dir=tmp_path)
    evals = json.loads((run_dir / R.EVAL_FILE).read_text())
    assert [e["training_iteration"] for e in evals] == [1, 2]
    assert all(0.0 <= e["coverage"] <= 1.0 for e in evals)


def test_poca_runs_on_another_env_mpe_simple_spread(ray_session):
    """POCA is not tied to the scanning env: it trains on PettingZoo MPE (3 agents), and its
    group reward there is the sum of the three agents' rewards."""
    import numpy as np
    from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

    from rl_scan.algorithms.poca import columns as C
    from rl_scan.cli.bench_mpe import MODULE, mpe_config, train_mpe

    curve = train_mpe("poca", 0, env_steps=400, train_batch_size=200, minibatch_size=128,
                      num_epochs=1, hiddens=[16, 16])
    assert [s for s, _ in curve] == [200, 400]  # one batch of 200 env steps per iteration
    assert all(r < 0 for _, r in curve)  # simple_spread rewards are minus distances

    config = mpe_config("poca", 0, train_batch_size=50, minibatch_size=50, num_epochs=1,
                        hiddens=[16, 16])
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    episodes = runner.sample(num_timesteps=50, random_actions=False)
    rows = learner._learner_connector(rl_module=learner.module, batch={}, episodes=episodes,
                                      shared_data={})[MODULE]
    ep = episodes[0]
    per_agent = [np.asarray(sa.get_rewards()) for sa in ep.agent_episodes.values()]
    assert len(per_agent) == 3
    np.testing.assert_allclose(rows[C.GROUP_REW].numpy()[:len(per_agent[0])],
                               sum(per_agent), rtol=1e-6)
