"""MetaPOCA's relabel_query: the update at theta takes the adapted actors' query episodes
as theta's own (their stored action distribution recomputed with theta)."""

from __future__ import annotations

import copy

import numpy as np
import torch
from meta_learners import make_tasks, meta_setup, outer_update, sample, seeded, state_copy

from rl_scan.algorithms.poca.modules import CRITIC_ID


def test_relabelled_episodes_carry_the_current_actors_distribution():
    """relabel_behaviour recomputes each agent step's action distribution with the
    learner's actors: episodes theta sampled keep theta's (the observations and module
    mapping are the ones the runner acted on); after the actors move, the stored
    distribution is the moved actors' while the log-probability stays the sampler's (the
    importance weight's denominator)."""
    from ray.rllib.core.columns import Columns

    config, runner, learner = meta_setup()
    episodes = sample(runner, "train:0")
    relabelled = copy.deepcopy(episodes)
    learner.relabel_behaviour(relabelled)
    for before, after in zip(episodes, relabelled):
        for aid, steps in before.agent_episodes.items():
            np.testing.assert_allclose(
                after.agent_episodes[aid].get_extra_model_outputs(Columns.ACTION_DIST_INPUTS),
                steps.get_extra_model_outputs(Columns.ACTION_DIST_INPUTS), atol=1e-5)
    with torch.no_grad():
        for mid in learner.module.keys():
            if mid != CRITIC_ID:
                learner.module[mid].log_std.add_(0.5)
    learner.relabel_behaviour(relabelled)
    for before, after in zip(episodes, relabelled):
        for aid, steps in before.agent_episodes.items():
            old = steps.get_extra_model_outputs(Columns.ACTION_DIST_INPUTS)
            new = after.agent_episodes[aid].get_extra_model_outputs(Columns.ACTION_DIST_INPUTS)
            half = old.shape[-1] // 2
            np.testing.assert_allclose(new[:, :half], old[:, :half], atol=1e-5)  # means
            np.testing.assert_allclose(new[:, half:], old[:, half:] + 0.5, atol=1e-5)
            actions = steps.get_actions()
            std = np.exp(old[:, half:])
            sampler_logp = (-0.5 * ((actions - old[:, :half]) / std) ** 2 - np.log(std)
                            - 0.5 * np.log(2 * np.pi)).sum(-1)
            np.testing.assert_allclose(
                after.agent_episodes[aid].get_extra_model_outputs(Columns.ACTION_LOGP),
                sampler_logp, rtol=1e-4, atol=1e-4)


def test_relabel_query_makes_the_update_at_theta_a_plain_update_on_relabelled_batches():
    """multitask + relabel_query: the update at theta equals a plain update on the same
    batches whose query half carries theta's action distribution; without it the query
    rows keep the adapted actors' (so the two differ)."""
    config, runner, learner = meta_setup(outer="multitask", relabel_query=True)
    tasks = make_tasks(learner, runner, adapted_query=True)
    plain = config.build_learner(env=None, spaces=runner.get_spaces())
    start = copy.deepcopy(learner.get_state(components=["rl_module", "optimizer"]))
    plain.set_state(start)
    query = copy.deepcopy([e for t in tasks for e in t.query])
    unlabelled = copy.deepcopy([e for t in tasks for e in t.support]) + copy.deepcopy(query)
    plain.relabel_behaviour(query)
    mixed = copy.deepcopy([e for t in tasks for e in t.support]) + query

    seeded()
    outer_update(config, learner, tasks)
    seeded()
    plain.update(episodes=mixed, **plain.update_kwargs({}))
    reached = state_copy(plain)
    for key, t in learner.float_state().items():
        torch.testing.assert_close(t, reached[key], rtol=1e-5, atol=1e-6)
    plain.set_state(start)
    seeded()
    plain.update(episodes=unlabelled, **plain.update_kwargs({}))
    assert max(float((t - reached[k]).abs().max())
               for k, t in plain.float_state().items()) > 1e-4


def test_query_importance_leaves_on_policy_rows_alone_and_weighs_relabelled_ones():
    """multitask + relabel_query + query_importance: with the query sampled by theta every
    weight is 1, so the update at theta is the relabel-only one; with the query sampled by
    the adapted actors theta'_i the weights differ from 1 and so does the update."""
    reached = {}
    for adapted in (False, True):
        for importance in (False, True):
            config, runner, learner = meta_setup(outer="multitask", relabel_query=True,
                                                 query_importance=importance)
            seeded()
            tasks = make_tasks(learner, runner, adapted_query=adapted)
            seeded()
            outer_update(config, learner, tasks)
            reached[adapted, importance] = state_copy(learner)

    def gap(a, b):
        return max(float((t - reached[b][k]).abs().max()) for k, t in reached[a].items())

    assert gap((False, False), (False, True)) < 1e-5
    assert gap((True, False), (True, True)) > 1e-4
