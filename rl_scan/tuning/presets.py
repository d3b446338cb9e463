"""Training budgets: ``smoke`` (seconds, tests), ``quick`` (minutes on 2 cores), ``paper``.

A preset fixes the budget and batch sizes; env settings stay in EnvConfig (a preset may
shorten episodes through ``env_overrides`` so that tiny budgets still finish episodes) and
an algorithm's own settings in its registry entry (``algorithms/registry.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rl_scan.algorithms.registry import DEFAULT_SAMPLER, SAMPLERS
from rl_scan.config import build_config, check_range, fail


@dataclass(frozen=True)
class TrainPreset:
    """Budget and optimisation settings of one training run."""

    total_env_steps: int
    """Stop after this many env steps (all robots act in one env step)."""
    train_batch_size: int
    """Env steps sampled per training iteration."""
    minibatch_size: int
    """Agent rows per SGD minibatch."""
    num_epochs: int = 3
    """Passes over each batch (paper: 3)."""
    lr: float = 3e-4
    num_env_runners: int = 0
    """Remote sampling actors (0 = sample in the training process)."""
    learner_cpus: int = 1
    """CPUs the training process reserves, and so its torch threads (the learner's). One
    per run lets a 2-core machine train two runs side by side; a lone run learns ~1.5x
    faster with 2 (docs/performance.md). Never more threads than reserved CPUs: a
    two-thread learner beside a busy core runs several times slower."""
    num_envs_per_env_runner: int = 4
    custom_resources: dict[str, float] = field(default_factory=dict)
    """Custom Ray resources each run's training process asks for, e.g. ``{"trial_slot": 1}``
    on a cluster whose nodes were started with ``--resources '{"trial_slot": 1}'``: pins
    runs to nodes that have them (docs/cluster.md)."""
    decay_schedules: bool = False
    """ML-Agents' linear decays over ``total_env_steps``: lr to ~0, beta to 1e-5 and (POCA)
    the clip range 0.2 -> 0.1 (RLlib's PPO keeps its clip range fixed)."""
    overlap_sampling: bool = False
    """Remote runners sample the next batch while the learner trains on this one (needs
    num_env_runners >= 1; one iteration of policy lag; rl_scan.algorithms.overlap)."""
    sampler: str = DEFAULT_SAMPLER
    """How env runners sample: ``fast`` (batched, the default) or ``rllib`` (RLlib's own
    runner, the reference)."""
    evaluation_interval: int = 5
    """Evaluate every N iterations (0 = never)."""
    evaluation_episodes: int = 3
    checkpoint_frequency: int = 5
    """Checkpoint every N iterations (and at the end)."""
    env_overrides: dict[str, Any] = field(default_factory=dict)
    """EnvConfig fields this preset changes (e.g. shorter episodes for smoke runs)."""
    def validate(self, prefix: str = "") -> None:
        check_range(prefix + "total_env_steps", self.total_env_steps, 1)
        check_range(prefix + "train_batch_size", self.train_batch_size, 1)
        check_range(prefix + "minibatch_size", self.minibatch_size, 1)
        check_range(prefix + "num_epochs", self.num_epochs, 1, 100)
        check_range(prefix + "lr", self.lr, 0.0, 1.0, lo_open=True)
        check_range(prefix + "num_env_runners", self.num_env_runners, 0, 1024)
        check_range(prefix + "learner_cpus", self.learner_cpus, 1, 1024)
        if self.overlap_sampling and self.num_env_runners < 1:
            fail(prefix + "overlap_sampling", True, "only with num_env_runners >= 1 (remote "
                 f"runners sample while the learner learns; num_env_runners="
                 f"{self.num_env_runners})")
        for name, amount in self.custom_resources.items():
            if name in ("CPU", "GPU", "memory") or not isinstance(amount, (int, float)) \
                    or amount <= 0:
                fail(prefix + "custom_resources", {name: amount},
                     "custom resource names (not CPU/GPU/memory) with amounts > 0")
        check_range(prefix + "num_envs_per_env_runner", self.num_envs_per_env_runner, 1, 256)
        if self.sampler not in SAMPLERS:
            fail(prefix + "sampler", self.sampler, f"one of {sorted(SAMPLERS)}")
        check_range(prefix + "evaluation_interval", self.evaluation_interval, 0)
        check_range(prefix + "evaluation_episodes", self.evaluation_episodes, 1)
        check_range(prefix + "checkpoint_frequency", self.checkpoint_frequency, 1)

    @property
    def iterations(self) -> int:
        return -(-self.total_env_steps // self.train_batch_size)


PRESETS: dict[str, dict[str, Any]] = {
    "smoke": dict(total_env_steps=800, train_batch_size=400, minibatch_size=256, num_epochs=1,
                  num_envs_per_env_runner=2, evaluation_interval=1, evaluation_episodes=1,
                  checkpoint_frequency=1, env_overrides={"max_steps": 50}),
    "quick": dict(total_env_steps=200_000, train_batch_size=4_000, minibatch_size=1_024,
                  num_epochs=3, num_envs_per_env_runner=4, evaluation_interval=5,
                  evaluation_episodes=3, checkpoint_frequency=5),
    "paper": dict(total_env_steps=8_000_000, train_batch_size=10_240, minibatch_size=1_024,
                  num_epochs=3, num_env_runners=2, num_envs_per_env_runner=4,
                  evaluation_interval=10, evaluation_episodes=10, checkpoint_frequency=10,
                  decay_schedules=True),
}


def get_preset(name: str, overrides: dict[str, Any] | None = None) -> TrainPreset:
    """A named preset with optional field overrides, validated."""
    if name not in PRESETS:
        fail("preset", name, f"one of {sorted(PRESETS)}")
    return build_config(TrainPreset, {**PRESETS[name], **(overrides or {})}, prefix="preset.")


@dataclass(frozen=True)
class Protocol:
    """Budgets of one meta-MRSS protocol preset (env steps per pre-training and per
    adaptation run, trained with ``train_preset``)."""

    train_preset: str
    pretrain_steps: int
    adapt_steps: int
    eval_interval: int
    eval_episodes: int = 10
    """Episodes per adaptation evaluation: steps to 80 % is read from them."""


PROTOCOLS = {  # the meta-MRSS experiment's budgets (`rl-scan experiment meta-mrss`)
    "smoke": Protocol("smoke", pretrain_steps=800, adapt_steps=800, eval_interval=1,
                      eval_episodes=1),
    "quick": Protocol("quick", pretrain_steps=100_000, adapt_steps=40_000, eval_interval=2),
    # budgets where methods separate that still run on 2 cores in one night: 18.6M env
    # steps over 69 runs, ~6 h with 2 runs at a time (issue 16)
    "long": Protocol("quick", pretrain_steps=1_000_000, adapt_steps=160_000,
                     eval_interval=4),
    "paper": Protocol("paper", pretrain_steps=8_000_000, adapt_steps=2_000_000,
                      eval_interval=10),
}
