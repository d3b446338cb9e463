"""MetaPOCA's per-iteration diagnostics computed from the tasks' inner-update deltas."""

from __future__ import annotations

import math

import pytest
import torch

from rl_scan.algorithms.maml.meta_poca import delta_cosine


def test_delta_cosine_is_the_mean_over_task_pairs_of_the_parameters_cosine():
    keys = [("a", "w"), ("a", "b")]  # a return moment ("a", "m") is left out
    deltas = [{("a", "w"): torch.tensor([1.0, 0.0]), ("a", "b"): torch.tensor([0.0]),
               ("a", "m"): torch.tensor([5.0])},
              {("a", "w"): torch.tensor([1.0, 1.0]), ("a", "b"): torch.tensor([0.0]),
               ("a", "m"): torch.tensor([-5.0])},
              {("a", "w"): torch.tensor([0.0, 2.0]), ("a", "b"): torch.tensor([0.0]),
               ("a", "m"): torch.tensor([0.0])}]
    # pairs: 1/sqrt(2), 0, 1/sqrt(2) -> mean sqrt(2)/3
    assert delta_cosine(deltas, keys) == pytest.approx(2 ** 0.5 / 3)
    assert math.isnan(delta_cosine(deltas[:1], keys))
