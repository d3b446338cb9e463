"""MetaPOCA (first-order MAML-PPO over POCA): the inner update is POCA's own, the query
gradient is the one at theta + delta, the outer loop uses every sampled step.

Learners are built standalone (no Ray) on real episodes of the scanning env.
"""

from __future__ import annotations

import copy
import math
import random

import numpy as np
import pytest
import torch
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner
from ray.rllib.utils.metrics.metrics_logger import MetricsLogger

from rl_scan.algorithms.maml import meta_poca_config
from rl_scan.algorithms.maml.meta_poca import set_task
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.algorithms.poca.poca import poca_config
from rl_scan.config import ConfigError
from rl_scan.results import EV_VALUE, META_TERM_RESULTS

ENV = {"max_steps": 12}
TRAINING = dict(num_envs_per_env_runner=2, train_batch_size=64, minibatch_size=16,
                num_epochs=2, lr=1e-3, seed=0)


def _setup(**meta):
    config = meta_poca_config(ENV, **{"tasks": 2, "support_steps": 24, "query_steps": 24,
                                      "task_pool": 5, **meta}, **TRAINING)
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    return config, runner, learner


def _sample(runner, scenario: str, steps: int = 24) -> list:
    set_task(runner, scenario)
    return runner.sample(num_timesteps=steps, force_reset=True)


def _state(learner) -> dict:
    return {k: t.detach().clone() for k, t in learner.float_state().items()}


