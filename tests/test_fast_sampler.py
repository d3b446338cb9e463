"""The fast sampler (``FastEnvRunner``) against RLlib's own runner, in local mode.

RLlib's runner batches each module's rows in a hash-dependent agent order with two torch
threads; matrix products on other row orders differ in the last bits. So the comparison
uses a scripted actor whose actions come from each robot's own observation elementwise
(the same bits in any batch), acting greedily (explore=False), as evaluation without
exploration does: then every observation, action, reward and flag must be equal.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from ray.rllib.callbacks.callbacks import RLlibCallback
from ray.rllib.core.columns import Columns
from ray.rllib.core.distribution.torch.torch_distribution import TorchDiagGaussian
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

from rl_scan.algorithms.fast_runner import FastEnvRunner, check_fast_sampler
from rl_scan.algorithms.poca import poca_config
from rl_scan.algorithms.poca.modules import GaussianActor
from rl_scan.config import ConfigError

RAY_FEATURES = 6  # per ray: 4 tags, miss flag, hit fraction


class ScriptedActor(GaussianActor):
    """Mean action k = 2 * (hit fraction of ray 37 k) - 1: elementwise, batch-independent."""

    def _forward(self, batch, **kwargs):
        n = self.action_space.shape[0]
        hits = batch[Columns.OBS][:, RAY_FEATURES - 1::RAY_FEATURES * 37][:, :n]
        mean = 2.0 * hits - 1.0
        return {Columns.ACTION_DIST_INPUTS: torch.cat([mean, self.log_std.expand_as(mean)], -1)}


def poca_runner_config(max_steps: int, envs: int, seed: int = 3):
    return poca_config({"max_steps": max_steps}, train_batch_size=40, minibatch_size=32,
                       num_envs_per_env_runner=envs, seed=seed)


def scripted_config(max_steps: int, envs: int, seed: int = 3):
    config = poca_runner_config(max_steps, envs, seed)
    spec = RLModuleSpec(module_class=ScriptedActor, model_config={"hiddens": [8]})
    return config.rl_module(rl_module_spec=MultiRLModuleSpec(
        rl_module_specs={"wheeled": spec, "quad": spec}))


def chunk_data(episode) -> dict:
    """Everything a learner or callback reads from an episode chunk (ids aside)."""
    agents = {}
    for aid, sa in episode.agent_episodes.items():
        agents[aid] = {
            "obs": sa.observations.data, "actions": sa.actions.data,
            "rewards": sa.rewards.data, "lookback": sa.observations.lookback,
            "outputs": {k: v.data for k, v in sa.extra_model_outputs.items()},
            "flags": (sa.is_terminated, sa.is_truncated, sa.t_started, sa.t, sa.module_id),
            "infos": sa.infos.data, "env_t_to_agent_t": list(episode.env_t_to_agent_t[aid]
                                                            .data)}
    return {"len": len(episode), "env_t": (episode.env_t_started, episode.env_t),
            "flags": (episode.is_terminated, episode.is_truncated), "agents": agents}


def assert_same(a, b, path="episode"):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            assert_same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        np.testing.assert_array_equal(a, b, err_msg=path)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    else:
        assert a == b or (a != a and b != b), (path, a, b)  # NaN: steps never reached


def test_fast_batches_equal_rllib_batches_for_a_scripted_policy():
    config = scripted_config(max_steps=7, envs=3)
    stock, fast = MultiAgentEnvRunner(config=config), FastEnvRunner(config=config)
    same_episode = {}  # stock episode id -> fast episode id: chunks continue alike
    for call in ({"num_timesteps": 10}, {"num_timesteps": 4}, {"num_timesteps": 13},
                 {"num_timesteps": 2}, {"num_episodes": 2}, {"num_timesteps": 9}):
        ours, theirs = fast.sample(explore=False, **call), stock.sample(explore=False, **call)
        assert [len(e) for e in ours] == [len(e) for e in theirs], call
        for s, f in zip(theirs, ours):
            assert same_episode.setdefault(s.id_, f.id_) == f.id_
            assert_same(chunk_data(s), chunk_data(f))
    assert len(set(same_episode.values())) == len(same_episode)
    ours, theirs = fast.get_metrics(), stock.get_metrics()
    for key in ("num_env_steps_sampled", "num_episodes", "episode_len_mean",
                "episode_return_mean", "scan/coverage", "num_env_steps_sampled_lifetime"):
        assert ours[key].peek() == theirs[key].peek(), key
    for key in ("agent_episode_returns_mean", "num_agent_steps_sampled",
                "num_module_steps_sampled"):
        assert {k: v.peek() for k, v in ours[key].items()} == {
            k: v.peek() for k, v in theirs[key].items()}, key


def _glued(chunks) -> dict:
    """Per (agent, first observation): its episode's chunks concatenated, lookback dropped."""
    out, first = {}, {}
    for e in chunks:
        for aid, sa in e.agent_episodes.items():
            part = {"obs": sa.get_observations(), "actions": sa.get_actions(),
                    "rewards": sa.get_rewards()}
            key = first.setdefault((e.id_, aid), (aid, part["obs"][0].tobytes()))
            whole = out.get(key)
            if whole is None:
                out[key] = part
                continue
            # a continuation starts where its predecessor ended, which it keeps as lookback
            np.testing.assert_array_equal(part["obs"][0], whole["obs"][-1])
            np.testing.assert_array_equal(
                sa.get_observations(-1, neg_index_as_lookback=True), whole["obs"][-2])
            out[key] = {"obs": np.concatenate([whole["obs"], part["obs"][1:]]),
                        **{k: np.concatenate([whole[k], part[k]]) for k in ("actions",
                                                                            "rewards")}}
    return out


