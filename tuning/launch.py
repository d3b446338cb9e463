"""Launch one training run through Ray Tune (locally, or on a cluster with ``address``).

Everything is validated before Ray starts: the env config, the preset, the algorithm and
the CPUs the run needs (a trial that asks for more CPUs than Ray has would wait forever).
A run folder ``RESULTS/NAME/`` holds ``run.yaml`` (algorithm, preset, resolved env config,
seed, git commit, package versions), ``eval_metrics.json`` (one entry per evaluation),
and Tune's experiment under ``tune/`` whose ``trial/`` folder holds ``progress.csv``,
``result.json``, TensorBoard events and checkpoints. Our own files live outside ``tune/``
because Tune re-syncs that folder from its staging copy when a run is restored.
``resume=True`` continues an interrupted run from its last checkpoint.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import yaml

os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # Tune's boxed tables; we print one line/iter
from ray.tune import Callback  # noqa: E402

from rl_scan.algorithms.callbacks import EVAL_SCORE
from rl_scan.config import ConfigError, RunInterrupted, deep_merge, fail, to_dict
from rl_scan.envs.sim.env_config import make_env_config
from rl_scan.metrics import EVAL_FILE
from rl_scan.tuning.presets import TrainPreset, get_preset

# name -> (module, function building the AlgorithmConfig)
ALGORITHMS = {"ppo": ("rl_scan.algorithms.ppo", "ppo_config"),
              "poca": ("rl_scan.algorithms.poca", "poca_config"),
              "meta-poca": ("rl_scan.algorithms.maml", "meta_poca_config")}
RUN_FILE = "run.yaml"
TUNE_DIR = "tune"  # Tune's own experiment folder inside the run folder (Tune re-syncs it)
ENV_STEPS = "num_env_steps_sampled_lifetime"


def build_algorithm_config(algo: str, env_config: dict[str, Any], preset: TrainPreset,
                           seed: int = 0, init_from: str | Path | None = None,
                           algo_kwargs: dict[str, Any] | None = None):
    """The RLlib AlgorithmConfig of a run (env overrides of the preset applied), starting
    from the weights of checkpoint ``init_from`` if given; ``algo_kwargs`` override the
    preset's algorithm settings (e.g. lr, entropy_coeff in a hyperparameter search)."""
    if algo not in ALGORITHMS:
        fail("algo", algo, f"one of {sorted(ALGORITHMS)}")
    module, func = ALGORITHMS[algo]
    builder = getattr(importlib.import_module(module), func)
    kwargs = dict(train_batch_size=preset.train_batch_size,
                  minibatch_size=preset.minibatch_size, num_epochs=preset.num_epochs,
                  lr=preset.lr, num_env_runners=preset.num_env_runners,
                  num_envs_per_env_runner=preset.num_envs_per_env_runner,
                  evaluation_interval=preset.evaluation_interval,
                  evaluation_episodes=preset.evaluation_episodes, seed=seed)
    if algo == "meta-poca":
        kwargs.update(tasks=preset.meta_tasks, episodes=preset.meta_episodes,
                      inner_steps=preset.inner_steps, inner_lr=preset.inner_lr,
                      order=preset.meta_order, meta_epochs=preset.meta_epochs)
    kwargs.update(algo_kwargs or {})
    config = builder(deep_merge(preset.env_overrides, env_config), **kwargs)
    if init_from is not None:
        from rl_scan.algorithms.init_weights import init_from_callback

        config.callbacks(on_algorithm_init=init_from_callback(init_from))
    config.validate()  # every setting checked before Ray starts
    return config


def scenario_label(scenario: str) -> str:
    """A folder-name-safe scenario label: test:3 -> test3, train:* -> train-any,
    path/to/scene.yaml -> scene."""
    if scenario.endswith((".yaml", ".yml")):
        return Path(scenario).stem
    return scenario.replace(":*", "-any").replace(":", "")


