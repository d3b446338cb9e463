"""``rl-scan ablate``: the studies of ``rl_scan.studies`` as Ray Tune studies searched by Optuna.

Each trial is a run of the one run driver (``driver.train_run``) with evaluation and
checkpoints. Grid studies run the full grid of condition x seed (Optuna's
``GridSampler``); search studies sample with TPE. The study folder (layout in
``rl_scan.results``) holds the Optuna study in SQLite (readable by optuna-dashboard, as
the command prints). ``resume=True`` continues an
interrupted study: finished trials are kept, unfinished ones continue from their last
checkpoint.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rl_scan import results as R
from rl_scan.config import check_range, fail
from rl_scan.studies import Study, get_study
from rl_scan.tuning.checkpoints import checkpoint_config, restore_missing_checkpoints
from rl_scan.tuning.driver import (
    RunProgress,
    git_commit,
    make_run_spec,
    required_cpus,
    train_run,
    trial_resources,
)
from rl_scan.tuning.launch import (
    check_output_folder,
    check_resources,
    init_ray,
    lock_output_folder,
)


def split_conditions(text: str, known: Sequence[str]) -> list[str]:
    """``text`` split at commas, rejoining neighbours that make a known condition
    ("2,2,0,4" -> ["2,2", "0,4"] for the team study)."""
    parts, out, i = [p for p in text.split(",") if p], [], 0
    while i < len(parts):
        j = next((j for j in range(len(parts), i, -1) if ",".join(parts[i:j]) in known), i + 1)
        out.append(",".join(parts[i:j]))
        i = j
    return out


def resumable_optuna_search(**kwargs):
    """Ray's OptunaSearch, leaving an Optuna trial alone once Optuna has it finished.

    A driver killed after Optuna recorded a trial COMPLETE but before Tune saved its own
    state makes the resumed Tune run that trial again (to its end, from its last
    checkpoint); OptunaSearch would then raise UpdateFinishedTrialError and stop the study.
    A trial resumed from a checkpoint repeats the iterations after it: Optuna keeps the
    first value of a step (and warns on each repeat), so repeats are not reported.
    """
    from ray.tune.result import TRAINING_ITERATION
    from ray.tune.search.optuna import OptunaSearch

    class ResumableOptunaSearch(OptunaSearch):
        def _stored(self, trial_id: str):
            """Optuna's stored copy of the trial, None if Optuna has not seen it."""
            ot_trial = self._ot_trials.get(trial_id)
            return ot_trial and ot_trial.storage.get_trial(ot_trial._trial_id)

        def _finished_in_optuna(self, trial_id: str) -> bool:
            stored = self._stored(trial_id)
            return stored is not None and stored.state.is_finished()

        def on_trial_result(self, trial_id, result):
            stored = self._stored(trial_id)
            if stored is not None and (stored.state.is_finished() or result.get(
                    TRAINING_ITERATION) in stored.intermediate_values):
                return
            super().on_trial_result(trial_id, result)

        def on_trial_complete(self, trial_id, result=None, error=False):
            if not self._finished_in_optuna(trial_id):
                super().on_trial_complete(trial_id, result, error)

    return ResumableOptunaSearch(**kwargs)


def search_space(study: Study, seeds: int, first_seed: int = 0):
    """Optuna distributions and sampler of a study, and its trial count for a grid
    (seeds ``first_seed`` .. ``first_seed + seeds - 1``)."""
    import optuna
    from optuna.distributions import CategoricalDistribution

    if study.is_grid:
        grid = {"condition": list(study.conditions),
                "seed": list(range(first_seed, first_seed + seeds))}
        space = {k: CategoricalDistribution(v) for k, v in grid.items()}
        return space, optuna.samplers.GridSampler(grid, seed=0), len(study.conditions) * seeds
    space = {**study.space(), "seed": CategoricalDistribution([first_seed])}
    return space, optuna.samplers.TPESampler(seed=0), None


def only_conditions(study: Study, conditions: str | Sequence[str] | None) -> Study:
    """The study restricted to ``conditions`` (checked against its own; order kept).

    A string is the command line's comma-separated list; conditions that hold commas
    themselves (the team study's "2,2") are matched whole."""
    if isinstance(conditions, str):
        conditions = split_conditions(conditions, study.conditions)
    if not conditions:
        return study
    if not study.is_grid:
        fail("conditions", ",".join(conditions), f"none: {study.name} is a search study")
    unknown = [c for c in conditions if c not in study.conditions]
    if unknown:
        fail("conditions", ",".join(unknown), f"conditions of {study.name}: "
             + "; ".join(study.conditions))
    return dataclasses.replace(study, conditions=tuple(dict.fromkeys(conditions)))


