"""MetaPOCA's inner update: an ordinary POCA update on the support batch (fresh Adam, the
meta optimizer's moments or its scale), leaving theta and the meta optimizer as they were.

Learners are built standalone (no Ray) on real episodes of the scanning env.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from meta_learners import ENV, TRAINING, meta_setup, sample, seeded, state_copy

from rl_scan.algorithms.poca.poca import poca_config


@pytest.mark.parametrize("lr_scale", [1.0, 4.0])  # inner_lr: MAML's alpha over beta
def test_the_inner_update_is_an_ordinary_poca_update_and_leaves_theta_as_it_was(lr_scale):
    _, runner, learner = meta_setup()
    support = sample(runner, "train:0")
    # one outer-style update first, so the meta optimizer has state to keep
    learner.update(episodes=copy.deepcopy(support), **learner.update_kwargs({}))
    theta = state_copy(learner)
    meta_adam = {n: copy.deepcopy(o.state_dict()) for n, o in learner._named_optimizers.items()}

    seeded()
    delta, adapted, _ = learner.adapt(support, {}, lr_scale=lr_scale)
    # a standalone POCA learner from the same weights, with a new Adam at POCA's lr x
    # lr_scale, on the same batch
    plain_config = poca_config(ENV, **{**TRAINING, "lr": TRAINING["lr"] * lr_scale})
    plain = plain_config.build_learner(env=None, spaces=runner.get_spaces())
    for mid in learner.module.keys():
        plain.module[mid].load_state_dict(learner.module[mid].state_dict())
    seeded()
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
    for key, t in state_copy(learner).items():
        assert torch.equal(t, theta[key]), key
    for name, opt in learner._named_optimizers.items():
        for p, st in opt.state_dict()["state"].items():
            for k, v in st.items():
                assert torch.equal(v, meta_adam[name]["state"][p][k]), (name, k)


def test_the_inner_update_may_continue_the_meta_adam_state_and_leaves_it_as_it_was():
    """inner_adam='meta': the inner steps start from a copy of the meta optimizer's moments
    (a standalone learner given the same state takes the same steps)."""
    config, runner, learner = meta_setup(inner_adam="meta")
    support = sample(runner, "train:0")
    learner.update(episodes=copy.deepcopy(support), **learner.update_kwargs({}))
    theta = state_copy(learner)
    plain = config.build_learner(env=None, spaces=runner.get_spaces())
    plain.set_state(copy.deepcopy(learner.get_state(components=["rl_module", "optimizer"])))
    meta_adam = {n: copy.deepcopy(o.state_dict()) for n, o in learner._named_optimizers.items()}
    seeded()
    delta, _, _ = learner.adapt(support, {}, adam="meta")
    seeded()
    plain.update(episodes=copy.deepcopy(support), **plain.update_kwargs({}))
    reached = {k: t.detach() for k, t in plain.float_state().items()}
    for key, d in delta.items():
        torch.testing.assert_close(theta[key] + d, reached[key], rtol=1e-5, atol=1e-6)
    seeded()
    fresh, _, _ = learner.adapt(support, {})
    assert any(not torch.allclose(fresh[k], delta[k]) for k in delta)
    seeded()
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



def test_two_scenarios_adapt_to_different_policies():
    _, runner, learner = meta_setup()
    delta_a, adapted_a, _ = learner.adapt(sample(runner, "train:0"), {})
    delta_b, adapted_b, _ = learner.adapt(sample(runner, "train:3"), {})
    probe = sample(runner, "train:0")  # the same observations for both adapted teams
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

