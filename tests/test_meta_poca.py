"""MetaPOCA (MAML over POCA): inner step math, meta gradients, both orders, 2.60 bug fix.

Learners are built standalone (no Ray) on real episodes of the scanning env.
"""

from __future__ import annotations

import copy

import pytest
import torch
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

from rl_scan.algorithms.maml import meta_poca_config
from rl_scan.algorithms.maml.meta_poca import set_task
from rl_scan.algorithms.poca.modules import CRITIC_ID
from rl_scan.config import ConfigError

LR = 1e-3


def _setup(order: int, inner_steps: int = 1, meta_epochs: int = 1):
    config = meta_poca_config({"max_steps": 12}, tasks=2, episodes=1, inner_steps=inner_steps,
                              inner_lr=LR, order=order, meta_epochs=meta_epochs, task_pool=5,
                              num_envs_per_env_runner=1, seed=0)
    runner = MultiAgentEnvRunner(config=config)
    learner = config.build_learner(env=None, spaces=runner.get_spaces())
    return config, runner, learner


def _episodes(runner, scenario: str):
    set_task(runner, scenario)
    return runner.sample(num_episodes=1)


def _params(learner):
    return {mid: {n: p.detach().clone() for n, p in learner.module[mid].named_parameters()}
            for mid in learner.module.keys()}


def _support_gradients(learner, support):
    """POCA's support-loss gradient at the meta parameters, per module (reference)."""
    inner = learner.inner
    params = {mid: {n: p.detach().clone().requires_grad_() for n, p in ps.items()}
              for mid, ps in _params(learner).items()}
    batch = inner._learner_connector(rl_module=learner.module, batch={},
                                     episodes=copy.deepcopy(support), shared_data={})
    batch = {m: b for m, b in batch.items() if m in learner.module.keys()}
    fwd = inner._make_functional_call(params, batch)
    loss = sum(inner.compute_losses(fwd_out=fwd, batch=batch).values())
    flat = [(m, n) for m, ps in params.items() for n in ps]
    grads = torch.autograd.grad(loss, [params[m][n] for m, n in flat], allow_unused=True)
    return {(m, n): g for (m, n), g in zip(flat, grads)}


def test_first_order_inner_step_is_one_adam_step_and_tasks_adapt_differently():
    _, runner, learner = _setup(order=1)
    theta = _params(learner)
    support_a = _episodes(runner, "train:0")
    support_b = _episodes(runner, "train:1")
    grads = _support_gradients(learner, support_a)
    adapted_a = learner.adapt(support_a)
    adapted_b = learner.adapt(support_b)
    # Adam's first step is lr * g / (|g| + eps): lr * sign(g) wherever |g| >> eps
    for (mid, name), g in grads.items():
        if g is None:
            continue
        step = theta[mid][name] - adapted_a[mid][name]
        big = g.abs() > 1e-4
        torch.testing.assert_close(step[big], LR * torch.sign(g[big]), rtol=1e-3, atol=1e-7)
    # the meta parameters themselves are untouched, and two scenarios adapt differently
    for mid, ps in _params(learner).items():
        for n, p in ps.items():
            assert torch.equal(p, theta[mid][n])
    for mid in ("wheeled", "quad", CRITIC_ID):
        assert any(not torch.allclose(adapted_a[mid][n], adapted_b[mid][n])
                   for n in adapted_a[mid]), mid


def test_second_order_inner_step_is_sgd_and_gradients_map_to_their_own_modules():
    """Fails without the 2.60 workaround: the stock compute_gradients gives every module
    the first module's gradients (different shapes: error; same shapes: silent)."""
    _, runner, learner = _setup(order=2)
    theta = _params(learner)
    support = _episodes(runner, "train:0")
    grads = _support_gradients(learner, support)
    adapted = learner.adapt(support)
    checked = 0
    for (mid, name), g in grads.items():
        if g is None:
            continue
        torch.testing.assert_close(adapted[mid][name], theta[mid][name] - LR * g,
                                   rtol=1e-4, atol=1e-6)
        checked += 1
    assert checked > 30  # every module's parameters, critic included


@pytest.mark.parametrize("order", [1, 2])
def test_meta_update_moves_actors_and_critic(order):
    _, runner, learner = _setup(order=order, inner_steps=2)
    theta = _params(learner)
    tasks = []
    for scenario in ("train:0", "train:1"):
        set_task(runner, scenario)
        support = runner.sample(num_episodes=1)
        adapted = learner.adapt(support)
        for mid, sd in learner.adapted_state(adapted).items():
            runner.module[mid].load_state_dict(sd)
        query = runner.sample(num_episodes=1)
        tasks.append({"support": support, "query": query, "adapted": adapted})
    results = learner.meta_update(tasks)
    assert results["meta/grad_norm"] > 0
    for mid in ("wheeled", "quad", CRITIC_ID):
        moved = [n for n, p in learner.module[mid].named_parameters()
                 if not torch.equal(p.detach(), theta[mid][n])]
        assert len(moved) == len(theta[mid]), (mid, len(moved), len(theta[mid]))


