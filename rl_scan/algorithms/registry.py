"""The algorithm registry: name -> config builder and the algorithm's own settings.

Every entry's builder is called the same way by the run driver:
``builder(env_config, train_batch_size=..., minibatch_size=..., num_epochs=..., lr=...,
num_env_runners=..., num_envs_per_env_runner=..., evaluation_interval=...,
evaluation_episodes=..., seed=..., sampler=..., **settings, **algo_kwargs)`` and returns an RLlib
``AlgorithmConfig``. Adding an algorithm is one entry here. Builders are imported on
first use, so reading the registry (``--help``) does not import Ray.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rl_scan.config import build_config, fail, to_dict


@dataclass(frozen=True)
class AlgorithmEntry:
    """One trainable algorithm of ``rl-scan train --algo``."""

    name: str
    summary: str
    builder: str
    """``module:function`` returning the AlgorithmConfig."""
    settings: type | None = None
    """The algorithm's own settings dataclass (its fields become builder keywords)."""
    preset_settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Preset name -> settings that preset changes."""
    local_sampling: bool = False
    """Samples on the training process only: runs use no remote env runners."""

    def load_builder(self) -> Callable[..., Any]:
        module, func = self.builder.split(":")
        return getattr(importlib.import_module(module), func)

    def make_settings(self, preset: str, overrides: dict[str, Any] | None = None) -> Any:
        """The settings of a run on ``preset`` (None for an algorithm without any)."""
        if self.settings is None:
            if overrides:
                fail("algo_settings", overrides, f"none: {self.name} has no own settings")
            return None
        values = {**self.preset_settings.get(preset, {}), **(overrides or {})}
        return build_config(self.settings, values, prefix=f"{self.name}.")


def _meta_entry() -> AlgorithmEntry:
    from rl_scan.algorithms.maml.settings import PRESET_SETTINGS, MetaSettings

    return AlgorithmEntry(
        "meta-poca", "MetaPOCA: MAML over POCA (meta-MRSS, the paper's Algorithm 1)",
        "rl_scan.algorithms.maml:meta_poca_config", settings=MetaSettings,
        preset_settings=PRESET_SETTINGS, local_sampling=True)


SAMPLERS = {
    "fast": "batched sampling of all of a runner's worlds (rl_scan.algorithms.fast_runner)",
    "rllib": "RLlib's own MultiAgentEnvRunner (the reference)",
}
"""How env runners sample (``--sampler``); ``fast`` is the default."""
DEFAULT_SAMPLER = "fast"


def check_sampler(name: str) -> str:
    if name not in SAMPLERS:
        fail("sampler", name, f"one of {sorted(SAMPLERS)}")
    return name


ALGORITHMS: dict[str, AlgorithmEntry] = {e.name: e for e in (
    AlgorithmEntry("poca", "MA-POCA: centralized counterfactual critic, actors per robot kind",
                   "rl_scan.algorithms.poca:poca_config"),
    AlgorithmEntry("ppo", "RLlib's PPO on the same actor modules (the baseline)",
                   "rl_scan.algorithms.ppo:ppo_config"),
    _meta_entry(),
)}


def get_algorithm(name: str) -> AlgorithmEntry:
    if name not in ALGORITHMS:
        fail("algo", name, f"one of {sorted(ALGORITHMS)}")
    return ALGORITHMS[name]


def settings_kwargs(settings: Any) -> dict[str, Any]:
    """Builder keywords of an algorithm's settings object ({} for None)."""
    return to_dict(settings) if settings is not None else {}
