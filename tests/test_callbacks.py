"""The metrics callback: NaN guard and what it logs (no Ray cluster needed)."""

from __future__ import annotations

import math

import pytest

from rl_scan.algorithms.callbacks import NonFiniteLossError, ScanMetricsCallback


def test_non_finite_loss_stops_with_module_and_iteration():
    cb = ScanMetricsCallback()
    ok = {"training_iteration": 4, "learners": {"quad": {"total_loss": 1.5, "entropy": 2.0}}}
    cb.on_train_result(result=ok)
    bad = {"training_iteration": 5,
           "learners": {"wheeled": {"total_loss": 0.3}, "quad": {"policy_loss": math.nan}}}
    with pytest.raises(NonFiniteLossError, match=r"policy_loss=nan for module 'quad' at "
                                                 r"training iteration 5"):
        cb.on_train_result(result=bad)
    both = {"training_iteration": 6,  # several NaN losses: the first by name, every time
            "learners": {"quad": {"vf_loss_unclipped": math.nan, "policy_loss": math.nan}}}
    with pytest.raises(NonFiniteLossError, match=r"^policy_loss=nan for module 'quad'"):
        cb.on_train_result(result=both)


class _Episode:
    def __init__(self, infos):
        self._infos = infos

    def get_infos(self, index):
        assert index == -1
        return self._infos


class _Logger:
    def __init__(self):
        self.logged = {}

    def log_value(self, key, value, **kwargs):
        self.logged[key] = value


def test_episode_metrics_are_logged_and_unreached_steps_skipped():
    summary = {"coverage": 0.85, "steps_to_50": 40.0, "steps_to_95": math.nan, "success": 0.0}
    logger = _Logger()
    ScanMetricsCallback().on_episode_end(
        episode=_Episode({"quad_0": {"episode_metrics": summary}, "wheeled_0": {}}),
        metrics_logger=logger)
    assert logger.logged == {"scan/coverage": 0.85, "scan/reached_50": 1.0,
                             "scan/steps_to_50": 40.0, "scan/reached_95": 0.0,
                             "scan/success": 0.0}