def _query_gradient_reference(learner, support, query, adapted):
    """POCA's query-loss gradient at ``adapted``, keyed by (module, parameter name)."""
    from rl_scan.algorithms.maml.learners import QUERY, poca_functional_forward, poca_losses

    params = {mid: {n: p.clone().requires_grad_() for n, p in ps.items()}
              for mid, ps in adapted.items()}
    batch = learner._learner_connector(rl_module=learner.module, batch={},
                                       episodes=copy.deepcopy(query), shared_data={})
    batch = {m: b for m, b in batch.items() if m in learner.module.keys()}
    steps = learner.module[CRITIC_ID].minibatches[QUERY].steps
    losses, _ = poca_losses(learner.module, learner.config,
                            poca_functional_forward(learner.module, params, batch, QUERY,
                                                    steps), batch, QUERY, steps)
    sum(losses.values()).backward()
    return {(m, n): p.grad for m, ps in params.items() for n, p in ps.items()}


def test_first_order_meta_gradient_is_the_query_gradient_at_the_adapted_parameters():
    _, runner, learner = _setup(order=1)
    support = _episodes(runner, "train:2")
    adapted = learner.adapt(support)
    for mid, sd in learner.adapted_state(adapted).items():
        runner.module[mid].load_state_dict(sd)
    query = runner.sample(num_episodes=1)
    reference = _query_gradient_reference(learner, support, query, adapted)
    # capture the gradient the meta step applies
    applied = {}
    original = learner.apply_gradients

    def spy(gradients):
        applied.update({p: g.clone() for p, g in gradients.items()})
        original(gradients)

    learner.apply_gradients = spy
    learner.config._is_frozen = False
    learner.meta_update([{"support": support, "query": query, "adapted": adapted}])
    real = {p: (mid, n) for mid in learner.module.keys()
            for n, p in learner.module[mid].named_parameters()}
    for p, g in applied.items():
        ref = reference[real[p]]
        torch.testing.assert_close(g, ref if ref is not None else torch.zeros_like(g),
                                   rtol=1e-4, atol=1e-6)


def test_later_meta_epochs_re_adapt_from_the_updated_meta_parameters():
    """Epoch 2's meta gradient is the query gradient at adapt(theta_1, support), where
    theta_1 are the meta parameters after epoch 1's step (not the first adaptation)."""
    _, runner, learner = _setup(order=1, meta_epochs=2)
    support = _episodes(runner, "train:2")
    adapted = learner.adapt(support)
    for mid, sd in learner.adapted_state(adapted).items():
        runner.module[mid].load_state_dict(sd)
    query = runner.sample(num_episodes=1)
    calls, original = [], learner.apply_gradients

    def spy(gradients):  # the parameters before each step, and the step's gradient
        calls.append((_params(learner), {p: g.clone() for p, g in gradients.items()}))
        original(gradients)

    learner.apply_gradients = spy
    learner.meta_update([{"support": support, "query": query, "adapted": adapted}])
    assert len(calls) == 2
    theta_1, applied = calls[1]
    theta_0 = calls[0][0]
    assert any(not torch.equal(theta_1[m][n], theta_0[m][n])  # the first step moved them
               for m in theta_0 for n in theta_0[m])
    with torch.no_grad():  # rebuild theta_1 and adapt from it as the learner should have
        for mid in learner.module.keys():
            for n, p in learner.module[mid].named_parameters():
                p.copy_(theta_1[mid][n])
    reference = _query_gradient_reference(learner, support, query, learner.adapt(support))
    stale = _query_gradient_reference(learner, support, query, adapted)
    real = {p: (mid, n) for mid in learner.module.keys()
            for n, p in learner.module[mid].named_parameters()}
    differs = 0
    for p, g in applied.items():
        key = real[p]
        ref = reference[key] if reference[key] is not None else torch.zeros_like(g)
        torch.testing.assert_close(g, ref, rtol=1e-4, atol=1e-6)
        if stale[key] is not None and not torch.allclose(stale[key], ref):
            differs += 1
    assert differs > 0  # re-adapting matters: the stale adaptation gives other gradients


def test_bad_meta_settings_fail_before_building():
    with pytest.raises(ConfigError, match="meta.order"):
        meta_poca_config({}, tasks=2, episodes=1, order=3).validate()
    with pytest.raises(ConfigError, match="meta.tasks"):
        meta_poca_config({}, tasks=0, episodes=1).validate()
    with pytest.raises(ConfigError, match="meta.epochs"):
        meta_poca_config({}, tasks=1, episodes=1, meta_epochs=0).validate()
    with pytest.raises(ConfigError, match=r"meta.tasks=6 is invalid: allowed .*5"):
        meta_poca_config({}, tasks=6, episodes=1, task_pool=5).validate()
    with pytest.raises(ConfigError, match="num_env_runners"):
        meta_poca_config({}, tasks=1, episodes=1, num_env_runners=1).validate()


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
    config = meta_poca_config({"max_steps": 12}, tasks=3, episodes=1, meta_epochs=1,
                              task_pool=50, num_envs_per_env_runner=1, seed=4)

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