def _seeded(seed: int = 0) -> None:
    """Same minibatch shuffles in two learners' updates."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _outer_update(config, learner, tasks) -> None:
    """MetaPOCA's outer update on ``tasks`` (it reads only the algorithm's config and
    timesteps, so no algorithm is built)."""
    from types import SimpleNamespace

    from rl_scan.algorithms.maml.meta_poca import MetaPOCA

    MetaPOCA._outer_update(SimpleNamespace(config=config, _timesteps=dict), learner, tasks)


def _tasks(learner, runner, scenarios=("train:0", "train:1"), adapted_query=False) -> list:
    """Tasks with support and query batches and the inner update's delta; the query
    sampled by the adapted actors with ``adapted_query`` (as MetaPOCA samples it), else by
    theta."""
    from rl_scan.algorithms.maml.meta_poca import MetaPOCA, Task

    theta = {mid: copy.deepcopy(runner.module[mid].state_dict())
             for mid in runner.module.keys() if mid != CRITIC_ID}
    tasks = []
    for scenario in scenarios:
        support = _sample(runner, scenario)
        delta, adapted, _ = learner.adapt(support, {})
        if adapted_query:
            MetaPOCA._load_actors(runner, adapted)
        tasks.append(Task(scenario, support, _sample(runner, scenario), delta))
        MetaPOCA._load_actors(runner, theta)
    return tasks


@pytest.mark.parametrize("lr_scale", [1.0, 4.0])  # inner_lr: MAML's alpha over beta
def test_the_inner_update_is_an_ordinary_poca_update_and_leaves_theta_as_it_was(lr_scale):
    _, runner, learner = _setup()
    support = _sample(runner, "train:0")
    # one outer-style update first, so the meta optimizer has state to keep
    learner.update(episodes=copy.deepcopy(support), **learner.update_kwargs({}))
    theta = _state(learner)
    meta_adam = {n: copy.deepcopy(o.state_dict()) for n, o in learner._named_optimizers.items()}

    _seeded()
    delta, adapted, _ = learner.adapt(support, {}, lr_scale=lr_scale)
    # a standalone POCA learner from the same weights, with a new Adam at POCA's lr x
    # lr_scale, on the same batch
    plain_config = poca_config(ENV, **{**TRAINING, "lr": TRAINING["lr"] * lr_scale})
    plain = plain_config.build_learner(env=None, spaces=runner.get_spaces())
    for mid in learner.module.keys():
        plain.module[mid].load_state_dict(learner.module[mid].state_dict())
    _seeded()
    plain.update(episodes=copy.deepcopy(support), timesteps={},
                 num_epochs=plain_config.num_epochs, minibatch_size=plain_config.minibatch_size,
                 shuffle_batch_per_epoch=plain_config.shuffle_batch_per_epoch)
    reached = {(mid, n): t.detach() for mid in plain.module.keys()
               for n, t in plain.module[mid].state_dict().items() if t.is_floating_point()}
    moved = 0
    for key, d in delta.items():
        torch.testing.assert_close(theta[key] + d, reached[key], rtol=1e-5, atol=1e-6)
        moved += bool(d.abs().max() > 0)
    assert moved > 30  # actors and critic alike
    for mid, sd in adapted.items():
        for n, t in sd.items():
            torch.testing.assert_close(t, reached[(mid, n)], rtol=1e-5, atol=1e-6)
    # the learner is back at theta with the meta optimizer's moments and POCA's lr
    assert {o.param_groups[0]["lr"] for o in learner._named_optimizers.values()} == {
        TRAINING["lr"]}
    for key, t in _state(learner).items():
        assert torch.equal(t, theta[key]), key
    for name, opt in learner._named_optimizers.items():
        for p, st in opt.state_dict()["state"].items():
            for k, v in st.items():
                assert torch.equal(v, meta_adam[name]["state"][p][k]), (name, k)


def test_the_inner_update_may_continue_the_meta_adam_state_and_leaves_it_as_it_was():
    """inner_adam='meta': the inner steps start from a copy of the meta optimizer's moments
    (a standalone learner given the same state takes the same steps)."""
    config, runner, learner = _setup(inner_adam="meta")
    support = _sample(runner, "train:0")
    learner.update(episodes=copy.deepcopy(support), **learner.update_kwargs({}))
    theta = _state(learner)
    plain = config.build_learner(env=None, spaces=runner.get_spaces())
    plain.set_state(copy.deepcopy(learner.get_state(components=["rl_module", "optimizer"])))
    meta_adam = {n: copy.deepcopy(o.state_dict()) for n, o in learner._named_optimizers.items()}
    _seeded()
    delta, _, _ = learner.adapt(support, {}, adam="meta")
    _seeded()
    plain.update(episodes=copy.deepcopy(support), **plain.update_kwargs({}))
    reached = {k: t.detach() for k, t in plain.float_state().items()}
    for key, d in delta.items():
        torch.testing.assert_close(theta[key] + d, reached[key], rtol=1e-5, atol=1e-6)
    _seeded()
    fresh, _, _ = learner.adapt(support, {})
    assert any(not torch.allclose(fresh[k], delta[k]) for k in delta)
    _seeded()
    scaled, _, _ = learner.adapt(support, {}, adam="scale")  # beta1 = 0 inside only
    assert any(not torch.allclose(scaled[k], delta[k]) for k in delta)
    for name, opt in learner._named_optimizers.items():
        assert opt.param_groups[0]["betas"] == meta_adam[name]["param_groups"][0]["betas"]
        for p, st in opt.state_dict()["state"].items():
            for k, v in st.items():
                assert torch.equal(v, meta_adam[name]["state"][p][k]), (name, k)


@pytest.mark.parametrize("fused", [False, True])
def test_inner_adam_scale_steps_by_the_task_gradient_over_the_meta_second_moment(fused):
    """inner_adam='scale' by hand: after two meta steps (g1, g2) the inner step on g3 is
    lr * g3 / (sqrt(v3 / (1 - b2^3)) + eps), v3 = b2 v2 + (1 - b2) g3^2: no momentum (m = g3,
    beta1 = 0), the meta optimizer's per-weight scale; the saved meta state, loaded back,
    brings beta1 back. 'fresh' forgets the moments, 'meta' keeps them."""
    from rl_scan.algorithms.maml.learners import inner_adam_state

    lr, b2, eps = 0.1, 0.999, 1e-8
    g1, g2, g3 = [0.5, -1.0], [0.2, 0.4], [1.0, 0.1]
    p = torch.nn.Parameter(torch.tensor([1.0, -2.0]))
    opt = torch.optim.Adam([p], lr=lr, betas=(0.9, b2), eps=eps, fused=fused)
    for g in (g1, g2):
        p.grad = torch.tensor(g)
        opt.step()
    meta_state = copy.deepcopy(opt.state_dict())
    before = p.detach().clone()
    inner_adam_state(opt, "scale")
    p.grad = torch.tensor(g3)
    opt.step()
    for i in range(2):
        v3 = b2 * (b2 * (1 - b2) * g1[i] ** 2 + (1 - b2) * g2[i] ** 2) + (1 - b2) * g3[i] ** 2
        step = lr * g3[i] / (math.sqrt(v3 / (1 - b2 ** 3)) + eps)
        assert (before[i] - p[i]).item() == pytest.approx(step, rel=1e-5)
    opt.load_state_dict(meta_state)  # what adapt's restore does
    assert opt.param_groups[0]["betas"] == (0.9, b2)
    assert opt.state[p]["exp_avg"].abs().sum() > 0
    inner_adam_state(opt, "meta")
    assert torch.equal(opt.state[p]["exp_avg"], meta_state["state"][0]["exp_avg"])
    inner_adam_state(opt, "fresh")
    assert not opt.state
    with pytest.raises(ValueError, match="scale"):
        inner_adam_state(opt, "adamw")


def _params(learner) -> dict:
    return {(mid, n): p for mid in learner.module.keys()
            for n, p in learner.module[mid].named_parameters()}


def test_a_step_inside_shifted_is_the_step_taken_at_theta_plus_delta():
    """The first-order MAML step: the gradient at theta + delta, applied to theta."""
    config, runner, learner = _setup()
    delta, _, _ = learner.adapt(_sample(runner, "train:0"), {})
    query = _sample(runner, "train:0")
    theta = _state(learner)
    # a second learner with the same weights moved to theta + delta (return statistics
    # frozen there too): what functional_call at theta + delta would compute
    loaded = config.build_learner(env=None, spaces=runner.get_spaces())
    for mid in learner.module.keys():
        loaded.module[mid].load_state_dict(learner.module[mid].state_dict())
    with torch.no_grad():
        for key, p in _params(loaded).items():
            p.add_(delta[key])
    loaded.module[CRITIC_ID].return_stats_frozen = True

    _seeded()
    with learner.shifted(delta):
        learner.update(episodes=copy.deepcopy(query), **learner.update_kwargs({}))
    _seeded()
    loaded.update(episodes=copy.deepcopy(query), **loaded.update_kwargs({}))
    after = _params(loaded)
    moved = 0
    for key, p in _params(learner).items():
        step = p.detach() - theta[key]
        torch.testing.assert_close(step, after[key].detach() - theta[key] - delta[key],
                                   rtol=1e-4, atol=1e-6)
        moved += bool(step.abs().max() > 0)
    assert moved > 30
    assert not learner.module[CRITIC_ID].return_stats_frozen  # only inside the block


def test_two_scenarios_adapt_to_different_policies():
    _, runner, learner = _setup()
    delta_a, adapted_a, _ = learner.adapt(_sample(runner, "train:0"), {})
    delta_b, adapted_b, _ = learner.adapt(_sample(runner, "train:3"), {})
    probe = _sample(runner, "train:0")  # the same observations for both adapted teams
    for mid in ("wheeled", "quad"):
        module = copy.deepcopy(learner.module[mid])
        obs = torch.as_tensor(np.concatenate([
            np.asarray(e.agent_episodes[a].get_observations()[:-1])
            for e in probe for a in e.agent_ids if e.agent_episodes[a].module_id == mid]))
        means = []
        for adapted in (adapted_a, adapted_b):
            module.load_state_dict(adapted[mid])
            with torch.no_grad():
                means.append(module.forward_inference({"obs": obs})["action_dist_inputs"])
        theta_out = learner.module[mid].forward_inference({"obs": obs})["action_dist_inputs"]
        shift_a = (means[0] - theta_out).abs().mean()
        assert (means[0] - means[1]).abs().mean() > 0.1 * shift_a > 0, mid


def _module_rows(episodes, module_id: str) -> int:
    """Rows of a module in POCA's batch: each agent's steps plus the one bootstrap step
    RLlib's AddOneTsToEpisodesAndTruncate adds per episode chunk."""
    return sum(len(e.agent_episodes[a]) + 1 for e in episodes for a in e.agent_ids
               if e.agent_episodes[a].module_id == module_id)


