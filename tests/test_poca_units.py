"""POCA pieces against hand-computed values (no Ray cluster: modules and learners run locally)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from ray.rllib.utils.postprocessing.value_predictions import compute_value_targets

from rl_scan.algorithms.poca.losses import (
    lambda_returns,
    poca_critic_loss,
    standardize,
    trust_region_value_loss,
)


def test_lambda_returns_terminated_and_truncated_chunks():
    # gamma 0.9, lambda 0.5; each chunk is followed by its bootstrap row.
    # chunk A terminates at its 3rd step: G2 = 2; G1 = 0 + .9(.5*2.0 + .5*2) = 1.8;
    #   G0 = 1 + .9(.5*1.0 + .5*1.8) = 2.26; its bootstrap row (V = 3) is ignored: G = V.
    # chunk B is truncated after 2 steps, bootstrap V = 4: G1 = 1 + .9*4 = 4.6;
    #   G0 = 1 + .9(.5*2.0 + .5*4.6) = 3.97.
    values = np.array([0.5, 1.0, 2.0, 3.0, 1.0, 2.0, 4.0])
    rewards = np.array([1.0, 0.0, 2.0, 0.0, 1.0, 1.0, 0.0])
    term = np.array([0, 0, 1, 0, 0, 0, 0], bool)
    trunc = np.array([0, 0, 0, 0, 0, 1, 0], bool)
    g = lambda_returns(values, rewards, term, trunc, gamma=0.9, lambda_=0.5)
    np.testing.assert_allclose(g, [2.26, 1.8, 2.0, 3.0, 3.97, 4.6, 4.0], rtol=1e-6)
    # RLlib's GAE value targets agree on every real (non-bootstrap) row
    rllib = compute_value_targets(values, rewards, term.astype(float), trunc.astype(float),
                                  0.9, 0.5)
    real = [0, 1, 2, 4, 5]
    np.testing.assert_allclose(g[real], rllib[real], rtol=1e-6)


def test_trust_region_value_loss_and_critic_weighting_by_hand():
    # row 0: max((2-1)^2 = 1, (2 - (0 + .2))^2 = 3.24) = 3.24
    # row 1: max((3-3)^2 = 0, (3 - (3.5 - .2))^2 = .09) = .09 -> mean 1.665
    v, v_old, g = torch.tensor([1.0, 3.0]), torch.tensor([0.0, 3.5]), torch.tensor([2.0, 3.0])
    loss = trust_region_value_loss(v, v_old, g, 0.2, torch.ones(2))
    assert loss.item() == pytest.approx(1.665, abs=1e-6)
    assert poca_critic_loss(torch.tensor(2.0), torch.tensor(4.0)).item() == 2.0  # .5(2+.5*4)


def test_standardize_uses_valid_rows_only():
    x = np.array([1.0, 3.0, 1000.0])
    np.testing.assert_allclose(standardize(x, np.array([1, 1, 0])), [-1.0, 1.0, 998.0])


def _critic(slot_kinds, obs_dims=(3, 4), act_dims=(2, 3)):
    import gymnasium as gym
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from rl_scan.algorithms.poca.modules import POCACritic

    box = gym.spaces.Box(-1, 1, (1,), np.float32)
    torch.manual_seed(0)
    return RLModuleSpec(module_class=POCACritic, observation_space=box, action_space=box,
                        learner_only=True,
                        model_config={"slot_kinds": list(slot_kinds), "obs_dims": list(obs_dims),
                                      "act_dims": list(act_dims), "hidden": 16,
                                      "heads": 2}).build()


def _group(n_slots, rows=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(rows, n_slots, 4, generator=g) * 2 - 1,
            torch.rand(rows, n_slots, 3, generator=g) * 2 - 1, torch.ones(rows, n_slots))


@pytest.mark.parametrize("slot_kinds", [[0, 0, 1, 1], [0, 1, 1, 1]])
def test_baseline_ignores_own_action_but_not_teammates(slot_kinds):
    critic = _critic(slot_kinds)
    obs, act, present = _group(4)
    for me in range(4):
        idx = torch.full((5,), me)
        v, b = critic.values_and_baselines(obs, act, idx, present)
        own = act.clone()
        own[:, me] += 0.7
        v2, b2 = critic.values_and_baselines(obs, own, idx, present)
        assert torch.allclose(b, b2) and torch.allclose(v, v2)
        mate = act.clone()
        mate[:, (me + 1) % 4] += 0.7
        v3, b3 = critic.values_and_baselines(obs, mate, idx, present)
        assert torch.allclose(v, v3)  # V never sees actions
        assert not torch.allclose(b, b3, atol=1e-6)


def test_critic_loss_on_table_steps_is_the_ml_agents_weighting():
    critic = _critic([0, 0, 1, 1])
    obs, act, present = _group(4)
    present[1, 3] = 0.0  # one robot absent at step 1: its baseline is not regressed
    with torch.no_grad():
        v, b = critic.group_heads(critic.encode(obs), act, present)
    critic.set_group_table("train", obs=obs, act=act, present=present, returns=v + 1.0,
                           old_values=v, old_baselines=b)
    steps = torch.tensor([0, 1, 3])
    out = critic.loss(steps, epsilon=0.2)
    # unchanged weights (v = v_old, b = b_old): clipping changes nothing, so the losses
    # are the plain squared errors of both heads against the same return G = v + 1,
    # the baseline one averaged over the 11 present (step, robot) pairs
    assert out["value_loss"].item() == pytest.approx(1.0, abs=1e-5)
    err = (v[steps, None] + 1.0 - b[steps]) ** 2
    expected_b = (err.sum() - err[1, 3]).item() / 11
    assert out["baseline_loss"].item() == pytest.approx(expected_b, abs=1e-5)
    assert out["critic_loss"].item() == pytest.approx(0.5 * (1.0 + 0.5 * expected_b),
                                                      abs=1e-5)


def test_group_heads_equal_one_attention_pass_per_robot():
    """The shared-projection baselines equal attending over each robot's own sequence."""
    critic = _critic([0, 1, 1, 1])
    obs, act, present = _group(4)
    present[2, 0] = 0.0
    enc = critic.encode(obs)
    v, b = critic.group_heads(enc, act, present)
    obs_tok, oa_tok = torch.zeros_like(enc), torch.zeros_like(enc)
    for k, slots in critic._slots_of.items():
        obs_tok[:, slots] = critic.obs_embeddings[str(k)](enc[:, slots])
        oa_tok[:, slots] = critic.obs_action_embeddings[str(k)](
            torch.cat([enc[:, slots], act[:, slots, :critic.act_dims[k]]], -1))

    def value(tokens):
        pooled = critic.attention(tokens, present.bool())
        count = 2.0 * present.sum(1, keepdim=True) / 4 - 1.0
        return critic.head(critic.body(torch.cat([pooled, count], -1))).squeeze(-1)

    assert torch.allclose(v, value(obs_tok), atol=1e-6)
    for i in range(4):
        tokens = oa_tok.clone()
        tokens[:, i] = obs_tok[:, i]
        assert torch.allclose(b[:, i], value(tokens), atol=1e-6)


