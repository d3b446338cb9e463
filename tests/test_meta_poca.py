"""MetaPOCA's outer loop (first-order MAML-PPO over POCA): the query gradient is the one at
theta + delta, every sampled step is learned from, bad settings fail before building.

Learners are built standalone (no Ray) on real episodes of the scanning env.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from meta_learners import (
    ENV,
    TRAINING,
    make_tasks,
    meta_setup,
    outer_update,
    sample,
    seeded,
    state_copy,
)
from ray.rllib.utils.metrics.metrics_logger import MetricsLogger

from rl_scan.algorithms.maml import meta_poca_config
from rl_scan.algorithms.maml.meta_poca import MAML_TERM_PHASE
from rl_scan.algorithms.maml.random_streams import own_random_streams
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.config import ConfigError
from rl_scan.results import EV_VALUE, META_TERM_RESULTS


def _params(learner) -> dict:
    return {(mid, n): p for mid in learner.module.keys()
            for n, p in learner.module[mid].named_parameters()}


def test_a_step_inside_shifted_is_the_step_taken_at_theta_plus_delta():
    """The first-order MAML step: the gradient at theta + delta, applied to theta."""
    config, runner, learner = meta_setup()
    delta, _, _ = learner.adapt(sample(runner, "train:0"), {})
    query = sample(runner, "train:0")
    theta = state_copy(learner)
    # a second learner with the same weights moved to theta + delta (return statistics
    # frozen there too): what functional_call at theta + delta would compute
    loaded = config.build_learner(env=None, spaces=runner.get_spaces())
    for mid in learner.module.keys():
        loaded.module[mid].load_state_dict(learner.module[mid].state_dict())
    with torch.no_grad():
        for key, p in _params(loaded).items():
            p.add_(delta[key])
    loaded.module[CRITIC_ID].return_stats_frozen = True

    seeded()
    with learner.shifted(delta):
        learner.update(episodes=copy.deepcopy(query), **learner.update_kwargs({}))
    seeded()
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



def _module_rows(episodes, module_id: str) -> int:
    """Rows of a module in POCA's batch: each agent's steps plus the one bootstrap step
    RLlib's AddOneTsToEpisodesAndTruncate adds per episode chunk."""
    return sum(len(e.agent_episodes[a]) + 1 for e in episodes for a in e.agent_ids
               if e.agent_episodes[a].module_id == module_id)


def test_the_outer_update_takes_epochs_times_minibatches_steps_on_every_batch(monkeypatch):
    config, runner, learner = meta_setup()
    tasks = make_tasks(learner, runner)
    steps = []
    real = type(learner).apply_gradients
    monkeypatch.setattr(type(learner), "apply_gradients",
                        lambda self, grads: (steps.append(1), real(self, grads))[1])

    def minibatches(episodes) -> int:
        rows = max(_module_rows(episodes, mid) for mid in ("wheeled", "quad"))
        return math.ceil(config.num_epochs * rows / config.minibatch_size)

    expected = minibatches([e for t in tasks for e in t.support]) + sum(
        minibatches(t.query) for t in tasks)
    outer_update(config, learner, tasks)
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


def test_the_mean_maml_step_steps_once_per_minibatch_whatever_the_task_count(monkeypatch):
    config, runner, learner = meta_setup(maml_step="mean")
    tasks = make_tasks(learner, runner, scenarios=("train:0", "train:1", "train:2"))
    steps = []
    real = type(learner).apply_gradients
    monkeypatch.setattr(type(learner), "apply_gradients",
                        lambda self, grads: (steps.append(1), real(self, grads))[1])
    rows = max(_module_rows(tasks[0].query, mid) for mid in ("wheeled", "quad"))
    term = math.ceil(config.num_epochs * rows / config.minibatch_size)
    at_theta = math.ceil(config.num_epochs * max(
        _module_rows([e for t in tasks for e in t.support], mid) for mid in ("wheeled", "quad"))
        / config.minibatch_size)
    outer_update(config, learner, tasks)
    assert len(steps) == at_theta + term and term >= config.num_epochs


