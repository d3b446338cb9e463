"""Tune checkpoints of our runs: which ones are kept, and the repair a resume may need."""

from __future__ import annotations

from pathlib import Path

from rl_scan import results as R
from rl_scan.tuning.presets import TrainPreset


def checkpoint_config(preset: TrainPreset):
    """Keep the 3 best checkpoints by evaluation coverage, and always the latest (resume).

    Without evaluation there is no score: the 3 latest are kept.
    """
    from ray import tune

    scored = preset.evaluation_interval > 0
    return tune.CheckpointConfig(num_to_keep=3,
                                 checkpoint_score_attribute=R.EVAL_SCORE if scored else None,
                                 checkpoint_score_order="max")


def recorded_checkpoints(tune_dir: Path) -> list[Path]:
    """Each trial's latest checkpoint as Tune's newest saved state names it (under
    ``tune_dir``, wherever the folder was when the state was written). Reads the state
    with Ray 2.60's private readers (docs/library-facts.md)."""
    from ray.tune.execution.experiment_state import _find_newest_experiment_checkpoint
    from ray.tune.trainable.metadata import _TrainingRunMetadata

    state_file = _find_newest_experiment_checkpoint(str(tune_dir))
    paths = []
    for _, run_metadata in (R.read_json(Path(state_file))["trial_data"] if state_file else []):
        latest = _TrainingRunMetadata.from_json_state(run_metadata) \
            .checkpoint_manager.latest_checkpoint_result
        if latest is not None:
            recorded = Path(latest.checkpoint.path)
            paths.append(tune_dir / recorded.parent.name / recorded.name)
    return paths


def restore_missing_checkpoints(tune_dir: Path) -> list[str]:
    """Make every trial's latest checkpoint, as Tune's saved state names it, exist again.

    Tune registers checkpoint k + 1, deletes the lowest-scored kept one (which can be k,
    the latest until then) and saves its state later; a driver killed in between leaves a
    state whose restore fails ("does not exist on storage anymore"). The trial's newest
    checkpoint on disk is copied to that path, so the run goes on from it (RLlib's counters
    come from the checkpoint's contents). Returns one line per repair.
    """
    import shutil

    repairs = []
    for missing in recorded_checkpoints(tune_dir):
        on_disk = sorted(missing.parent.glob("checkpoint_*"))
        if missing.exists() or not on_disk:
            continue
        shutil.copytree(on_disk[-1], missing)
        repairs.append(f"Tune's state names {missing.name} of {missing.parent.name}, deleted "
                       f"before the state was saved: resuming from {on_disk[-1].name}")
    return repairs