def ablate(study_name: str, preset_name: str = "quick", *, seeds: int = 3, trials: int = 8,
           results_dir: str | Path = "results", name: str | None = None,
           address: str | None = None, resume: bool = False,
           env_config: dict[str, Any] | None = None,
           preset_overrides: dict[str, Any] | None = None,
           conditions: str | Sequence[str] | None = None, first_seed: int = 0) -> Path:
    """Run (or resume) one ablation study; returns its folder.

    ``conditions`` runs a subset of a grid study's conditions (all by default), e.g. only
    the team-reward half of ``reward``; the report compares what ran. ``first_seed``
    shifts the seeds, so a study can grow by more seeds in another folder (the report
    merges folders of one study: ``--compare``).
    """
    from rich.console import Console

    console = Console()
    study = only_conditions(get_study(study_name), conditions)
    check_range("seeds", seeds, 1, 100)
    check_range("seed", first_seed, 0, 10_000)
    check_range("trials", trials, 1, 10_000)
    base = make_run_spec("poca", env_config, preset_name, preset_overrides=preset_overrides)
    preset = base.preset
    if preset.evaluation_interval < 1:  # the study's metric is the last evaluation
        fail("evaluation_interval", preset.evaluation_interval, "at least 1 in a study")
    name = name or f"ablate-{study.name}-{preset_name}"
    folder = Path(results_dir).resolve() / name
    check_output_folder(folder, R.STUDY_FILE, "study", resume)
    space, sampler, grid_size = search_space(study, seeds, first_seed)
    for params in study.example_params():  # every condition builds before Ray starts
        base.for_trial(study.name, params).algorithm_config()
    cpus = init_ray(address)
    check_resources(preset, cpus)
    with lock_output_folder(folder, "study"):
        import optuna
        from ray import tune
        num_samples = grid_size or trials
        if not resume:
            folder.mkdir(parents=True)
            R.write_yaml(folder / R.STUDY_FILE, {
                "study": study.name, "preset": preset_name, "seeds": seeds,
                "first_seed": first_seed, "trials": num_samples,
                "conditions": list(study.conditions),
                "evaluation_episodes": preset.evaluation_episodes,
                "env_config": dict(env_config or {}), "preset_overrides": preset_overrides or {},
                "git_commit": git_commit(), "started": time.strftime("%Y-%m-%d %H:%M:%S")})
        trainable = tune.with_resources(
            tune.with_parameters(train_run, spec=base, study=study.name),
            trial_resources(preset))
        concurrent = max(1, int(cpus) // required_cpus(preset))
        console.print(f"[bold]ablate {study.name}[/]: {num_samples} trials of {preset_name} "
                      f"({preset.total_env_steps:,} env steps each), {concurrent} at a time "
                      f"-> {folder}")
        if resume and (folder / R.TUNE_DIR).is_dir():
            for line in restore_missing_checkpoints(folder / R.TUNE_DIR):
                console.print(line)
            tuner = tune.Tuner.restore(str(folder / R.TUNE_DIR), trainable=trainable,
                                       resume_errored=True, resume_unfinished=True)
        else:
            storage = optuna.storages.RDBStorage(f"sqlite:///{folder / R.OPTUNA_DB}")
            searcher = resumable_optuna_search(space=space, metric=R.EVAL_SCORE, mode="max",
                                    sampler=sampler, study_name=name, storage=storage)
            progress = RunProgress(preset.total_env_steps, study_dir=folder, spec=base,
                                   study=study.name, trials=num_samples, concurrent=concurrent)
            tuner = tune.Tuner(
                trainable,
                tune_config=tune.TuneConfig(search_alg=searcher, num_samples=num_samples,
                                            max_concurrent_trials=concurrent,
                                            trial_dirname_creator=lambda t: t.trial_id),
                run_config=tune.RunConfig(
                    storage_path=str(folder), name=R.TUNE_DIR, verbose=0,
                    failure_config=tune.FailureConfig(max_failures=2),
                    checkpoint_config=checkpoint_config(preset), callbacks=[progress]))
        grid = tuner.fit()
        failed = [r for r in grid if r.error]
        if failed:
            console.print(f"[red]{len(failed)} trial(s) failed[/]: {failed[0].error}")
        return folder
