"""Launch one training run through Ray Tune (locally, or on a cluster with ``address``).

Everything is validated before Ray starts: the run's inputs (``driver.make_run_spec``),
its algorithm config and the CPUs the run needs (a trial that asks for more CPUs than Ray
has would wait forever). The run folder ``RESULTS/NAME/`` is laid out as
``rl_scan.results`` describes; ``driver.train_run`` trains it. ``resume=True`` continues
an interrupted run from its last checkpoint.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # Tune's boxed tables; we print one line/iter

from rl_scan import results as R  # noqa: E402
from rl_scan.config import ConfigError, RunInterrupted, fail  # noqa: E402
from rl_scan.tuning.checkpoints import checkpoint_config, restore_missing_checkpoints  # noqa: E402
from rl_scan.tuning.driver import (  # noqa: E402
    RunProgress,
    RunSpec,
    make_run_spec,
    required_cpus,
    train_run,
    trial_resources,
)
from rl_scan.tuning.presets import TrainPreset  # noqa: E402


def scenario_label(scenario: str) -> str:
    """A folder-name-safe scenario label: test:3 -> test3, train:* -> train-any,
    path/to/scene.yaml -> scene."""
    if scenario.endswith((".yaml", ".yml")):
        return Path(scenario).stem
    return scenario.replace(":*", "-any").replace(":", "")


def check_output_folder(folder: Path, marker: str, what: str, resume: bool) -> None:
    """A new run/study needs a fresh folder; a resumed one needs its ``marker`` file."""
    if folder.exists() and not resume:
        raise ConfigError(f"{what} folder {str(folder)!r} exists: pass --resume to continue "
                          "it or choose another --name")
    if resume and not (folder / marker).is_file():
        raise ConfigError(f"--resume: no {what} to resume in {str(folder)!r}")


@contextmanager
def lock_output_folder(folder: Path, what: str) -> Iterator[None]:
    """Hold the run/study folder's lock (``results.folder_lock``) for the whole launch:
    two processes on one folder (a second ``--resume`` beside the first) would train the
    same trials twice into the same files. Taken once the input is checked, so bad input
    leaves nothing behind; a folder another process holds is refused at once."""
    with ExitStack() as held:
        try:
            held.enter_context(R.folder_lock(folder.parent, folder.name))
        except R.FolderBusy:
            fail("name", folder.name, f"a {what} no other process is running ({folder.parent}"
                                      f"/.{folder.name}.lock is held: wait for that {what} "
                                      "or stop it)")
        yield


def check_resources(preset: TrainPreset, available: float,
                    custom: dict[str, float] | None = None) -> None:
    """Refuse runs whose trial could never be scheduled (Tune would wait silently):
    more CPUs than the cluster has, or a custom resource no node offers enough of
    (``custom``: the most of each that one node has; read from Ray when not given)."""
    need = required_cpus(preset)
    if need > available:
        field, other = (("num_env_runners", "learner_cpus") if preset.num_env_runners
                        else ("learner_cpus", "num_env_runners"))
        allowed = int(available) - getattr(preset, other)
        fail(field, getattr(preset, field),
             f"at most {allowed} on this Ray cluster ({available:g} CPUs; a run needs "
             f"learner_cpus + num_env_runners = {need})")
    if preset.custom_resources and custom is None:
        custom = largest_per_node()
    for name, amount in preset.custom_resources.items():
        have = (custom or {}).get(name, 0.0)
        if amount > have:
            fail("custom_resources", {name: amount},
                 f"resources one node of this Ray cluster has ({name}: at most {have:g} on "
                 f"a node; start nodes with `ray start --resources '{{\"{name}\": 1}}'`, "
                 "docs/cluster.md)")


def largest_per_node() -> dict[str, float]:
    """The most of each resource one live node of the connected Ray cluster has ({} if
    Ray is not running here): a run's first bundle must fit on one node."""
    import ray

    if not ray.is_initialized():
        return {}
    out: dict[str, float] = {}
    for node in ray.nodes():
        if node.get("Alive"):
            for name, amount in node.get("Resources", {}).items():
                out[name] = max(out.get(name, 0.0), float(amount))
    return out


# Same seed, same run: RLlib iterates over sets of module ids while sampling, and a set's
# order follows the string hash seed, so every Ray worker of ours gets a fixed one.
RUNTIME_ENV = {"env_vars": {"PYTHONHASHSEED": "0"}}


