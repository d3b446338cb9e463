"""Start a run from another run's weights: adaptation and fine-tuning (meta-MRSS protocol).

``init_from_callback(checkpoint)`` is an ``on_algorithm_init`` callback that loads every
module the checkpoint and the new algorithm share (actors and POCA's critic) into the
learner and syncs the actors to all env runners. On a Tune restore the trial's own
checkpoint is loaded afterwards, so a resumed run continues from its own weights.
"""

from __future__ import annotations

import functools
from pathlib import Path

from rl_scan.algorithms.rollout import MODULES, resolve_checkpoint


def load_module_weights(checkpoint: str | Path, *, algorithm, **kwargs) -> list[str]:
    """Load the shared modules of ``checkpoint`` into ``algorithm``; returns their ids."""
    path = resolve_checkpoint(checkpoint)
    module_ids = [mid for mid in algorithm.learner_group._learner.module.keys()
                  if (path / MODULES / mid).is_dir()]
    if not module_ids:
        raise ValueError(f"checkpoint {str(path)!r} holds none of the modules "
                         f"{sorted(algorithm.learner_group._learner.module.keys())}")
    for mid in module_ids:
        algorithm.restore_from_path(path / MODULES / mid,
                                    component=f"{MODULES.as_posix()}/{mid}")
    for group in (algorithm.env_runner_group, algorithm.eval_env_runner_group):
        if group is not None:
            group.sync_weights(from_worker_or_learner_group=algorithm.learner_group,
                               inference_only=True)
    return module_ids


def init_from_callback(checkpoint: str | Path):
    """A picklable ``on_algorithm_init`` callback loading ``checkpoint``'s weights."""
    return functools.partial(load_module_weights, str(resolve_checkpoint(checkpoint)))