def git_commit() -> str:
    """The commit of the rl-scan source tree, or 'unknown' outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def check_output_folder(folder: Path, marker: str, what: str, resume: bool) -> None:
    """A new run/study needs a fresh folder; a resumed one needs its ``marker`` file."""
    if folder.exists() and not resume:
        raise ConfigError(f"{what} folder {str(folder)!r} exists: pass --resume to continue "
                          "it or choose another --name")
    if resume and not (folder / marker).is_file():
        raise ConfigError(f"--resume: no {what} to resume in {str(folder)!r}")


def required_cpus(preset: TrainPreset) -> int:
    """CPU bundles of one trial: the training process plus one per env runner."""
    return 1 + preset.num_env_runners


def check_resources(preset: TrainPreset, available: float) -> None:
    """Refuse runs whose trial could never be scheduled (Tune would wait silently)."""
    need = required_cpus(preset)
    if need > available:
        fail("num_env_runners", preset.num_env_runners,
             f"at most {int(available) - 1} on this Ray cluster ({available:g} CPUs; a run "
             f"needs 1 + num_env_runners = {need})")


def checkpoint_config(preset: TrainPreset):
    """Keep the 3 best checkpoints by evaluation coverage, and always the latest (resume).

    Without evaluation there is no score: the 3 latest are kept.
    """
    from ray import tune

    scored = preset.evaluation_interval > 0
    return tune.CheckpointConfig(
        checkpoint_frequency=preset.checkpoint_frequency, checkpoint_at_end=True,
        num_to_keep=3, checkpoint_score_attribute=EVAL_SCORE if scored else None,
        checkpoint_score_order="max")


def _versions() -> dict[str, str]:
    import gymnasium
    import numpy
    import ray
    import torch

    import rl_scan

    mods = {"rl_scan": rl_scan, "ray": ray, "torch": torch, "gymnasium": gymnasium,
            "numpy": numpy}
    return {name: str(mod.__version__) for name, mod in mods.items()}


def init_ray(address: str | None) -> float:
    """Join the Ray cluster at ``address`` or start a local Ray (once); its CPU count."""
    import ray

    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)
    return float(ray.cluster_resources().get("CPU", 0))


def train(algo: str, env_config: dict[str, Any], preset_name: str = "smoke", *,
          seed: int = 0, results_dir: str | Path = "results", name: str | None = None,
          address: str | None = None, resume: bool = False,
          preset_overrides: dict[str, Any] | None = None, init_from: str | Path | None = None,
          console=None) -> Path:
    """Run (or resume) one Tune training run; returns its run folder.

    ``init_from``: a checkpoint (or run folder) whose module weights the run starts from
    (adaptation / fine-tuning); recorded in run.yaml.
    """
    from rich.console import Console

    console = console or Console()
    preset = get_preset(preset_name, preset_overrides)
    env_cfg = make_env_config(deep_merge(preset.env_overrides, env_config))
    if algo not in ALGORITHMS:
        fail("algo", algo, f"one of {sorted(ALGORITHMS)}")
    name = name or f"{algo}_{scenario_label(env_cfg.scenario)}_{preset_name}_s{seed}"
    run_dir = Path(results_dir).resolve() / name
    check_output_folder(run_dir, RUN_FILE, "run", resume)
    if init_from is not None:
        from rl_scan.algorithms.rollout import resolve_checkpoint

        init_from = resolve_checkpoint(init_from)
    config = build_algorithm_config(algo, env_config, preset, seed, init_from)
    cpus = init_ray(address)
    check_resources(preset, cpus)

    from ray import tune

    if not resume:
        text = yaml.safe_dump({
            "algo": algo, "preset": preset_name, "preset_config": to_dict(preset),
            "seed": seed, "env_config": to_dict(env_cfg),
            "init_from": str(init_from) if init_from else None, "git_commit": git_commit(),
            "versions": _versions(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        }, sort_keys=False)
        run_dir.mkdir(parents=True)
        (run_dir / RUN_FILE).write_text(text)
        if init_from is not None and preset.evaluation_interval > 0:
            start = evaluate_start_weights(init_from, env_cfg, preset.evaluation_episodes,
                                           seed)
            (run_dir / EVAL_FILE).write_text(json.dumps([start], indent=1, default=float))
            console.print(f"start weights on {env_cfg.scenario}: coverage "
                          f"{start['coverage']:.3f} over {preset.evaluation_episodes} episodes "
                          "(evaluation 0)")
    progress = ProgressCallback(run_dir, preset.total_env_steps, preset.evaluation_interval)
    algo_cls = config.algo_class
    if resume:
        console.print(f"resuming {run_dir}")
        # The run config, this progress callback included, is restored from tuner.pkl.
        tuner = tune.Tuner.restore(str(run_dir / TUNE_DIR), trainable=algo_cls,
                                   resume_errored=True,
                                   resume_unfinished=True)
    else:
        tuner = tune.Tuner(
            algo_cls, param_space=config,
            tune_config=tune.TuneConfig(num_samples=1,
                                        trial_dirname_creator=lambda t: "trial"),
            run_config=tune.RunConfig(
                storage_path=str(run_dir), name=TUNE_DIR, verbose=0,
                stop={ENV_STEPS: preset.total_env_steps},
                checkpoint_config=checkpoint_config(preset),
                failure_config=tune.FailureConfig(max_failures=2),
                callbacks=[progress]))
    console.print(f"[bold]{algo}[/] on {env_cfg.scenario} ({env_cfg.team.wheeled} wheeled + "
                  f"{env_cfg.team.quad} quads, comm {env_cfg.comm_scheme}), preset "
                  f"{preset_name}: {preset.total_env_steps:,} env steps in "
                  f"{preset.iterations} iterations -> {run_dir}")
    grid = tuner.fit()
    errors = [r.error for r in grid if r.error]
    if errors:
        raise RuntimeError(f"training failed: {errors[0]}")
    steps = max((int(r.metrics.get(ENV_STEPS, 0)) for r in grid), default=0)
    if steps < preset.total_env_steps:  # Tune ends a run quietly on Ctrl+C
        raise RunInterrupted(f"{name} stopped at {steps:,} of {preset.total_env_steps:,} "
                             "env steps; its last checkpoint is kept")
    return run_dir


def evaluate_start_weights(checkpoint: Path, env_cfg, episodes: int, seed: int) -> dict:
    """Evaluation 0 of a run that starts from other weights: its start policy on its own
    env before any training (how well a pre-trained policy does zero-shot), with the
    sampled actions and the keys of RLlib's evaluations (``append_eval``)."""
    import numpy as np
    import torch

    from rl_scan import metrics as M
    from rl_scan.algorithms.rollout import PolicyTeam, load_actors
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import run_episode

    core, team = ScanCore(env_cfg), PolicyTeam(load_actors(Path(checkpoint)))
    torch.manual_seed(seed)
    episodes_metrics = [run_episode(core, team, seed=10_000 * (seed + 1) + i)
                        for i in range(episodes)]
    entry = {"training_iteration": 0, "env_steps": 0, "time_total_s": 0.0,
             "episode_return_mean": float(np.mean([
                 sum(m[k] * n for k, n in zip(M.RETURN_BY_KIND.values(),
                                              (env_cfg.team.wheeled, env_cfg.team.quad)))
                 for m in episodes_metrics]))}
    for key in M.EPISODE_METRICS:
        values = np.array([m[key] for m in episodes_metrics], dtype=float)
        if key in M.STEPS_TO.values():  # as the callback: the mean over runs reaching it
            entry["reached_" + key[len("steps_to_"):]] = float(np.mean(~np.isnan(values)))
            values = values[~np.isnan(values)]
        if len(values):
            entry[key] = float(values.mean())
    return entry


