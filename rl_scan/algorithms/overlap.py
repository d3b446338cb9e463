"""Sampling overlapped with learning: runners sample batch k+1 while the learner trains on k.

PPO's ``training_step`` samples, then learns, then syncs weights, so a process that samples
waits for the learner and the other way round. With ``overlap_sampling`` the remote env
runners are asked for the next batch before the learner starts on this one; the learner's
new weights reach them after that batch (Ray runs an actor's calls in submission order),
so every batch is learned one update after the weights that sampled it. PPO's ratio is
taken against the sampling policy's own log-probabilities, so the clip bounds the update
around the policy that acted (one iteration of policy lag, as APPO allows more of).

It needs remote env runners (``num_env_runners >= 1``): the learner's process does not
sample. Measured gains and when it pays are in docs/performance.md.
"""

from __future__ import annotations

import math
import time
from typing import Any

from ray.rllib.core import ALL_MODULES
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_MODULE_STEPS_TRAINED_LIFETIME,
    SYNCH_WORKER_WEIGHTS_TIMER,
    TIMERS,
)

SAMPLE_TAG = "overlapped_sample"


def _sample_with_metrics(runner, num_timesteps: int) -> tuple[list, Any]:
    return runner.sample(num_timesteps=num_timesteps), runner.get_metrics()


class OverlappedSamplingConfig:
    """AlgorithmConfig mixin: the ``overlap_sampling`` switch (off: PPO's own loop)."""

    overlap_sampling: bool = False


class OverlappedSampling:
    """Algorithm mixin for PPO-family algorithms (PPO, POCA): see the module doc."""

    _requested_runners: int = 0  # runners asked for a batch not yet collected

    def training_step(self) -> None:
        if not getattr(self.config, "overlap_sampling", False):
            return super().training_step()
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            if not self._requested_runners:  # first iteration, or after a restore
                self._request_batch()
            episodes, runner_metrics = self._collect_batch()
            self._request_batch()  # sampled while the learner works on `episodes`
        if not episodes:
            return None
        self.metrics.aggregate(runner_metrics, key=ENV_RUNNER_RESULTS)
        # From here on as PPO.training_step (RLlib 2.60).
        with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
            learner_results = self.learner_group.update(
                episodes=episodes,
                timesteps={
                    NUM_ENV_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
                        (ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME)),
                    NUM_MODULE_STEPS_TRAINED_LIFETIME: self.metrics.peek(
                        (LEARNER_RESULTS, ALL_MODULES, NUM_MODULE_STEPS_TRAINED_LIFETIME),
                        default=0),
                },
                num_epochs=self.config.num_epochs,
                minibatch_size=self.config.minibatch_size,
                shuffle_batch_per_epoch=self.config.shuffle_batch_per_epoch)
            self.metrics.aggregate(learner_results, key=LEARNER_RESULTS)
        with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
            # Queued behind the batch requested above: it samples with the old weights.
            self.env_runner_group.sync_weights(
                from_worker_or_learner_group=self.learner_group,
                policies=set(learner_results[0].keys()) - {ALL_MODULES},
                inference_only=True)
        return None

    def _request_batch(self) -> None:
        """Ask every healthy remote runner for its share of one training batch."""
        group = self.env_runner_group
        runners = group.num_healthy_remote_env_runners()
        if runners == 0:
            raise RuntimeError("overlap_sampling needs a healthy remote env runner; none left")
        share = math.ceil(self.config.total_train_batch_size / runners)
        self._requested_runners = group.foreach_env_runner_async(
            _sample_with_metrics, tag=SAMPLE_TAG, kwargs={"num_timesteps": share})

    def _collect_batch(self) -> tuple[list, list]:
        """Wait for the requested batch (a runner that dies drops its share)."""
        group, episodes, metrics = self.env_runner_group, [], []
        deadline = time.monotonic() + (self.config.sample_timeout_s or math.inf)
        while group.num_in_flight_async_reqs(tag=SAMPLE_TAG) and time.monotonic() < deadline:
            for _, (runner_episodes, runner_metrics) in group.fetch_ready_async_reqs(
                    tags=SAMPLE_TAG, timeout_seconds=1.0):
                episodes += runner_episodes
                metrics.append(runner_metrics)
        self._requested_runners = 0
        return episodes, metrics