def check_address(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast when nothing answers at a cluster address: ``ray.init`` would retry for
    minutes, printing GCS warnings. ``auto`` (the cluster this node belongs to) is Ray's."""
    import socket

    if address in ("auto", "local"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        fail("address", address, "HOST:PORT of a Ray cluster's head (or ray://HOST:PORT, "
             "or auto)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        fail("address", address, f"the address of a running Ray cluster: nothing answers at "
             f"{host}:{port} ({e.strerror or e}); start one with `ray start --head --port "
             f"{port}` (docs/cluster.md)")


def init_ray(address: str | None) -> float:
    """Join the Ray cluster at ``address`` or start a local Ray (once); its CPU count
    (``cluster_resources()`` has the rest)."""
    import ray

    if not ray.is_initialized():
        if address:
            check_address(address)
            ray.init(address=address, log_to_driver=False, runtime_env=RUNTIME_ENV)
        else:
            ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False,
                     runtime_env=RUNTIME_ENV)
    return float(ray.cluster_resources().get("CPU", 0))


def train(algo: str, env_config: dict[str, Any], preset_name: str = "smoke", *,
          seed: int = 0, results_dir: str | Path = "results", name: str | None = None,
          address: str | None = None, resume: bool = False,
          preset_overrides: dict[str, Any] | None = None, init_from: str | Path | None = None,
          settings_overrides: dict[str, Any] | None = None, console=None) -> Path:
    """Run (or resume) one Tune training run; returns its run folder.

    ``init_from``: a checkpoint (or run folder) whose module weights the run starts from
    (adaptation / fine-tuning); recorded in the run folder's RUN_FILE.
    ``settings_overrides``: the algorithm's own settings over its preset's (MetaPOCA's).
    """
    spec = make_run_spec(algo, env_config, preset_name, seed=seed,
                         preset_overrides=preset_overrides, init_from=init_from,
                         settings_overrides=settings_overrides)
    return train_spec(spec, results_dir=results_dir, name=name, address=address,
                      resume=resume, console=console)


def train_spec(spec: RunSpec, *, results_dir: str | Path = "results", name: str | None = None,
               address: str | None = None, resume: bool = False, console=None) -> Path:
    """Run (or resume) the training run ``spec`` through Tune; returns its run folder."""
    from rich.console import Console

    console = console or Console()
    preset, env = spec.preset, spec.env
    name = name or f"{spec.algo}_{scenario_label(env.scenario)}_{spec.preset_name}_s{spec.seed}"
    run_dir = Path(results_dir).resolve() / name
    check_output_folder(run_dir, R.RUN_FILE, "run", resume)
    spec.algorithm_config()  # every setting checked before Ray starts
    check_resources(preset, init_ray(address))

    with lock_output_folder(run_dir, "run"):
        return _fit_run(spec, run_dir, name, resume, console)


def _fit_run(spec: RunSpec, run_dir: Path, name: str, resume: bool, console) -> Path:
    """``train_spec``'s Tune part, under the run folder's lock."""
    from ray import tune

    preset, env = spec.preset, spec.env
    if not resume:
        run_dir.mkdir(parents=True)
        R.write_yaml(run_dir / R.RUN_FILE, spec.metadata())
        if spec.init_from is not None and preset.evaluation_interval > 0:
            start = evaluate_start_weights(Path(spec.init_from), env,
                                           preset.evaluation_episodes, spec.seed)
            R.write_json(run_dir / R.EVAL_FILE, [start])
            console.print(f"start weights on {env.scenario}: coverage "
                          f"{start['coverage']:.3f} over {preset.evaluation_episodes} episodes "
                          "(evaluation 0)")
    trainable = tune.with_resources(tune.with_parameters(train_run, spec=spec),
                                    trial_resources(preset))
    if resume:
        console.print(f"resuming {run_dir}")
        for line in restore_missing_checkpoints(run_dir / R.TUNE_DIR):
            console.print(line)
        # The run config, the progress callback included, is restored from tuner.pkl.
        tuner = tune.Tuner.restore(str(run_dir / R.TUNE_DIR), trainable=trainable,
                                   resume_errored=True, resume_unfinished=True)
    else:
        tuner = tune.Tuner(
            trainable,
            tune_config=tune.TuneConfig(num_samples=1,
                                        trial_dirname_creator=lambda t: R.TRAIN_TRIAL),
            run_config=tune.RunConfig(
                storage_path=str(run_dir), name=R.TUNE_DIR, verbose=0,
                checkpoint_config=checkpoint_config(preset),
                failure_config=tune.FailureConfig(max_failures=2),
                callbacks=[RunProgress(preset.total_env_steps, run_dir=run_dir)]))
    console.print(f"[bold]{spec.algo}[/] on {env.scenario} ({env.team.wheeled} wheeled + "
                  f"{env.team.quad} quads, comm {env.comm_scheme}), preset "
                  f"{spec.preset_name}: {preset.total_env_steps:,} env steps in "
                  f"{spec.iterations} iterations -> {run_dir}")
    grid = tuner.fit()
    errors = [r.error for r in grid if r.error]
    if errors:  # the cause's own line, not Ray's traceback around it
        raise RuntimeError(f"training failed: {str(errors[0]).strip().splitlines()[-1]}")
    steps = max((int(r.metrics.get(R.ENV_STEPS, 0)) for r in grid), default=0)
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
    from rl_scan.envs.episode import run_episode

    core, team = ScanCore(env_cfg), PolicyTeam(load_actors(Path(checkpoint)))
    torch.manual_seed(seed)
    episodes_metrics = [run_episode(core, team, seed=10_000 * (seed + 1) + i)
                        for i in range(episodes)]
    entry = {R.ITERATION: 0, "env_steps": 0, R.TIME_TOTAL: 0.0,
             R.EPISODE_RETURN: float(np.mean([
                 sum(m[k] * n for k, n in zip(M.RETURN_BY_KIND.values(),
                                              (env_cfg.team.wheeled, env_cfg.team.quad)))
                 for m in episodes_metrics]))}
    for key in M.EPISODE_METRICS:
        values = np.array([m[key] for m in episodes_metrics], dtype=float)
        if key in M.STEPS_TO.values():  # as the callback: the mean over runs reaching it
            entry[M.REACHED[key]] = float(np.mean(~np.isnan(values)))
            values = values[~np.isnan(values)]
        if len(values):
            entry[key] = float(values.mean())
    return entry
