"""POCA's policy loss against hand-computed values: the clipped surrogate per action
dimension, the joint-ratio ablation, the importance weights of MetaPOCA's query rows, and
a policy module's whole loss on a tiny batch."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

from rl_scan.algorithms.poca.learner import POCATorchLearner
from rl_scan.algorithms.poca.losses import clipped_policy_loss, gaussian_entropy


def test_clipped_policy_loss_by_hand():
    # row 0: r = e^.5 = 1.65, A = +1 -> min(1.65, 1.2) = 1.2
    # row 1: r = e^-.5 = .607, A = -2 -> min(-1.213, .8 * -2 = -1.6) = -1.6
    # row 2 is masked out. loss = -(1.2 - 1.6) / 2 = 0.2
    logp = torch.tensor([[0.5], [-0.5], [9.0]])
    old = torch.zeros(3, 1)
    adv = torch.tensor([1.0, -2.0, 100.0])
    loss = clipped_policy_loss(logp, old, adv, 0.2, torch.tensor([1.0, 1.0, 0.0]))
    assert loss.item() == pytest.approx(0.2, abs=1e-6)


def test_ratio_is_clipped_per_action_dimension():
    # dim 0 ratio e^.5 -> clipped to 1.2; dim 1 ratio 1; A = 1: mean(1.2, 1.0) = 1.1
    loss = clipped_policy_loss(torch.tensor([[0.5, 0.0]]), torch.zeros(1, 2),
                               torch.tensor([1.0]), 0.2, torch.ones(1))
    assert loss.item() == pytest.approx(-1.1, abs=1e-6)


def test_full_policy_module_loss_on_a_tiny_batch():
    """compute_loss_for_module = clipped loss - beta * entropy, by hand."""
    log_std = torch.tensor([[0.0, math.log(2.0)]])
    # old mean 0, new mean 0.1 on dim 0; action (0.5, 0) ->
    # dim 0: logp_new - logp_old = -(.4^2 - .5^2)/2 = .045 -> r = e^.045 = 1.046 (< 1.2)
    # dim 1: same distribution -> r = 1.  A = 2 -> surrogate mean = (2*1.046 + 2) / 2
    fwd = {Columns.ACTION_DIST_INPUTS: torch.cat([torch.tensor([[0.1, 0.0]]), log_std], -1)}
    batch = {Columns.ACTION_DIST_INPUTS: torch.cat([torch.zeros(1, 2), log_std], -1),
             Columns.ACTIONS: torch.tensor([[0.5, 0.0]]),
             Columns.LOSS_MASK: torch.ones(1), Postprocessing.ADVANTAGES: torch.tensor([2.0])}
    beta = 0.005  # the critic's own loss is checked separately
    fake = SimpleNamespace(
        entropy_coeff_schedulers={"quad": SimpleNamespace(get_current_value=lambda: beta)},
        current_clip=lambda: 0.2,
        metrics=SimpleNamespace(log_dict=lambda *a, **k: None))
    loss = POCATorchLearner.compute_loss_for_module(
        fake, module_id="quad", config=SimpleNamespace(clip_param=0.2, value_clip=None),
        batch=batch,
        fwd_out=fwd)
    # ML-Agents' entropy: the mean over the two dimensions (sigma 1 and 2)
    entropy = (2 * 0.5 * (math.log(2 * math.pi) + 1) + math.log(2.0)) / 2
    expected = -(2 * math.exp(0.045) + 2) / 2 - beta * entropy
    assert loss.item() == pytest.approx(expected, abs=1e-5)
    assert gaussian_entropy(log_std).item() == pytest.approx(entropy, abs=1e-6)


def test_the_joint_ratio_ablation_clips_the_product_of_the_dimensions_ratios():
    from rl_scan.algorithms.poca.learner import actor_loss

    # means move .15 and .1 from 0 (sigma 1, action 1 in both dims), A = 1, beta = 0.
    log_std = torch.zeros(1, 2)
    fwd = {Columns.ACTION_DIST_INPUTS: torch.cat([torch.tensor([[0.15, 0.1]]), log_std], -1)}
    batch = {Columns.ACTION_DIST_INPUTS: torch.cat([torch.zeros(1, 2), log_std], -1),
             Columns.ACTIONS: torch.tensor([[1.0, 1.0]]), Columns.LOSS_MASK: torch.ones(1),
             Postprocessing.ADVANTAGES: torch.tensor([1.0])}
    # logp_new - logp_old = -((1 - m)^2 - 1) / 2 = m - m^2 / 2: .13875 and .095
    per_dim, _ = actor_loss(fwd, batch, 0.2, 0.0)
    joint, _ = actor_loss(fwd, batch, 0.2, 0.0, joint_ratio=True)
    assert per_dim.item() == pytest.approx(-(math.exp(0.13875) + math.exp(0.095)) / 2, abs=1e-5)
    assert joint.item() == pytest.approx(-1.2, abs=1e-6)  # e^.23375 = 1.263 > 1.2
    from rl_scan.algorithms.poca import POCAConfig
    from rl_scan.config import ConfigError

    with pytest.raises(ConfigError, match="policy_ratio='both' is invalid"):
        POCAConfig().poca(policy_ratio="both")


def test_importance_weights_scale_each_rows_clipped_surrogate_and_are_capped():
    """Decoupled PPO (MetaPOCA's query_importance): the ratio is clipped around the stored
    distribution (theta's after the relabel), each row weighed by pi_theta / pi_behaviour
    of its joint action, capped at 2; masked rows get 1 whatever their padding holds."""
    from rl_scan.algorithms.poca.learner import actor_loss
    from rl_scan.algorithms.poca.losses import IMPORTANCE_CAP

    # Both rows: stored N(0, 1) in 2 dims, action (1, 1), the new mean .15 and .1 (the
    # joint-ratio test's numbers): per-dim ratios e^.13875 and e^.095, unclipped at eps .3.
    log_std = torch.zeros(3, 2)
    mean = torch.tensor([[0.15, 0.1]] * 3)
    fwd = {Columns.ACTION_DIST_INPUTS: torch.cat([mean, log_std], -1)}
    stored_logp = 2 * (-0.5 - 0.5 * math.log(2 * math.pi))  # joint logp of (1, 1) under N(0, 1)
    # behaviour logps: row 0 sampled 0.5 nats likelier than theta would (w = e^-.5), row 1
    # 2 nats less likely (w = e^2 > cap: 2), row 2 masked (garbage padding)
    behaviour = torch.tensor([stored_logp + 0.5, stored_logp - 2.0, 1e9])
    batch = {Columns.ACTION_DIST_INPUTS: torch.cat([torch.zeros(3, 2), log_std], -1),
             Columns.ACTIONS: torch.ones(3, 2), Columns.ACTION_LOGP: behaviour,
             Columns.LOSS_MASK: torch.tensor([True, True, False]),
             Postprocessing.ADVANTAGES: torch.tensor([1.0, -1.0, 5.0])}
    loss, stats = actor_loss(fwd, batch, 0.3, 0.0, importance=True)
    r = (math.exp(0.13875) + math.exp(0.095)) / 2  # mean over dims of the unclipped surrogate
    expected = -(math.exp(-0.5) * r * 1.0 + IMPORTANCE_CAP * r * -1.0) / 2
    assert IMPORTANCE_CAP == 2.0
    assert loss.item() == pytest.approx(expected, abs=1e-5)
    assert stats["importance_weight"].item() == pytest.approx((math.exp(-0.5) + 2.0) / 2,
                                                              abs=1e-6)
    plain, _ = actor_loss(fwd, batch, 0.3, 0.0)
    assert plain.item() == pytest.approx(-(r - r) / 2, abs=1e-5)
