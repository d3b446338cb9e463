"""POCA's learner pipeline on real episodes: row alignment, targets, one update (no Ray)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.metrics.metrics_logger import MetricsLogger

from rl_scan.algorithms.poca import columns as C
from rl_scan.algorithms.poca import poca_config
from rl_scan.algorithms.poca.losses import explained_variance, lambda_returns, standardize
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.config import ConfigError
from rl_scan.results import EV_BASELINE, EV_VALUE


def _runner_and_learner(team, **env):
    config = poca_config({"team": {"wheeled": team[0], "quad": team[1]}, "max_steps": 12, **env},
                         train_batch_size=40, minibatch_size=32, num_epochs=1,
                         num_envs_per_env_runner=2)
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    return config, runner, learner


@pytest.mark.parametrize("team", [(2, 2), (1, 3)])
def test_every_row_holds_its_own_observation_and_action_at_its_slot(team):
    config, runner, learner = _runner_and_learner(team)
    episodes = runner.sample(num_timesteps=30, random_actions=False)
    batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=episodes,
                                       shared_data={})
    slots = config.poca_team["slots"]
    table = {k: t.numpy() for k, t in learner.module[CRITIC_ID].table("train").items()}
    table_obs, table_act, present = table["obs"], table["act"], table["present"]
    assert present.min() == 1.0  # every robot acts every step
    for module_id in ("wheeled", "quad"):
        rows = batch[module_id]
        obs, act = rows[Columns.OBS].numpy(), rows[Columns.ACTIONS].numpy()
        idx, step = rows[C.SELF_IDX].numpy(), rows[C.GROUP_ROW].numpy()
        assert set(idx) == {i for i, a in enumerate(slots) if a.startswith(module_id)}
        np.testing.assert_array_equal(table_obs[step, idx, :obs.shape[1]], obs)
        np.testing.assert_array_equal(table_act[step, idx, :act.shape[1]], np.clip(act, -1, 1))
        # the critic's per-step targets are the rows' own (same group return for all
        # robots), in the critic's normalised units
        critic = learner.module[CRITIC_ID]
        for key, column in (("returns", C.RETURNS), ("old_baselines", C.OLD_BASELINES)):
            per_row = table[key][step] if key == "returns" else table[key][step, idx]
            np.testing.assert_allclose(critic.denormalize(torch.as_tensor(per_row)).numpy(),
                                       rows[column].numpy(), rtol=1e-4, atol=1e-3)
    # every step of the table is shared by all the robots' rows of that step
    n_steps = len(table_obs)
    assert n_steps * len(slots) == len(batch["wheeled"][C.GROUP_ROW]) + len(
        batch["quad"][C.GROUP_ROW])
    assert CRITIC_ID not in batch  # the critic learns on the group table instead
    # its minibatches: 32-row module minibatches over the largest module's rows take
    # ceil(valid steps * 32 / largest rows) steps, so both pass equally often
    largest = max(len(batch[m][C.GROUP_ROW]) for m in ("wheeled", "quad"))
    valid = int(sum(batch["quad"][Columns.LOSS_MASK].numpy())) // team[1]
    schedule = learner.module[CRITIC_ID].minibatches["train"]
    assert len(schedule.steps) == valid
    assert schedule.size == int(np.ceil(valid * 32 / largest))


def test_targets_are_lambda_returns_of_the_group_reward_minus_baselines():
    config, runner, learner = _runner_and_learner((2, 2))
    episodes = runner.sample(num_timesteps=30, random_actions=False)
    metrics = MetricsLogger()
    batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=episodes,
                                       shared_data={}, metrics=metrics)
    rows = batch["quad"]
    v, b = rows[C.OLD_VALUES].numpy(), rows[C.OLD_BASELINES].numpy()
    g = lambda_returns(v, rows[C.GROUP_REW].numpy(), rows[Columns.TERMINATEDS].numpy(),
                       rows[Columns.TRUNCATEDS].numpy(), config.gamma, config.lambda_)
    np.testing.assert_allclose(rows[C.RETURNS].numpy(), g, rtol=1e-5, atol=1e-5)
    mask = rows[Columns.LOSS_MASK].numpy()
    np.testing.assert_allclose(rows[Postprocessing.ADVANTAGES].numpy(),
                               standardize(g - b, mask), rtol=1e-4, atol=1e-4)
    # the critic diagnostics: how much of the returns b_i (per kind) and V explain
    valid = mask.astype(bool)
    assert metrics.peek(("quad", EV_BASELINE)) == pytest.approx(
        explained_variance(g[valid], b[valid]), abs=1e-5)
    critic = learner.module[CRITIC_ID]
    table, steps = critic.table(), critic.minibatches["train"].steps
    # the critic regresses on normalised targets: they de-normalise to the group returns
    quad_steps = rows[C.GROUP_ROW].long()[torch.as_tensor(valid)]
    np.testing.assert_allclose(critic.denormalize(table["returns"][quad_steps]).numpy(),
                               g[valid], rtol=1e-4, atol=1e-3)
    assert abs(critic.return_scale()[0].item() - 0.0) > 1e-3  # statistics were set
    assert metrics.peek((CRITIC_ID, EV_VALUE)) == pytest.approx(explained_variance(
        table["returns"][steps].numpy(), table["old_values"][steps].numpy()), abs=1e-5)
    # the group reward of a step is the sum of the four robots' rewards at that step
    ep = episodes[0]
    total = sum(np.asarray(sa.get_rewards()) for sa in ep.agent_episodes.values())
    quad_rows = rows[C.GROUP_REW].numpy()[: len(total)]
    np.testing.assert_allclose(quad_rows, total)


def test_the_review_ablations_use_g_minus_v_and_the_mean_group_reward():
    """advantage_baseline='value': every robot's advantage is G - V (no b_i);
    group_reward='mean': the group reward is the robots' mean, not their sum."""
    config = poca_config({"team": {"wheeled": 2, "quad": 2}, "max_steps": 12},
                         train_batch_size=40, minibatch_size=32, num_epochs=1,
                         num_envs_per_env_runner=2)
    config.poca(advantage_baseline="value", group_reward="mean")
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    episodes = runner.sample(num_timesteps=30, random_actions=False)
    batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=episodes,
                                       shared_data={})
    rows = batch["quad"]
    v = rows[C.OLD_VALUES].numpy()
    g = rows[C.RETURNS].numpy()
    np.testing.assert_allclose(rows[Postprocessing.ADVANTAGES].numpy(),
                               standardize(g - v, rows[Columns.LOSS_MASK].numpy()),
                               rtol=1e-4, atol=1e-4)
    ep = episodes[0]
    total = sum(np.asarray(sa.get_rewards()) for sa in ep.agent_episodes.values())
    np.testing.assert_allclose(rows[C.GROUP_REW].numpy()[: len(total)], total / 4, rtol=1e-6)
    with pytest.raises(ConfigError, match="advantage_baseline='v' is invalid"):
        config.copy(copy_frozen=False).poca(advantage_baseline="v")


