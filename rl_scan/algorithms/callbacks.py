"""RLlib callback that logs the scanning metrics of every finished episode.

The env puts ``episode_metrics`` (coverage, success, steps to 50/80/95 %, collisions,
returns per kind; names in ``rl_scan.metrics``) into the last step's infos. They are
logged under ``results.scan_key(name)`` (``scan/<name>``) as windowed means, so they appear
in ``result["env_runners"]["scan/coverage"]`` (and under ``evaluation`` for eval runs).
``steps_to_X`` is logged only for episodes that reached X, beside ``scan/reached_X``.

Every training result also gets ``eval_coverage`` (top level): the coverage of the most
recent evaluation (NaN before the first). Tune ranks checkpoints by it, so a run keeps its
best checkpoints beside the latest one (checkpoints fall on evaluation iterations).

It also stops training on a non-finite loss: the iteration fails before its checkpoint
is written, so the last good checkpoint is the one a resume (or Tune's retry) uses.
"""

from __future__ import annotations

import math

from ray.rllib.callbacks.callbacks import RLlibCallback

from rl_scan import metrics as M
from rl_scan.results import EVAL_SCORE, evaluation_of, scan_key

WINDOW = 100


class NonFiniteLossError(FloatingPointError):
    """A learner produced a NaN/inf loss."""


def check_losses_finite(result: dict) -> None:
    """Raise NonFiniteLossError naming the module and iteration if any loss is not finite
    (the first such loss by name, so the message does not depend on logging order)."""
    for module_id, stats in sorted(result.get("learners", {}).items()):
        for key, value in sorted(stats.items()) if isinstance(stats, dict) else ():
            if "loss" in key and isinstance(value, (int, float)) and not math.isfinite(value):
                raise NonFiniteLossError(
                    f"{key}={value} for module {module_id!r} at training iteration "
                    f"{result.get('training_iteration')}: training stopped; the last good "
                    "checkpoint is kept (lower the learning rate or check the inputs)")


def episode_summary(episode) -> dict[str, float] | None:
    """The env's ``episode_metrics`` from a finished episode's last infos (None if cut)."""
    infos = episode.get_infos(-1)
    return next((i["episode_metrics"] for i in infos.values()
                 if isinstance(i, dict) and "episode_metrics" in i), None)


def episode_scenario(episode) -> str | None:
    """The scene a finished episode ran on (``train:*`` resolved to ``train:k``; None if cut)."""
    infos = episode.get_infos(-1)
    return next((i["scenario"] for i in infos.values()
                 if isinstance(i, dict) and "scenario" in i), None)


class ScanMetricsCallback(RLlibCallback):
    """Logs ``scan/*`` episode metrics from the env's final infos; stops on NaN losses."""

    def on_train_result(self, *, algorithm=None, metrics_logger=None, result: dict,
                        **kwargs) -> None:
        check_losses_finite(result)
        result[EVAL_SCORE] = float(evaluation_of(result).get(scan_key(M.COVERAGE), math.nan))

    def on_episode_end(self, *, episode, metrics_logger=None, **kwargs) -> None:
        if metrics_logger is None:
            return
        summary = episode_summary(episode)
        if summary is None:
            return
        for key, value in summary.items():
            if key in M.STEPS_TO.values():
                reached = not math.isnan(value)
                metrics_logger.log_value(scan_key(M.REACHED[key]),
                                         float(reached), reduce="mean", window=WINDOW)
                if not reached:
                    continue
            metrics_logger.log_value(scan_key(key), float(value), reduce="mean", window=WINDOW)
