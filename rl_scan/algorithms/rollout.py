"""Play episodes with the trained actor modules of a checkpoint (no Ray needed).

Works for every rl-scan algorithm: their checkpoints keep one actor module per robot kind
under ``learner_group/learner/rl_module/<kind>`` (learner-only modules such as POCA's
critic are skipped). A checkpoint can be given as the checkpoint folder, a trial folder or
a run folder (the newest checkpoint is used); the run's env config comes from its run
folder's RUN_FILE.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from rl_scan import results as R
from rl_scan.config import ConfigError
from rl_scan.envs.observations import kind_of
from rl_scan.envs.sim.robots import KINDS

MODULES = Path("learner_group") / "learner" / "rl_module"


def resolve_checkpoint(path: str | Path) -> Path:
    """The checkpoint folder for a checkpoint, trial or run folder (newest checkpoint).

    Absolute: RLlib's ``from_checkpoint`` reads relative paths as malformed URIs.
    """
    path = Path(path).resolve()
    if (path / MODULES).is_dir():
        return path
    if R.is_run_folder(path) and R.tune_trial_dir(path).is_dir():
        path = R.tune_trial_dir(path)
    found = sorted(path.glob("**/checkpoint_*/"), key=lambda p: (p.stat().st_mtime, p.name))
    found = [p for p in found if (p / MODULES).is_dir()]
    if not found:
        raise ConfigError(f"checkpoint={str(path)!r} is invalid: allowed a checkpoint folder "
                          "or a run/trial folder that contains one")
    return found[-1]


def best_checkpoint(path: str | Path) -> tuple[Path, dict[str, float]]:
    """The kept checkpoint of a run (or trial, or study) folder with the highest evaluation
    coverage.

    Scores are the evaluations Tune recorded with each checkpoint (``EVAL_SCORE``).
    Returns the checkpoint folder and {training_iteration, env_steps, eval_coverage}.
    """
    from ray.tune import ExperimentAnalysis

    path = Path(path).resolve()
    if R.is_run_folder(path):
        path = R.tune_trial_dir(path)
    experiment = next((p for p in (path / R.TUNE_DIR, path, path.parent)
                       if any(p.glob("experiment_state-*.json"))), None)
    if experiment is None:
        raise ConfigError(f"checkpoint={str(path)!r} is invalid: --best needs a run or trial "
                          "folder written by Tune (rl-scan train, ablate, meta-mrss)")
    candidates = []
    for trial in ExperimentAnalysis(str(experiment)).trials:
        for kept in trial.run_metadata.checkpoint_manager.best_checkpoint_results:
            folder = Path(kept.checkpoint.path)
            if path not in (experiment, path / R.TUNE_DIR) and path not in folder.parents:
                continue  # another trial of the same study
            m = kept.metrics
            score = m.get(R.EVAL_SCORE)
            if score is not None and score == score and (folder / MODULES).is_dir():
                candidates.append((float(score), folder, m))
    if not candidates:
        raise ConfigError(f"checkpoint={str(path)!r} is invalid: no kept checkpoint there "
                          "carries an evaluation score")
    score, folder, m = max(candidates, key=lambda c: (c[0], c[2].get(R.ITERATION, 0)))
    return folder, {R.ITERATION: int(m.get(R.ITERATION, 0)),
                    "env_steps": int(m.get(R.ENV_STEPS, 0)), R.EVAL_SCORE: score}


def run_env_config(checkpoint: Path) -> dict[str, Any]:
    """The env config recorded for the run a checkpoint belongs to ({} if none is)."""
    return R.run_meta_of(checkpoint).get("env_config", {})


def load_actors(checkpoint: Path) -> dict[str, Any]:
    """The actor RLModules of a checkpoint, by robot kind."""
    from ray.rllib.core.rl_module.rl_module import RLModule

    root = checkpoint / MODULES
    return {kind: RLModule.from_checkpoint(root / kind) for kind in KINDS
            if (root / kind).is_dir()}


class PolicyTeam:
    """A team acting with trained modules: sampled actions, or the mean if not ``explore``."""

    def __init__(self, modules: dict[str, Any], explore: bool = True):
        from ray.rllib.core.columns import Columns

        self.modules, self.explore, self._obs_key = modules, explore, Columns.OBS
        self._dist_key = Columns.ACTION_DIST_INPUTS

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        actions: dict[str, np.ndarray] = {}
        for kind, module in self.modules.items():
            aids = [a for a in obs if kind_of(a) == kind]
            if not aids:
                continue
            batch = torch.as_tensor(np.stack([obs[a] for a in aids]))
            out = module.forward_inference({self._obs_key: batch})
            dist = module.get_inference_action_dist_cls().from_logits(out[self._dist_key])
            if not self.explore:
                dist = dist.to_deterministic()
            act = np.clip(dist.sample().numpy(), -1.0, 1.0)
            actions.update(zip(aids, act))
        missing = sorted(kind_of(a) for a in obs if a not in actions)
        if missing:
            raise ConfigError(f"the checkpoint has no policy for robot kind {missing[0]!r}: "
                              f"it has {sorted(self.modules)}")
        return actions