def test_episodes_cut_across_calls_resume_exactly_while_exploring():
    """Three calls of 14 env steps give the same episodes as one call of 42 steps."""
    config = poca_runner_config(max_steps=9, envs=2)
    cut = FastEnvRunner(config=config)
    torch.manual_seed(1)
    pieces = [e for _ in range(3) for e in cut.sample(num_timesteps=14, explore=True)]
    whole = FastEnvRunner(config=config)
    torch.manual_seed(1)
    once = whole.sample(num_timesteps=42, explore=True)
    assert sorted(len(e) for e in once) == [3, 3, 9, 9, 9, 9]  # 9, reset, 9, reset, 3
    assert any(e.env_t_started > 0 for e in pieces)
    glued, reference = _glued(pieces), _glued(once)
    assert glued.keys() == reference.keys() and len(glued) == 6 * 4
    for key, episode in reference.items():
        for k in ("obs", "actions", "rewards"):
            np.testing.assert_array_equal(glued[key][k], episode[k])


def test_truncation_at_max_steps_then_reset_at_the_next_step():
    runner = FastEnvRunner(config=scripted_config(max_steps=5, envs=2))
    episodes = runner.sample(num_timesteps=24, explore=False)
    done = [e for e in episodes if e.is_done]
    # per world: 5 steps, a reset step, 5 steps, a reset step, 2 steps (24 env steps)
    assert [len(e) for e in done] == [5, 5, 5, 5] and len(episodes) == 6
    for e in done:
        assert e.is_truncated and e.is_terminated  # RLlib 2.60 marks all-done as terminated
        sa = e.agent_episodes["wheeled_0"]
        assert sa.is_truncated and len(sa.get_observations()) == 6
        assert "episode_metrics" in e.get_infos(-1)["wheeled_0"]
    second = done[2:]
    assert all(e.env_t_started == 0 for e in second)
    assert {e.id_ for e in second}.isdisjoint({e.id_ for e in done[:2]})
    world = runner.worlds[0]
    assert world.t == 2 and not world.done  # auto-reset, then two steps of the third episode
    metrics = runner.get_metrics()
    assert metrics["num_episodes"].peek() == 4 and metrics["episode_len_mean"].peek() == 5
    assert metrics["scan/episode_steps"].peek() == 5  # the callback saw every episode


def test_same_seed_same_batch_and_another_seed_another():
    def first_batch(seed):
        runner = FastEnvRunner(config=poca_runner_config(max_steps=6, envs=2, seed=seed))
        return [chunk_data(e) for e in runner.sample(num_timesteps=16, explore=True)]

    a, b, c = first_batch(5), first_batch(5), first_batch(6)
    assert_same(a, b)
    with pytest.raises(AssertionError):
        assert_same(a, c)


def test_exploring_draws_from_the_modules_gaussian():
    """The numpy draw is TorchDiagGaussian's: the stored logp is its logp of the stored
    action, and the actions' standardised noise is standard normal."""
    runner = FastEnvRunner(config=poca_runner_config(max_steps=50, envs=2))
    noise = []
    for e in runner.sample(num_timesteps=400, explore=True):
        for sa in e.agent_episodes.values():
            inputs = sa.get_extra_model_outputs(Columns.ACTION_DIST_INPUTS)
            actions = sa.get_actions()
            dist = TorchDiagGaussian.from_logits(torch.from_numpy(inputs))
            np.testing.assert_allclose(sa.get_extra_model_outputs(Columns.ACTION_LOGP),
                                       dist.logp(torch.from_numpy(actions)).numpy(),
                                       rtol=1e-5, atol=1e-4)
            mean, log_std = np.split(inputs, 2, axis=-1)
            noise.append(((actions - mean) / np.exp(log_std)).ravel())
    noise = np.concatenate(noise)
    assert len(noise) == 400 * 16 and abs(noise.mean()) < 0.05 and abs(noise.std() - 1) < 0.05


def test_force_reset_and_num_episodes_reset_as_rllib_does():
    """Forced and num_episodes resets continue the envs' generators; the call after a
    num_episodes call starts again from the seeded reset (RLlib's runner does the same)."""
    runner = FastEnvRunner(config=scripted_config(max_steps=6, envs=2))

    def first_obs(episodes):
        return episodes[0].agent_episodes["quad_0"].get_observations(0)

    first = runner.sample(num_timesteps=4, explore=False)
    again = runner.sample(num_timesteps=4, explore=False, force_reset=True)
    assert [e.env_t_started for e in again] == [0, 0]
    assert {e.id_ for e in again}.isdisjoint({e.id_ for e in first})
    assert not np.array_equal(first_obs(first), first_obs(again))
    episodes = runner.sample(num_episodes=3, explore=False)
    assert len(episodes) == 3 and all(len(e) == 6 and e.is_done for e in episodes)
    np.testing.assert_array_equal(first_obs(first),
                                  first_obs(runner.sample(num_timesteps=4, explore=False)))


class StepCallback(RLlibCallback):
    def on_episode_step(self, **kwargs):
        pass


def test_what_the_fast_sampler_cannot_run_fails_with_the_fix():
    config = scripted_config(max_steps=6, envs=1)
    with pytest.raises(ConfigError, match=r"sampler='fast' is invalid: allowed 'rllib'.*"
                                          r"on_episode_step"):
        check_fast_sampler(config.copy().callbacks(StepCallback))
    with pytest.raises(ConfigError, match=r"sampler='fast'.*ScanMultiAgentEnv"):
        FastEnvRunner(config=config.copy().environment("CartPole-v1"))
    with pytest.raises(ConfigError, match="random_actions"):
        FastEnvRunner(config=config).sample(num_timesteps=2, random_actions=True)