def test_group_minibatches_pass_over_every_step_once_per_pass():
    from rl_scan.algorithms.poca.connectors import GroupMinibatches

    torch.manual_seed(0)
    steps = torch.tensor([0, 2, 3, 5, 7, 8, 9])
    schedule = GroupMinibatches(steps, 3)
    drawn = torch.cat([schedule.next() for _ in range(7)])  # 21 = 3 passes of 7
    assert all(len(schedule.next()) == 3 for _ in range(2))
    for p in range(3):
        assert sorted(drawn[7 * p:7 * p + 7].tolist()) == steps.tolist()
    assert len(GroupMinibatches(steps[:0], 4).next()) == 0


def test_critic_ignores_padding_and_absent_robots():
    critic = _critic([0, 0, 1, 1])
    obs, act, present = _group(4)
    idx = torch.zeros(5, dtype=torch.long)
    v, b = critic.values_and_baselines(obs, act, idx, present)
    padded = obs.clone()
    padded[:, :2, 3:] = 5.0  # wheeled robots have 3 obs features: the 4th is padding
    v2, b2 = critic.values_and_baselines(padded, act, idx, present)
    assert torch.allclose(v, v2) and torch.allclose(b, b2)
    absent = present.clone()
    absent[:, 3] = 0.0
    changed = obs.clone()
    changed[:, 3] += 1.0
    v3, _ = critic.values_and_baselines(obs, act, idx, absent)
    v4, _ = critic.values_and_baselines(changed, act, idx, absent)
    assert torch.allclose(v3, v4)  # an absent robot's observation is masked out
    assert not torch.allclose(v, v3)


