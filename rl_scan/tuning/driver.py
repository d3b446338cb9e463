"""The one run driver: every training run (``train``, ``meta-train``, ``adapt``, each
ablation trial, each experiment run) is a ``RunSpec`` trained by ``train_run`` under Tune.

``RunSpec``      what to train, validated once when it is made (typed EnvConfig, preset,
                 the algorithm's own settings); ``metadata()`` is the run folder's RUN_FILE.
``train_run``    the Tune function trainable: builds the algorithm, restores Tune's
                 checkpoint, calls ``train()`` until the budget, checkpoints every
                 ``checkpoint_frequency`` iterations and at the end, marks evaluations.
``RunProgress``  the Tune callback on the driver: one line per iteration, and every
                 evaluation appended to the run folder's EVAL_FILE (outside Tune's folder,
                 which Tune re-syncs from a staging copy on restore).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ray.tune import Callback

from rl_scan import results as R
from rl_scan.algorithms.registry import get_algorithm, settings_kwargs
from rl_scan.config import deep_merge, fail, to_dict
from rl_scan.envs.sim.env_config import EnvConfig, make_env_config
from rl_scan.studies import get_study
from rl_scan.tuning.presets import TrainPreset, get_preset


@dataclass(frozen=True)
class RunSpec:
    """One training run, validated: what ``train_run`` builds and the run folder records."""

    algo: str
    env: EnvConfig
    preset_name: str
    preset: TrainPreset
    seed: int = 0
    settings: Any = None
    """The algorithm's own settings (its registry entry), None if it has none."""
    algo_kwargs: dict[str, Any] = field(default_factory=dict)
    """Builder keywords on top of the preset's (e.g. lr in a hyperparameter search)."""
    init_from: str | None = None
    """A checkpoint folder whose module weights the run starts from."""
    study: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    """A study trial's parameters (condition or searched values, seed)."""

    def algorithm_config(self):
        """The RLlib AlgorithmConfig of this run, validated."""
        entry = get_algorithm(self.algo)
        p = self.preset
        kwargs = dict(train_batch_size=p.train_batch_size, minibatch_size=p.minibatch_size,
                      num_epochs=p.num_epochs, lr=p.lr, num_env_runners=p.num_env_runners,
                      num_envs_per_env_runner=p.num_envs_per_env_runner,
                      evaluation_interval=p.evaluation_interval,
                      evaluation_episodes=p.evaluation_episodes, seed=self.seed,
                      sampler=p.sampler, overlap_sampling=p.overlap_sampling,
                      decay_steps=p.total_env_steps if p.decay_schedules else None,
                      **settings_kwargs(self.settings), **self.algo_kwargs)
        config = entry.load_builder()(self.env, **kwargs)
        if self.init_from is not None:
            from rl_scan.algorithms.init_weights import init_from_callback

            config.callbacks(on_algorithm_init=init_from_callback(self.init_from))
        config.validate()
        return config

    def for_trial(self, study: str, params: dict[str, Any]) -> RunSpec:
        """This spec with a study trial's condition applied."""
        run = get_study(study).run_of(params)
        env = make_env_config(deep_merge(to_dict(self.env), run.env))
        return dataclasses.replace(
            self, algo=run.algo, env=env, seed=int(params.get("seed", 0)),
            settings=get_algorithm(run.algo).make_settings(self.preset_name),
            algo_kwargs={**self.algo_kwargs, **run.algo_kwargs}, study=study,
            params=dict(params))

    @property
    def iterations(self) -> int:
        """Training iterations to the budget (a meta-iteration samples its own steps)."""
        per = getattr(self.settings, "env_steps_per_iteration", None)
        return -(-self.preset.total_env_steps // per()) if per else self.preset.iterations

    def metadata(self) -> dict[str, Any]:
        """The run folder's RUN_FILE: what ran, from which code."""
        return {"algo": self.algo, "preset": self.preset_name,
                "preset_config": to_dict(self.preset), "seed": self.seed,
                "algo_settings": to_dict(self.settings), "algo_kwargs": self.algo_kwargs,
                "env_config": to_dict(self.env), "init_from": self.init_from,
                "study": self.study, "params": self.params, "git_commit": git_commit(),
                "versions": _versions(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}


def make_run_spec(algo: str, env_config: dict[str, Any] | None = None,
                  preset_name: str = "smoke", *, seed: int = 0,
                  preset_overrides: dict[str, Any] | None = None,
                  init_from: str | Path | None = None,
                  algo_kwargs: dict[str, Any] | None = None,
                  settings_overrides: dict[str, Any] | None = None) -> RunSpec:
    """Validate a run's inputs once (the preset's env overrides under the user's, the
    preset's algorithm settings under ``settings_overrides``)."""
    entry = get_algorithm(algo)
    preset = get_preset(preset_name, preset_overrides)
    if entry.local_sampling:  # it samples in its own process with fixed settings
        for name in ("overlap_sampling", "decay_schedules"):
            if name in (preset_overrides or {}) and getattr(preset, name):
                fail(name, True, f"False for {algo} (it samples in its own process and "
                                 "meta-updates with fixed settings)")
        preset = dataclasses.replace(preset, overlap_sampling=False, decay_schedules=False)
    settings = entry.make_settings(preset_name, settings_overrides)
    if hasattr(settings, "fit_preset"):  # iterations of its own size (MetaPOCA)
        preset = settings.fit_preset(preset, prefix=f"{algo}.")
    env = make_env_config(deep_merge(preset.env_overrides, dict(env_config or {})))
    if init_from is not None:
        from rl_scan.algorithms.rollout import resolve_checkpoint

        init_from = str(resolve_checkpoint(init_from))
    return RunSpec(algo, env, preset_name, preset, seed, settings,
                   dict(algo_kwargs or {}), init_from)


def train_run(params: dict[str, Any], *, spec: RunSpec, study: str | None = None) -> None:
    """Tune function trainable: one run to its budget, resumable from Tune's checkpoint.

    ``params`` are a study trial's parameters (``study`` names the study), else empty.
    """
    from ray import tune

    if study is not None:
        spec = spec.for_trial(study, params)
    import torch

    from rl_scan.algorithms.callbacks import NonFiniteLossError

    # A non-finite loss is not retried by FailureConfig: it would recur from the same
    # checkpoint. The first failure leaves its message here; a retry only repeats it.
    stopped = Path(tune.get_context().get_trial_dir()) / R.NONFINITE_FILE
    if stopped.is_file():
        raise NonFiniteLossError(f"{stopped.read_text()} (not retried: it would recur "
                                 "from the same checkpoint)")
    preset = spec.preset
    checkpoint, saved = tune.get_checkpoint(), {}
    if checkpoint is not None:
        with checkpoint.as_directory() as folder:
            saved = R.read_json(Path(folder) / R.CHECKPOINT_STEPS) or {}
        if saved.get("env_steps", 0) >= preset.total_env_steps:
            return  # restored at its end: nothing left to train (a resumed study may)
        final = final_checkpoint(checkpoint, preset.total_env_steps)
        if final is not None:  # its last report again (a study records its metric once)
            with tempfile.TemporaryDirectory() as tmp:  # Tune may persist it under its name
                shutil.copytree(final, tmp, dirs_exist_ok=True)
                tune.report(R.read_json(final / R.CHECKPOINT_STEPS)[FINAL_RESULT],
                            checkpoint=tune.Checkpoint.from_directory(tmp))
            return
    torch.set_num_threads(preset.learner_cpus)  # as many threads as reserved CPUs
    algorithm = spec.algorithm_config().build_algo()
    if checkpoint is not None:
        with checkpoint.as_directory() as folder:
            algorithm.restore_from_path(folder)
    nodes = placement(algorithm)
    seconds = saved.get(R.RUN_SECONDS, 0.0)
    try:
        while True:
            result = algorithm.train()
            it = result[R.ITERATION]
            seconds += result.get("time_this_iter_s", 0.0)
            result[R.RUN_SECONDS] = seconds
            # RLlib repeats the last evaluation in later results: mark the fresh ones.
            result[R.EVALUATED] = bool(preset.evaluation_interval and R.evaluation_of(result)
                                       and it % preset.evaluation_interval == 0)
            result[R.LEARNER_THREADS] = torch.get_num_threads()
            result[R.NODES] = nodes
            done = result[R.ENV_STEPS] >= preset.total_env_steps
            if done or it % preset.checkpoint_frequency == 0:
                with tempfile.TemporaryDirectory() as tmp:
                    algorithm.save_to_path(tmp)
                    R.write_json(Path(tmp) / R.CHECKPOINT_STEPS,
                                 {"env_steps": int(result[R.ENV_STEPS]), R.ITERATION: it,
                                  R.RUN_SECONDS: seconds,
                                  **({FINAL_RESULT: R.jsonable(result)} if done else {})})
                    tune.report(result, checkpoint=tune.Checkpoint.from_directory(tmp))
            else:
                tune.report(result)
            if done:
                return
    except NonFiniteLossError as error:
        stopped.write_text(str(error))
        raise
    finally:
        algorithm.stop()


FINAL_RESULT = "final_result"  # in a run's last checkpoint: the result reported with it


def final_checkpoint(checkpoint, total_env_steps: int) -> Path | None:
    """This trial's last checkpoint if it already wrote it, though Tune restores an earlier one.

    Tune saves its experiment state every ~10 s: a driver killed just after a trial's last
    report resumes that trial from the checkpoint its saved state names, while the trial's
    folder (local or shared file system) holds the final one beside it. Reporting the final
    one again finishes the trial with the result it had, instead of re-training its last
    iterations (whose new results would differ from those a study already recorded).
    """
    import pyarrow.fs

    if not isinstance(checkpoint.filesystem, pyarrow.fs.LocalFileSystem):
        return None  # cloud storage: Tune's own checkpoint is the one we have
    for folder in sorted(Path(checkpoint.path).parent.glob("checkpoint_*"), reverse=True):
        saved = R.read_json(folder / R.CHECKPOINT_STEPS) or {}
        if saved.get("env_steps", 0) >= total_env_steps and FINAL_RESULT in saved:
            return folder
    return None


def placement(algorithm) -> dict[str, Any]:
    """The Ray nodes of this run: its training process's and each remote env runner's
    (node id and IP; two nodes on one machine share the IP)."""
    import ray

    def here(*_):
        return {"node_id": ray.get_runtime_context().get_node_id(),
                "ip": ray.util.get_node_ip_address()}

    group = algorithm.env_runner_group
    remote = group.foreach_env_runner(here, local_env_runner=False) if (
        group is not None and group.num_remote_env_runners()) else []
    return {"trainable": here(), "env_runners": list(remote)}


def required_cpus(preset: TrainPreset) -> int:
    """CPUs of one run: the training process's ``learner_cpus`` plus one per env runner."""
    return preset.learner_cpus + preset.num_env_runners


def trial_resources(preset: TrainPreset):
    """Tune's placement group of one run: the training process's bundle, then one per runner.

    The first bundle is the trainable's own (Ray gives it OMP_NUM_THREADS = its CPUs); env
    runners created inside it are captured into the others. One bundle holding every CPU
    would leave none for the runners.
    """
    from ray.tune.execution.placement_groups import PlacementGroupFactory

    return PlacementGroupFactory([{"CPU": preset.learner_cpus, **preset.custom_resources}]
                                 + [{"CPU": 1}] * preset.num_env_runners)


class RunProgress(Callback):
    """One line per iteration; evaluations appended to the run folder's EVAL_FILE.

    ``run_dir`` is the run folder of a single run; for a study (``study_dir``) each trial
    has its own run folder, ``trial_run_dir(study_dir, trial_id)``, made at its start.
    """

    def __init__(self, total_steps: int, run_dir: Path | None = None,
                 study_dir: Path | None = None, spec: RunSpec | None = None,
                 study: str | None = None, trials: int = 1, concurrent: int = 1) -> None:
        self.total, self.run_dir, self.study_dir = total_steps, run_dir, study_dir
        self.spec, self.study, self.trials = spec, study, trials
        self.concurrent = concurrent

    def _folder(self, trial) -> Path:
        return self.run_dir or R.trial_run_dir(self.study_dir, trial.trial_id)

    def on_trial_start(self, iteration, trials, trial, **info) -> None:
        folder = self._folder(trial)
        if self.study is not None and not R.is_run_folder(folder):
            folder.mkdir(parents=True, exist_ok=True)
            meta = self.spec.for_trial(self.study, trial.config).metadata()
            R.write_yaml(folder / R.RUN_FILE, {**meta, "tune_trial": trial.trial_id})

    def on_trial_result(self, iteration, trials, trial, result, **info) -> None:
        folder = self._folder(trial)
        runners = result.get(R.ENV_RUNNERS, {})
        steps = int(result.get(R.ENV_STEPS, 0))
        label = folder.name if self.study is None else _label(trial.config)
        line = (f"{label}  iter {result.get(R.ITERATION, 0):>4}  env steps {steps:>10,} "
                f"({100 * steps / self.total:5.1f}%)  "
                f"return {runners.get(R.EPISODE_RETURN, math.nan):8.1f}  "
                f"coverage {runners.get(R.scan_key('coverage'), math.nan):5.3f}  "
                f"{result.get('time_this_iter_s', 0):5.1f} s/iter")
        if R.META_AFTER in result:  # meta-poca
            line += (f"  meta coverage {result[R.META_BEFORE]:5.3f} -> "
                     f"{result[R.META_AFTER]:5.3f} after adaptation")
            R.append_meta(folder, result)
        if result.get(R.EVALUATED):
            line += f"  eval coverage {result.get(R.EVAL_SCORE, math.nan):5.3f}"
            R.append_eval(folder, R.eval_entry(result))
        R.record_nodes(folder, result.get(R.ITERATION, 0), result.get(R.NODES))
        print(line, flush=True)

    def on_trial_complete(self, iteration, trials, trial, **info) -> None:
        if self.study is not None:  # trials: all of Tune's, those a resume restored too
            done = 1 + sum(t.status == "TERMINATED" for t in trials if t is not trial)
            left = self._time_left(trials)
            print(f"finished {done}/{self.trials}: {_label(trial.config)} eval "
                  f"coverage {trial.last_result.get(R.EVAL_SCORE, math.nan):.3f}"
                  + (f"; about {format_duration(left)} left" if left else ""), flush=True)

    def _time_left(self, trials) -> float:
        """Seconds until the study ends: env steps still to run / the trials' env steps
        per second so far (Tune's per-trial totals, kept across resumes) / trials at a
        time (a study restored from before this estimate has no count: 1)."""
        steps = sum(t.last_result.get(R.ENV_STEPS, 0) for t in trials)
        seconds = sum(t.last_result.get("time_total_s", 0.0) for t in trials)
        left = self.trials * self.total - steps
        if left <= 0 or steps <= 0 or seconds <= 0:
            return 0.0
        return left / (steps / seconds) / getattr(self, "concurrent", 1)


def format_duration(seconds: float) -> str:
    """``42 s``, ``35 min`` or ``2.5 h``: how progress lines say a time."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 90 * 60 else f"{seconds / 3600:.1f} h"


def _label(params: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in sorted(params.items()))


def git_commit() -> str:
    """The commit of the rl-scan source tree, or 'unknown' outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


RECORDED_PACKAGES = ("rl_scan", "ray", "torch", "gymnasium", "numpy", "numba", "llvmlite",
                     "trimesh", "scipy")
"""Packages whose versions a run folder records: each can change a seeded run's numbers
(numba and llvmlite compile the raycasts, trimesh builds the objects' meshes)."""


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str:
        try:
            return version(name.replace("_", "-"))
        except PackageNotFoundError:
            return "not installed"

    return {name: installed(name) for name in RECORDED_PACKAGES}
