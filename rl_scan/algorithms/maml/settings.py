"""MetaPOCA's own settings (the paper's Algorithm 1), kept out of the generic training preset."""

from __future__ import annotations

from dataclasses import dataclass

from rl_scan.config import check_range


@dataclass(frozen=True)
class MetaSettings:
    """Meta-learning settings of one MetaPOCA run (paper: tau = 10, K = 20, epoch 3)."""

    tasks: int = 10
    """Tasks (train scenarios) per meta-iteration (paper tau = 10)."""
    episodes: int = 20
    """Support episodes, and as many query episodes, per task (paper K = 20)."""
    inner_steps: int = 1
    """Inner (adaptation) steps per task."""
    inner_lr: float = 3e-4
    """Inner learning rate (Adam for first order, SGD for second order)."""
    order: int = 1
    """1 = first order with inner Adam (paper), 2 = second order with SGD."""
    meta_epochs: int = 3
    """Meta (outer) steps per meta-iteration on its query episodes (paper: 3)."""

    def validate(self, prefix: str = "") -> None:
        check_range(prefix + "tasks", self.tasks, 1)
        check_range(prefix + "episodes", self.episodes, 1)
        check_range(prefix + "inner_steps", self.inner_steps, 1)
        check_range(prefix + "inner_lr", self.inner_lr, 0.0, 1.0, lo_open=True)
        check_range(prefix + "order", self.order, 1, 2)
        check_range(prefix + "meta_epochs", self.meta_epochs, 1, 100)


# Smaller task batches for the short presets (the defaults are the paper's).
PRESET_SETTINGS = {"smoke": dict(tasks=2, episodes=1, inner_steps=1),
                   "quick": dict(tasks=4, episodes=2, inner_steps=2)}