def _episode(rewards: dict[str, list[float]]):
    from ray.rllib.env.multi_agent_episode import MultiAgentEpisode

    ep = MultiAgentEpisode()
    ep.add_env_reset(observations={a: np.zeros(3, np.float32) for a in rewards})
    for t in range(len(next(iter(rewards.values())))):
        ep.add_env_step(observations={a: np.full(3, t + 1, np.float32) for a in rewards},
                        actions={a: np.zeros(2, np.float32) for a in rewards},
                        rewards={a: r[t] for a, r in rewards.items()})
    return ep


@pytest.mark.parametrize("team, rewards, group", [
    (False, {"w_0": [2.0, 1.0], "q_0": [-1.0, 0.0], "q_1": [-2.0, 0.5]}, [-1.0, 1.5]),
    (True, {"w_0": [-1.5, 3.0], "q_0": [-1.5, 3.0], "q_1": [-1.5, 3.0]}, [-1.5, 3.0])])
def test_group_reward_sums_individual_rewards_and_keeps_a_negative_team_reward(
        team, rewards, group):
    from rl_scan.algorithms.poca.connectors import AddGroupColumns

    connector = AddGroupColumns(slots=list(rewards), obs_dim=3, act_dim=2, team_reward=team)
    np.testing.assert_allclose(connector.group_arrays(_episode(rewards))["rew"], group)


def test_team_reward_mode_refuses_robots_with_different_rewards():
    from rl_scan.algorithms.poca.connectors import AddGroupColumns

    connector = AddGroupColumns(slots=["w_0", "q_0"], obs_dim=3, act_dim=2, team_reward=True)
    with pytest.raises(ValueError, match="robot q_0 .* differ from its team's"):
        connector.group_arrays(_episode({"w_0": [1.0], "q_0": [0.5]}))


def test_explained_variance_by_hand():
    from rl_scan.algorithms.poca.losses import explained_variance

    returns = np.array([1.0, 2.0, 3.0, 4.0])  # variance 1.25
    assert explained_variance(returns, returns) == 1.0
    assert explained_variance(returns, np.full(4, 2.5)) == pytest.approx(0.0)
    # errors (0.5, -0.5, 0.5, -0.5): variance 0.25 -> 1 - 0.25 / 1.25
    assert explained_variance(returns, returns - [0.5, -0.5, 0.5, -0.5]) == pytest.approx(0.8)
    assert math.isnan(explained_variance(np.ones(4), np.zeros(4)))


def test_ml_agents_decays_at_0_50_and_100_percent_of_the_budget():
    """decay_steps: lr, clip range and beta fall linearly to ML-Agents' ends, and the
    learner's optimizer, clip range and entropy weight follow them."""
    from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner
    from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

    from rl_scan.algorithms.poca import poca_config
    from rl_scan.config import ConfigError

    config = poca_config({"max_steps": 12}, train_batch_size=40, minibatch_size=32,
                         decay_steps=1000, lr=4e-4, clip_param=0.3, entropy_coeff=0.01)
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    expected = {0: (4e-4, 0.3, 0.01), 500: ((4e-4 + 1e-10) / 2, 0.2, (0.01 + 1e-5) / 2),
                1000: (1e-10, 0.1, 1e-5), 2000: (1e-10, 0.1, 1e-5)}
    for step, (lr, clip, beta) in expected.items():
        learner.after_gradient_based_update(timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: step})
        lrs = [g["lr"] for opt in learner._optimizer_parameters for g in opt.param_groups]
        assert lrs and all(x == pytest.approx(lr, rel=1e-6) for x in lrs), (step, lrs)
        assert learner.current_clip() == pytest.approx(clip), step
        assert learner.entropy_coeff_schedulers["quad"].get_current_value() == pytest.approx(
            beta, rel=1e-6), step
    runner.stop()
    with pytest.raises(ConfigError, match="decay_steps=0 is invalid"):
        poca_config({}, train_batch_size=40, minibatch_size=32, decay_steps=0)