def test_the_outer_update_takes_epochs_times_minibatches_steps_on_every_batch(monkeypatch):
    config, runner, learner = _setup()
    tasks = _tasks(learner, runner)
    steps = []
    real = type(learner).apply_gradients
    monkeypatch.setattr(type(learner), "apply_gradients",
                        lambda self, grads: (steps.append(1), real(self, grads))[1])

    def minibatches(episodes) -> int:
        rows = max(_module_rows(episodes, mid) for mid in ("wheeled", "quad"))
        return math.ceil(config.num_epochs * rows / config.minibatch_size)

    expected = minibatches([e for t in tasks for e in t.support]) + sum(
        minibatches(t.query) for t in tasks)
    _outer_update(config, learner, tasks)
    assert len(steps) == expected > 2 * config.num_epochs


def test_a_meta_iteration_learns_from_every_step_it_charges(ray_session):
    """Env steps charged = env steps in the support and query batches = tasks * (S + Q)."""
    config = meta_poca_config(ENV, tasks=2, support_steps=24, query_steps=48, task_pool=5,
                              **TRAINING)
    algo = config.build_algo()
    sampled: list = []
    runner = algo.env_runner
    real = runner.sample

    def recording(**kwargs):
        episodes = real(**kwargs)
        sampled.append(sum(e.env_steps() for e in episodes))
        return episodes

    runner.sample = recording
    learner, evs = algo.learner_group._learner, []  # each update's explained variance of V
    update = learner.update

    def recording_update(**kwargs):
        results = update(**kwargs)
        evs.append(MetricsLogger.peek_results(results)[CRITIC_ID][EV_VALUE])
        return results

    learner.update = recording_update
    result = algo.train()
    algo.stop()
    charged = result["env_runners"]["num_env_steps_sampled_lifetime"]
    assert charged == sum(sampled) == 2 * (24 + 48)
    assert sampled == [24, 48, 24, 48]
    assert result["meta/delta_norm"] > 0 and -1 <= result["meta/delta_cosine"] <= 1
    # 2 inner updates, the update at theta, 2 at theta + delta_i: the learners' results are
    # the update at theta's (as POCA's are), the MAML term's are logged apart
    assert len(evs) == 5 and len(set(evs)) == 5
    assert result["learners"][CRITIC_ID][EV_VALUE] == pytest.approx(evs[2])
    assert result[META_TERM_RESULTS][CRITIC_ID][EV_VALUE] == pytest.approx(np.mean(evs[3:]))


