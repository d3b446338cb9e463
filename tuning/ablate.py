"""``rl-scan ablate``: the paper's ablations as Ray Tune studies searched by Optuna.

Studies (each trial is a real training run with evaluation and checkpoints):
  comm  the seven communication schemes of Table II, plus scheme 1 without the
        quad->wheeled object-information channel ("1-noinfo");
  algo  POCA vs PPO with the same hyperparameters (the paper's comparison);
  team  heterogeneous 2 wheeled + 2 quads vs homogeneous 4 quads and 4 wheeled;
  hpo   Optuna TPE over POCA's lr, entropy coefficient, lambda and epochs.
Categorical studies are a full grid (Optuna's ``GridSampler``) of condition x seed.

A study folder ``RESULTS/NAME/`` holds ``study.yaml`` (what was asked), ``optuna.db``
(the Optuna study in SQLite: ``optuna-dashboard sqlite:///RESULTS/NAME/optuna.db``) and
Tune's experiment under ``tune/``; each trial folder holds ``eval_metrics.json``,
``progress.csv`` and checkpoints. ``resume=True`` continues an interrupted study: finished
trials are kept, unfinished ones continue from their last checkpoint.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
from ray.tune import Callback

from rl_scan.algorithms.callbacks import EVAL_SCORE
from rl_scan.config import check_range, fail
from rl_scan.tuning.launch import (
    ENV_STEPS,
    append_eval,
    build_algorithm_config,
    check_output_folder,
    check_resources,
    git_commit,
    init_ray,
)
from rl_scan.tuning.presets import get_preset

COMM_CONDITIONS = [str(i) for i in range(1, 8)] + ["1-noinfo"]
GRIDS = {
    "comm": COMM_CONDITIONS,
    "algo": ["poca", "ppo"],
    "team": ["2,2", "0,4", "4,0"],
}
STUDIES = (*GRIDS, "hpo")
STUDY_FILE, OPTUNA_DB, TUNE_DIR = "study.yaml", "optuna.db", "tune"
METRIC = EVAL_SCORE  # the last evaluation's mean coverage: the final-checkpoint score


def condition_run(study: str, params: dict[str, Any], base_env: dict[str, Any]
                  ) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """(algorithm, env config, algorithm keyword overrides) of one trial's parameters."""
    env = dict(base_env)
    algo, algo_kwargs = "poca", {}
    cond = params.get("condition")
    if study == "comm":
        scheme, _, info = str(cond).partition("-")
        env["comm_scheme"] = int(scheme)
        env["object_info"] = info != "noinfo"
    elif study == "algo":
        algo = str(cond)
    elif study == "team":
        wheeled, quad = (int(x) for x in str(cond).split(","))
        env["team"] = {"wheeled": wheeled, "quad": quad}
    elif study == "hpo":
        algo_kwargs = {k: params[k] for k in ("lr", "entropy_coeff", "lambda_")}
        algo_kwargs["num_epochs"] = int(params["num_epochs"])
    return algo, env, algo_kwargs


def run_trial(params: dict[str, Any], study: str, preset_name: str,
              preset_overrides: dict[str, Any], base_env: dict[str, Any]) -> None:
    """Tune function trainable: one training run, evaluation and checkpoints, resumable."""
    from ray import tune

    preset = get_preset(preset_name, preset_overrides)
    algo, env, algo_kwargs = condition_run(study, params, base_env)
    config = build_algorithm_config(algo, env, preset, seed=int(params.get("seed", 0)),
                                    algo_kwargs=algo_kwargs)
    algorithm = config.build_algo()
    trial_dir = Path(tune.get_context().get_trial_dir())
    (trial_dir / "condition.json").write_text(json.dumps(
        {"study": study, "algo": algo, "params": params, "env_config": env}, default=str))
    checkpoint = tune.get_checkpoint()
    if checkpoint is not None:
        with checkpoint.as_directory() as folder:
            algorithm.restore_from_path(folder)
    last_eval = math.nan
    try:
        while True:
            result = algorithm.train()
            it, steps = result["training_iteration"], int(result[ENV_STEPS])
            evaluation = result.get("evaluation", {}).get("env_runners", {})
            if preset.evaluation_interval and it % preset.evaluation_interval == 0 and evaluation:
                last_eval = float(evaluation.get("scan/coverage", math.nan))
                append_eval(trial_dir, result, evaluation)
            done = steps >= preset.total_env_steps
            metrics = {ENV_STEPS: steps, METRIC: 0.0 if math.isnan(last_eval) else last_eval,
                       "coverage": result.get("env_runners", {}).get("scan/coverage", math.nan),
                       "done": done}
            if done or it % preset.checkpoint_frequency == 0:
                with tempfile.TemporaryDirectory() as tmp:
                    algorithm.save_to_path(tmp)
                    tune.report(metrics, checkpoint=tune.Checkpoint.from_directory(tmp))
            else:
                tune.report(metrics)
            if done:
                return
    finally:
        algorithm.stop()