class ProgressCallback(Callback):
    """One line per iteration, and every evaluation appended to ``eval_metrics.json``."""

    def __init__(self, run_dir: Path, total_steps: int, evaluation_interval: int) -> None:
        self.run_dir, self.total = Path(run_dir), total_steps  # picklable: Tune saves it
        self.evaluation_interval = evaluation_interval

    def on_trial_result(self, iteration, trials, trial, result, **info) -> None:
        runners = result.get("env_runners", {})
        steps = int(result.get(ENV_STEPS, 0))
        cov = runners.get("scan/coverage", math.nan)
        line = (f"{self.run_dir.name}  iter {result.get('training_iteration', 0):>4}  "
                f"env steps {steps:>10,} "
                f"({100 * steps / self.total:5.1f}%)  "
                f"return {runners.get('episode_return_mean', math.nan):8.1f}  "
                f"coverage {cov:5.3f}  {result.get('time_this_iter_s', 0):5.1f} s/iter")
        if "meta/coverage_after_adaptation" in result:  # meta-poca
            line += (f"  meta coverage {result['meta/coverage_before_adaptation']:5.3f} -> "
                     f"{result['meta/coverage_after_adaptation']:5.3f} after adaptation")
        # RLlib repeats the previous evaluation in the next results: use evaluation iterations.
        it = result.get("training_iteration", 0)
        evaluated = self.evaluation_interval > 0 and it % self.evaluation_interval == 0
        evaluation = result.get("evaluation", {}).get("env_runners", {})
        if evaluated and evaluation:
            ecov = evaluation.get("scan/coverage", math.nan)
            line += f"  eval coverage {ecov:5.3f}"
            append_eval(self.run_dir, result, evaluation)
        print(line, flush=True)


def append_eval(folder: Path, result: dict, evaluation: dict) -> None:
    """Append one evaluation (RLlib's ``evaluation/env_runners`` dict) to eval_metrics.json."""
    path = Path(folder) / EVAL_FILE
    entries = json.loads(path.read_text()) if path.is_file() else []
    it = result.get("training_iteration", 0)
    # After a restore, iterations past the checkpoint run again: the new ones win.
    entries = [e for e in entries if e["training_iteration"] < it]
    entries.append({
        "training_iteration": it,
        "env_steps": result.get(ENV_STEPS),
        "time_total_s": result.get("time_total_s"),
        "episode_return_mean": evaluation.get("episode_return_mean"),
        "module_returns": evaluation.get("module_episode_returns_mean", {}),
        **{k[len("scan/"):]: v for k, v in evaluation.items() if k.startswith("scan/")},
    })
    path.write_text(json.dumps(entries, indent=1, default=float))