def test_reptile_moves_theta_by_the_mean_task_delta():
    config, runner, learner = _setup(outer="reptile", reptile_lr=0.5)
    theta = _state(learner)
    tasks = _tasks(learner, runner)
    _seeded()
    further = [learner.adapt(t.query, {}, 1, start=t.delta)[0] for t in tasks]

    _seeded()
    _outer_update(config, learner, tasks)
    for key, t in _state(learner).items():
        expected = theta[key] + 0.5 * (further[0][key] + further[1][key]) / 2
        torch.testing.assert_close(t, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("outer, weight", [("multitask", 1.0), ("maml_dr", 1.0),
                                           ("maml_dr", 0.5), ("maml_dr", 0.0)])
def test_the_update_at_theta_learns_every_batch_for_multitask_and_maml_dr(outer, weight):
    """outer='multitask' is one ordinary update at theta on every batch (DR on the same
    data); 'maml_dr' then adds each task's query update at theta + delta at lr x
    maml_weight, for the actors only: a standalone learner with the same state making
    those updates ends at the same weights, its critic (and the critic's Adam) where the
    update at theta left it."""
    config, runner, learner = _setup(outer=outer, maml_weight=weight)
    tasks = _tasks(learner, runner)
    plain = config.build_learner(env=None, spaces=runner.get_spaces())
    plain.set_state(copy.deepcopy(learner.get_state(components=["rl_module", "optimizer"])))
    mixed = copy.deepcopy([e for t in tasks for e in t.support]
                          + [e for t in tasks for e in t.query])
    queries = copy.deepcopy([t.query for t in tasks])

    _seeded()
    _outer_update(config, learner, tasks)
    _seeded()
    plain.update(episodes=mixed, **plain.update_kwargs({}))
    after_mixed = {k: t.detach().clone() for k, t in plain.float_state().items()}
    critic_adam = copy.deepcopy(plain._named_optimizers[f"{CRITIC_ID}_default_optimizer"]
                                .state_dict())
    if outer == "maml_dr" and weight > 0:
        for task, query in zip(tasks, queries):
            for optimizer in plain._named_optimizers.values():
                optimizer.param_groups[0]["lr"] = config.lr * weight  # RLlib resets it after
            with plain.shifted(task.delta), plain.critic_frozen():
                plain.update(episodes=query, **plain.update_kwargs({}))
    reached = plain.float_state()
    for key, t in learner.float_state().items():
        torch.testing.assert_close(t, reached[key], rtol=1e-5, atol=1e-6)
        if key[0] == CRITIC_ID:  # the critic learns at theta only, where tasks are mixed
            # (to the rounding of shifting by +delta and back; an Adam step is ~lr = 1e-3)
            torch.testing.assert_close(t, after_mixed[key], rtol=1e-6, atol=1e-6)
    moved = any(not torch.equal(t, after_mixed[k]) for k, t in reached.items())
    assert moved == (outer == "maml_dr" and weight > 0)  # the MAML term goes on past it
    assert {o.param_groups[0]["lr"] for o in learner._named_optimizers.values()} == {config.lr}
    adam = learner._named_optimizers[f"{CRITIC_ID}_default_optimizer"].state_dict()["state"]
    for index, state in critic_adam["state"].items():
        for name, value in state.items():
            torch.testing.assert_close(adam[index][name], value, rtol=0, atol=0)


@pytest.mark.parametrize("meta, message", [
    (dict(inner_updates=0), r"meta.inner_updates=0 is invalid"),
    (dict(tasks=0), r"meta.tasks=0 is invalid"),
    (dict(tasks=6, task_pool=5), r"meta.tasks=6 is invalid: allowed .*5"),
    (dict(support_steps=25), r"meta.support_steps=25 is invalid: allowed a multiple of "
                             r"num_envs_per_env_runner=2"),
    (dict(query_steps=1), r"meta.query_steps=1 is invalid"),
    (dict(query_steps=22), r"meta.query_steps=22 is invalid: allowed at least max_steps x "
                           r"num_envs_per_env_runner = 24"),
    (dict(outer="sgd"), r"meta.outer='sgd' is invalid: allowed one of \['maml', 'maml_dr', "
                        r"'reptile', 'multitask'\]"),
    (dict(inner_adam="warm"), r"meta.inner_adam='warm' is invalid"),
    (dict(maml_weight=-0.5), r"meta.maml_weight=-0.5 is invalid"),
    (dict(inner_lr=0), r"meta.inner_lr=0 is invalid"),
    (dict(task_envs=-1), r"meta.task_envs=-1 is invalid"),
    (dict(outer="maml", relabel_query=True), r"meta.relabel_query=True is invalid: allowed "
                                             r"false with outer='maml'"),
    (dict(num_env_runners=1), r"num_env_runners=1"),
])
def test_bad_meta_settings_fail_before_building(meta, message):
    with pytest.raises(ConfigError, match=message):
        meta_poca_config(ENV, **{"tasks": 2, "support_steps": 24, "query_steps": 24,
                                 "task_pool": 5, **TRAINING, **meta}).validate()


def test_a_restored_run_draws_the_tasks_the_uninterrupted_run_draws(ray_session, tmp_path,
                                                                    monkeypatch):
    """Iteration 2's tasks are the same whether the run went on or was saved after
    iteration 1 and restored into a new algorithm (what Tune does on resume)."""
    from rl_scan.algorithms.maml import meta_poca

    drawn: list[str] = []
    real = meta_poca.set_task

    def recording(env_runner, scenario):  # the real setter, noting what it set
        drawn.append(scenario)
        real(env_runner, scenario)

    monkeypatch.setattr(meta_poca, "set_task", recording)
    config = meta_poca_config(ENV, tasks=3, support_steps=24, query_steps=24, task_pool=50,
                              **{**TRAINING, "seed": 4})

    def second_iteration_tasks(algo) -> list[str]:
        drawn.clear()
        algo.train()
        return [s for s in drawn if s.startswith("train:")]

    straight = config.build_algo()
    straight.train()
    straight.save_to_path(tmp_path / "ckpt")
    expected = second_iteration_tasks(straight)
    straight.stop()
    restored = config.build_algo()
    restored.restore_from_path(tmp_path / "ckpt")
    assert second_iteration_tasks(restored) == expected and len(expected) == 3
    first = restored.meta_tasks_of(0)
    restored.stop()
    assert expected != first  # tasks change from one iteration to the next
