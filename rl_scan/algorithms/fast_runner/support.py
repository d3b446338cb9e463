"""What the fast sampler supports: checked when a config selects it (before Ray starts) and
again when the runner is built, so that an unsupported setup fails with the fix in the
message instead of sampling something different from RLlib's runner."""

from __future__ import annotations

from typing import Any

from ray.rllib.callbacks.callbacks import RLlibCallback
from ray.rllib.utils import force_list

from rl_scan.config import fail
from rl_scan.envs.rllib_env import ScanMultiAgentEnv

# Episodes are built in bulk at the end of sample(): there is no episode object to hand
# to a callback before that, so only on_episode_end (and on_sample_end) are made.
PER_STEP_CALLBACKS = ("on_episode_created", "on_episode_start", "on_episode_step")


def unsupported_reason(config: Any) -> str | None:
    """Why the fast sampler cannot run ``config`` (None if it can)."""
    env = config.env
    if not (isinstance(env, type) and issubclass(env, ScanMultiAgentEnv)):
        return f"env={env!r}: it steps ScanMultiAgentEnv worlds only"
    for name in PER_STEP_CALLBACKS:
        if getattr(config, f"callbacks_{name}", None):
            return f"callbacks({name}=...): it makes on_episode_end callbacks only"
        for cls in force_list(config.callbacks_class):
            if getattr(cls, name) is not getattr(RLlibCallback, name):
                return f"{cls.__name__}.{name}: it makes on_episode_end callbacks only"
    if (config._env_to_module_connector is not None
            or config._module_to_env_connector is not None
            or not config.add_default_connectors_to_env_to_module_pipeline
            or not config.add_default_connectors_to_module_to_env_pipeline):
        return "env_to_module/module_to_env connectors: it runs RLlib's default ones only"
    if config.restart_failed_sub_environments:
        return "restart_failed_sub_environments=True: an env error ends its sample() call"
    return None


def check_fast_sampler(config: Any) -> None:
    """Raise a ConfigError naming what the fast sampler does not support in ``config``."""
    reason = unsupported_reason(config)
    if reason is not None:
        fail("sampler", "fast", f"'rllib' for this config ({reason})")