def test_one_update_moves_actors_and_critic():
    _, runner, learner = _runner_and_learner((2, 2))
    before = {m: [p.detach().clone() for p in learner.module[m].parameters()]
              for m in ("wheeled", "quad", CRITIC_ID)}
    episodes = runner.sample(num_timesteps=40, random_actions=False)
    results = learner.update(episodes=episodes, num_epochs=1, minibatch_size=32)
    for m, params in before.items():
        after = list(learner.module[m].parameters())
        assert any(not torch.equal(a, b) for a, b in zip(after, params)), m
    for kind in ("wheeled", "quad"):  # the actor loss as logged, from its parts by hand
        r = {k: float(v) for k, v in results[kind].items() if k in (
            "total_loss", "policy_loss", "entropy", "entropy_coeff")}
        assert r["total_loss"] == pytest.approx(r["policy_loss"] - 0.005 * r["entropy"],
                                                abs=1e-6)
        # an untrained Gaussian (log std ~ 0): mean entropy per dimension 0.5 ln(2 pi e)
        assert r["entropy"] == pytest.approx(0.5 * math.log(2 * math.pi * math.e), abs=2e-3)


@pytest.mark.parametrize("poison", [False, True])
def test_the_lean_optimizer_step_equals_rllibs(poison):
    """One fused finite check instead of RLlib's two per parameter, same parameters after;
    a NaN gradient takes RLlib's own path (zeroed, with its warning)."""
    from collections import defaultdict

    from ray.rllib.core.learner.torch.torch_learner import TorchLearner

    _, _, learner = _runner_and_learner((2, 2))
    start = {pid: p.detach().clone() for pid, p in learner._params.items()}
    gen = torch.Generator().manual_seed(0)
    grads = {pid: torch.randn(p.shape, generator=gen) for pid, p in learner._params.items()}
    first = next(iter(grads))
    if poison:  # zeroed by RLlib's path: Adam's first step then leaves it in place
        grads[first] = torch.full_like(grads[first], float("nan"))

    def step(apply) -> dict:
        with torch.no_grad():
            for pid, p in learner._params.items():
                p.copy_(start[pid])
        for module_id, names in learner._module_optimizers.items():
            for name in names:  # a fresh Adam state
                learner.get_optimizer(module_id, name).state = defaultdict(dict)
        apply(learner, {k: g.clone() for k, g in grads.items()})
        return {pid: p.detach().clone() for pid, p in learner._params.items()}

    lean, rllib = step(type(learner).apply_gradients), step(TorchLearner.apply_gradients)
    for pid in start:
        moved = not torch.equal(lean[pid], start[pid])
        assert torch.isfinite(lean[pid]).all() and moved != (poison and pid is first)
        assert torch.equal(lean[pid], rllib[pid])