def search_space(study: str, seeds: int):
    """Optuna distributions and sampler of a study (grid for categorical studies)."""
    import optuna
    from optuna.distributions import (
        CategoricalDistribution,
        FloatDistribution,
        IntDistribution,
    )

    if study in GRIDS:
        grid = {"condition": GRIDS[study], "seed": list(range(seeds))}
        space = {k: CategoricalDistribution(v) for k, v in grid.items()}
        return space, optuna.samplers.GridSampler(grid, seed=0), len(GRIDS[study]) * seeds
    space = {"lr": FloatDistribution(5e-5, 2e-3, log=True),
             "entropy_coeff": FloatDistribution(1e-4, 2e-2, log=True),
             "lambda_": FloatDistribution(0.8, 0.99),
             "num_epochs": IntDistribution(1, 5),
             "seed": CategoricalDistribution([0])}
    return space, optuna.samplers.TPESampler(seed=0), None


def ablate(study: str, preset_name: str = "quick", *, seeds: int = 3, trials: int = 8,
           results_dir: str | Path = "results", name: str | None = None,
           address: str | None = None, resume: bool = False,
           env_config: dict[str, Any] | None = None,
           preset_overrides: dict[str, Any] | None = None, console=None) -> Path:
    """Run (or resume) one ablation study; returns its folder."""
    from rich.console import Console

    console = console or Console()
    if study not in STUDIES:
        fail("study", study, f"one of {', '.join(STUDIES)}")
    check_range("seeds", seeds, 1, 100)
    check_range("trials", trials, 1, 10_000)
    preset = get_preset(preset_name, preset_overrides)
    env_config = dict(env_config or {})
    name = name or f"ablate-{study}-{preset_name}"
    folder = Path(results_dir).resolve() / name
    check_output_folder(folder, STUDY_FILE, "study", resume)
    space, sampler, grid_size = search_space(study, seeds)
    for params in _example_params(study, space):  # every condition builds before Ray starts
        algo, env, kw = condition_run(study, params, env_config)
        build_algorithm_config(algo, env, preset, algo_kwargs=kw)
    cpus = init_ray(address)
    check_resources(preset, cpus)

    import optuna
    from ray import tune
    from ray.tune.search.optuna import OptunaSearch

    num_samples = grid_size or trials
    if not resume:
        folder.mkdir(parents=True)
        (folder / STUDY_FILE).write_text(yaml.safe_dump({
            "study": study, "preset": preset_name, "seeds": seeds, "trials": num_samples,
            "env_config": env_config, "preset_overrides": preset_overrides or {},
            "git_commit": git_commit(), "started": time.strftime("%Y-%m-%d %H:%M:%S")},
            sort_keys=False))
    trainable = tune.with_resources(
        tune.with_parameters(run_trial, study=study, preset_name=preset_name,
                             preset_overrides=dict(preset_overrides or {}),
                             base_env=env_config),
        {"cpu": 1 + preset.num_env_runners})
    concurrent = max(1, int(cpus) // (1 + preset.num_env_runners))
    console.print(f"[bold]ablate {study}[/]: {num_samples} trials of {preset_name} "
                  f"({preset.total_env_steps:,} env steps each), {concurrent} at a time "
                  f"-> {folder}")
    if resume and (folder / TUNE_DIR).is_dir():
        tuner = tune.Tuner.restore(str(folder / TUNE_DIR), trainable=trainable,
                                   resume_errored=True, resume_unfinished=True)
    else:
        storage = optuna.storages.RDBStorage(f"sqlite:///{folder / OPTUNA_DB}")
        searcher = OptunaSearch(space=space, metric=METRIC, mode="max", sampler=sampler,
                                study_name=name, storage=storage)
        tuner = tune.Tuner(
            trainable,
            tune_config=tune.TuneConfig(search_alg=searcher, num_samples=num_samples,
                                        max_concurrent_trials=concurrent),
            run_config=tune.RunConfig(
                storage_path=str(folder), name=TUNE_DIR, verbose=0,
                failure_config=tune.FailureConfig(max_failures=2),
                # the 2 best checkpoints by evaluation coverage, and always the latest
                checkpoint_config=tune.CheckpointConfig(
                    num_to_keep=2, checkpoint_score_attribute=METRIC,
                    checkpoint_score_order="max"),
                callbacks=[StudyProgress(num_samples)]))
    grid = tuner.fit()
    failed = [r for r in grid if r.error]
    if failed:
        console.print(f"[red]{len(failed)} trial(s) failed[/]: {failed[0].error}")
    return folder


def _example_params(study: str, space: dict) -> list[dict[str, Any]]:
    if study in GRIDS:
        return [{"condition": c, "seed": 0} for c in GRIDS[study]]
    return [{"lr": 3e-4, "entropy_coeff": 5e-3, "lambda_": 0.95, "num_epochs": 3, "seed": 0}]


class StudyProgress(Callback):
    """Tune callback: one line per trial result and per finished trial."""

    def __init__(self, total: int) -> None:
        self.total, self.finished = total, 0

    def on_trial_result(self, iteration, trials, trial, result, **info) -> None:
        print(f"trial {trial.trial_id} {_label(trial.config)}: "
              f"{result.get(ENV_STEPS, 0):,} env steps, eval coverage "
              f"{result.get(METRIC, math.nan):.3f}", flush=True)

    def on_trial_complete(self, iteration, trials, trial, **info) -> None:
        self.finished += 1
        print(f"finished {self.finished}/{self.total}: {_label(trial.config)} "
              f"eval coverage {trial.last_result.get(METRIC, math.nan):.3f}", flush=True)


def _label(config: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in sorted(config.items()))