def test_decay_schedules_come_with_the_paper_preset_and_meta_poca_keeps_fixed_settings():
    from rl_scan.config import ConfigError
    from rl_scan.tuning.driver import make_run_spec

    poca = make_run_spec("poca", {}, "paper").algorithm_config()
    assert poca.clip_param_schedule == [[0, 0.2], [8_000_000, 0.1]]
    assert poca.lr == [[0, 3e-4], [8_000_000, 1e-10]]
    assert make_run_spec("poca", {}, "quick").algorithm_config().lr == 3e-4
    assert not make_run_spec("meta-poca", {}, "paper").preset.decay_schedules
    with pytest.raises(ConfigError, match="decay_schedules=True is invalid: allowed False "
                                          "for meta-poca"):
        make_run_spec("meta-poca", {}, "quick", preset_overrides={"decay_schedules": True})


def test_return_normalisation_keeps_every_output_and_targets_denormalise_to_returns():
    """PopArt: new statistics rescale the output layer so V and b_i (de-normalised) do not
    move; the first batch sets the statistics, later ones move them by RETURN_STATS_RATE."""
    from rl_scan.algorithms.poca.modules import RETURN_STATS_RATE

    critic = _critic([0, 0, 1, 1])
    obs, act, present = _group(4)

    def outputs():
        with torch.no_grad():
            v, b = critic.group_heads(critic.encode(obs), act, present)
        return critic.denormalize(v), critic.denormalize(b)

    before = outputs()
    returns = torch.tensor([10.0, 50.0, 300.0])
    critic.update_return_stats(returns)
    mean, std = critic.return_scale()
    assert mean.item() == pytest.approx(120.0) and std.item() == pytest.approx(
        float(np.std([10.0, 50.0, 300.0])), rel=1e-5)
    for a, b in zip(before, outputs()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(critic.denormalize(critic.normalize(returns)), returns)
    critic.update_return_stats(torch.tensor([220.0]))  # mean -> 0.9 * 120 + 0.1 * 220
    assert critic.return_scale()[0].item() == pytest.approx(
        (1 - RETURN_STATS_RATE) * 120.0 + RETURN_STATS_RATE * 220.0)
    for a, b in zip(before, outputs()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)


def test_counterfactual_baseline_assigns_credit_to_the_agent_whose_action_counts():
    """Two agents, one step: the team reward is 1 if agent 0's action is positive, whatever
    agent 1 does. After POCA's critic regression, agent 0's advantage G - b_0 tracks its
    own action and agent 1's G - b_1 is ~0 (b_1 sees agent 0's action and absorbs the
    reward). With V as every agent's baseline, agent 1 gets as large an advantage as agent
    0 for an action that did not matter: the credit POCA exists for."""
    critic = _critic([0, 1], obs_dims=(3, 3), act_dims=(1, 1))
    optimizer = torch.optim.Adam(critic.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    steps, present = 512, torch.ones(512, 2)
    obs = torch.zeros(steps, 2, 3)

    def play():
        act = torch.rand(steps, 2, 1, generator=g) * 2 - 1
        return act, (act[:, 0, 0] > 0).float()  # team reward, held by both agents

    for _ in range(150):  # one POCA critic update per batch, as POCATargets sets it up
        act, returns = play()
        with torch.no_grad():
            v, b = critic.group_heads(critic.encode(obs), act, present)
            v, b = critic.denormalize(v), critic.denormalize(b)
        critic.update_return_stats(returns)
        critic.set_group_table(obs=obs, act=act, present=present,
                               returns=critic.normalize(returns), old_values=critic.normalize(v),
                               old_baselines=critic.normalize(b))
        loss = critic.loss(torch.arange(steps), epsilon=0.2)["critic_loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    act, returns = play()
    with torch.no_grad():
        v, b = critic.group_heads(critic.encode(obs), act, present)
        v, b = critic.denormalize(v), critic.denormalize(b)
    own_action_counts = (act[:, 0, 0] > 0).float()
    adv_0, adv_1 = returns - b[:, 0], returns - b[:, 1]
    assert np.corrcoef(adv_0.numpy(), own_action_counts.numpy())[0, 1] > 0.95
    assert adv_1.abs().mean() < 0.2 * adv_0.abs().mean()
    adv_v = returns - v  # the same for both agents when V is the baseline
    assert adv_v.abs().mean() > 0.8 * adv_0.abs().mean()