def test_the_mean_maml_step_applies_the_tasks_mean_gradient_at_theta_plus_delta_i(
        monkeypatch):
    """Reference: each task's gradient from an ordinary update inside shifted(delta_i)
    (critic frozen), recorded and not applied; one Adam step on their mean."""
    config, runner, learner = meta_setup(maml_step="mean")
    tasks = make_tasks(learner, runner, adapted_query=True)
    whole = dict(timesteps={}, num_epochs=1, minibatch_size=100_000,
                 shuffle_batch_per_epoch=False)
    recorded = []
    cls = type(learner)
    real_gradients, real_apply = cls.compute_gradients, cls.apply_gradients
    with monkeypatch.context() as patch:
        patch.setattr(cls, "compute_gradients", lambda self, losses, **kw: recorded.append(
            {k: g.detach().clone() for k, g in real_gradients(self, losses).items()
             if g is not None}) or recorded[-1])
        patch.setattr(cls, "apply_gradients", lambda self, grads: None)
        for task in tasks:
            with learner.shifted(task.delta), learner.critic_frozen():
                learner.update(episodes=copy.deepcopy(task.query), **whole)
    first, second = recorded
    assert first.keys() == second.keys()
    assert max(float((first[k] - second[k]).abs().max()) for k in first) > 1e-3
    saved = learner._snapshot()
    real_apply(learner, learner.postprocess_gradients(
        {k: (first[k] + second[k]) / 2 for k in first}))
    expected = state_copy(learner)
    learner._restore(saved)
    theta = state_copy(learner)
    learner.mean_shifted_update([(copy.deepcopy(t.query), t.delta) for t in tasks], **whole)
    moved = 0
    for key, t in state_copy(learner).items():
        # Adam steps are ~lr = 1e-3 per weight; threaded matmuls leave ~1e-6 of roundoff
        torch.testing.assert_close(t, expected[key], rtol=1e-4, atol=1e-5)
        moved += bool((t - theta[key]).abs().max() > 0)
    assert moved > 10
    critic = [k for k in theta if k[0] == CRITIC_ID]
    after = state_copy(learner)  # the critic takes no step (only the shift's roundoff)
    assert critic and all(torch.allclose(after[k], theta[k], atol=1e-6) for k in critic)


def test_reptile_moves_theta_by_the_mean_task_delta():
    config, runner, learner = meta_setup(outer="reptile", reptile_lr=0.5)
    theta = state_copy(learner)
    tasks = make_tasks(learner, runner)
    with own_random_streams(config.seed, 0, MAML_TERM_PHASE, 0):  # the outer update's
        further = [learner.adapt(t.query, {}, 1, start=t.delta)[0] for t in tasks]

    outer_update(config, learner, tasks)
    for key, t in state_copy(learner).items():
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
    config, runner, learner = meta_setup(outer=outer, maml_weight=weight)
    tasks = make_tasks(learner, runner)
    plain = config.build_learner(env=None, spaces=runner.get_spaces())
    plain.set_state(copy.deepcopy(learner.get_state(components=["rl_module", "optimizer"])))
    mixed = copy.deepcopy([e for t in tasks for e in t.support]
                          + [e for t in tasks for e in t.query])
    queries = copy.deepcopy([t.query for t in tasks])

    seeded()
    outer_update(config, learner, tasks)
    seeded()
    plain.update(episodes=mixed, **plain.update_kwargs({}))
    after_mixed = {k: t.detach().clone() for k, t in plain.float_state().items()}
    critic_adam = copy.deepcopy(plain._named_optimizers[f"{CRITIC_ID}_default_optimizer"]
                                .state_dict())
    if outer == "maml_dr" and weight > 0:
        with own_random_streams(config.seed, 0, MAML_TERM_PHASE, 0):  # the term's streams
            for task, query in zip(tasks, queries):
                for optimizer in plain._named_optimizers.values():
                    optimizer.param_groups[0]["lr"] = config.lr * weight  # RLlib resets it
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
                           r"num_envs_per_env_runner=2 = 24"),
    (dict(sampling="pooled"), r"meta.sampling='pooled' is invalid: allowed one of "
                              r"\['per_task', 'shared'\]"),
    (dict(sampling="shared", support_steps=46), r"meta.support_steps=46 is invalid: allowed "
                                                r"at least 2 x max_steps x "
                                                r"num_envs_per_env_runner=2 = 48"),
    (dict(sampling="shared", support_steps=48, tasks=3), r"meta.tasks=3 is invalid: allowed "
                                                         r"at most num_envs_per_env_runner=2"),
    (dict(sampling="shared", support_steps=48, query_steps=11),
     r"meta.query_steps=11 is invalid: allowed at least max_steps x the side runner's 1 env"),
    (dict(maml_step="sum"), r"meta.maml_step='sum' is invalid: allowed one of "
                            r"\['per_task', 'mean'\]"),
    (dict(outer="multitask", maml_step="mean"), r"meta.maml_step='mean' is invalid: "
                                                r"allowed 'per_task' with outer='multitask'"),
    (dict(outer="sgd"), r"meta.outer='sgd' is invalid: allowed one of \['maml', 'maml_dr', "
                        r"'reptile', 'multitask'\]"),
    (dict(inner_adam="warm"), r"meta.inner_adam='warm' is invalid"),
    (dict(maml_weight=-0.5), r"meta.maml_weight=-0.5 is invalid"),
    (dict(inner_lr=0), r"meta.inner_lr=0 is invalid"),
    (dict(task_envs=-1), r"meta.task_envs=-1 is invalid"),
    (dict(outer="maml", relabel_query=True), r"meta.relabel_query=True is invalid: allowed "
                                             r"false with outer='maml'"),
    (dict(outer="maml_dr", query_importance=True), r"meta.query_importance=True is invalid: "
                                                   r"allowed false unless relabel_query=true"),
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
