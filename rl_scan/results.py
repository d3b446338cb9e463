"""The results format, in one place: folder layouts, file names, result keys, readers/writers.

Every rl-scan command writes under a results folder, and ``rl-scan report`` reads it back:

  run folder          RUN_FILE (what ran: algorithm, preset, env config, seed, commit),
                      EVAL_FILE (one entry per training-time evaluation), BEST_EVAL_FILE
                      (``evaluate --best``), NODES_FILE (the Ray nodes it ran on), META_FILE
                      (MetaPOCA: diagnostics per meta-iteration), DONE (a
                      finished run of an experiment), and TUNE_DIR/trial/ (Tune:
                      progress.csv, result.json, checkpoints; NONFINITE_FILE after a NaN).
  study folder        STUDY_FILE, OPTUNA_DB, TRIALS_DIR/<trial id>/ (one run folder per
                      trial) and TUNE_DIR/<trial id>/ (Tune's) (``rl-scan ablate``).
  experiment folder   PROTOCOL_FILE, PRETRAIN_DIR/<run>/, ADAPT_DIR/<run>/, LOG_DIR/,
                      SUMMARY_FILE, TABLE_FILE (``rl-scan experiment meta-mrss``).
  report folder       report.md/.html, figures/, marl_eval.json and REPORT_RUNS_FILE, from
                      which ``rl-scan report`` rebuilds the report (``rl-scan report``).

Our own files live beside Tune's folder, never in it: when an experiment is restored, Tune
copies every JSON file under its folder to a staging copy and later syncs that copy back,
which would overwrite evaluations written since. This module imports no Ray (reports
and the command line read results without starting it).
"""

from __future__ import annotations

import csv
import json
import math
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

RUN_FILE = "run.yaml"
EVAL_FILE = "eval_metrics.json"  # every training-time evaluation
BEST_EVAL_FILE = "best_checkpoint_eval.json"  # the best kept checkpoint, re-evaluated
TUNE_DIR = "tune"
TRIALS_DIR = "trials"  # a study's run folders, one per trial, named by Tune's trial id
TRAIN_TRIAL = "trial"  # the Tune trial folder of a single run: RUN/TUNE_DIR/TRAIN_TRIAL
PROGRESS_FILE = "progress.csv"  # Tune's, one row per iteration
RESULT_FILE = "result.json"  # Tune's, one JSON result per line: what the reports read
STUDY_FILE = "study.yaml"
OPTUNA_DB = "optuna.db"
PROTOCOL_FILE = "protocol.yaml"  # a meta-MRSS experiment's plan (methods, tests, seeds, runs)
HETERO_MAP = "hetero_map.json"  # a hetero-map study's points (greedy coverages per team)
PRETRAIN_DIR, ADAPT_DIR = "pretrain", "adapt"
SUMMARY_FILE, TABLE_FILE = "summary.json", "table.md"
DONE = "DONE"  # a finished run of an experiment (skipped when the experiment is re-run)
REPORT_RUNS_FILE = "runs.json"  # in a report folder: every run it read (it rebuilds from this)
NODES_FILE = "nodes.json"  # in a run folder: the Ray nodes its trial ran on, per iteration span
NODES = "nodes"  # result key: this process's node and its remote env runners' nodes
CHECKPOINT_STEPS = "rl_scan_env_steps.json"  # in a checkpoint: env steps it was taken at
NONFINITE_FILE = "nonfinite_loss.txt"  # in a trial folder: why it stopped (never retried)
LOG_DIR = "logs"  # stderr of every experiment run started in a child process

# Keys of RLlib's training results (``Algorithm.train()``) that rl-scan reads.
ENV_STEPS = "num_env_steps_sampled_lifetime"  # == ray.rllib.utils.metrics' constant (tested)
ITERATION = "training_iteration"
TIME_TOTAL = "time_total_s"
# The run's own training seconds, summed by the driver and carried in its checkpoints: Tune
# recomputes time_total_s from the checkpoint it restores, so a final result reported again
# after a restore from an earlier checkpoint would get another time.
RUN_SECONDS = "rl_scan_run_seconds"
EVALUATION = "evaluation"
ENV_RUNNERS = "env_runners"
EPISODE_RETURN = "episode_return_mean"
MODULE_RETURNS = "module_episode_returns_mean"

# Keys rl-scan adds to the results.
SCAN_PREFIX = "scan/"  # episode metrics (rl_scan.metrics names) logged by the callback
EVAL_SCORE = "eval_coverage"  # the latest evaluation's mean coverage (checkpoint score)
EVALUATED = "evaluated"  # True in the results of an iteration that ran an evaluation
LEARNER_THREADS = "learner_threads"  # torch threads of the training process (learner_cpus)
LEARNERS = "learners"  # RLlib's per-module learner results: learners/<module>/<key>
EV_VALUE = "explained_variance_v"  # POCA, under the critic: V at sampling time vs returns
EV_BASELINE = "explained_variance_baseline"  # POCA, under each actor module: its b_i
META_BEFORE = "meta/coverage_before_adaptation"  # MetaPOCA: support episodes' coverage
META_AFTER = "meta/coverage_after_adaptation"  # MetaPOCA: query episodes' coverage
META_DELTA_NORM = "meta/delta_norm"  # MetaPOCA: mean over tasks of ||theta'_i - theta||
META_DELTA_COSINE = "meta/delta_cosine"  # MetaPOCA: mean cosine between tasks' delta_i
META_TERM_RESULTS = "meta/maml_term"  # MetaPOCA: learner results at theta + delta_i
META_FILE = "meta_diagnostics.json"  # in a MetaPOCA run folder: one entry per meta-iteration


PLACEMENT_SETTINGS = ("num_env_runners", "learner_cpus", "custom_resources",
                      "evaluation_interval", "evaluation_episodes", "checkpoint_frequency")
"""Preset fields of a RUN_FILE that say where a run trains and how often it is evaluated
and saved, not what it learns."""


def learning_settings(run_meta: dict[str, Any]) -> dict[str, Any]:
    """A RUN_FILE's preset values that shape what the run learns (budget, batch, minibatch,
    epochs, lr, envs per runner, schedules, sampler, the preset's env overrides): all but
    PLACEMENT_SETTINGS. Two runs of one algorithm and EnvConfig with equal ones are the same
    trial (reports/borrow.py)."""
    return {k: v for k, v in (run_meta.get("preset_config") or {}).items()
            if k not in PLACEMENT_SETTINGS}


def scan_key(metric: str) -> str:
    """The result key of an episode metric: 'coverage' -> 'scan/coverage'."""
    return SCAN_PREFIX + metric


def evaluation_of(result: dict[str, Any]) -> dict[str, Any]:
    """The env-runner metrics of a result's evaluation ({} if it has none)."""
    return result.get(EVALUATION, {}).get(ENV_RUNNERS, {})


def eval_entry(result: dict[str, Any]) -> dict[str, Any]:
    """One EVAL_FILE entry from a result whose iteration ran an evaluation."""
    evaluation = evaluation_of(result)
    return {
        ITERATION: result.get(ITERATION, 0),
        "env_steps": result.get(ENV_STEPS),
        TIME_TOTAL: result.get(RUN_SECONDS, result.get(TIME_TOTAL)),
        EPISODE_RETURN: evaluation.get(EPISODE_RETURN),
        "module_returns": evaluation.get(MODULE_RETURNS, {}),
        **{k[len(SCAN_PREFIX):]: v for k, v in evaluation.items() if k.startswith(SCAN_PREFIX)},
    }


def append_eval(folder: Path, entry: dict[str, Any]) -> None:
    """Append an evaluation entry to a run folder's EVAL_FILE.

    After a restore, iterations past the checkpoint run again: their new entries win.
    """
    path = Path(folder) / EVAL_FILE
    entries = read_json(path) or []
    entries = [e for e in entries if e[ITERATION] < entry[ITERATION]]
    write_json(path, [*entries, entry])


def append_meta(folder: Path, result: dict[str, Any]) -> None:
    """Add a MetaPOCA result's diagnostics to its run folder's META_FILE (an iteration run
    again after a restore replaces its entry)."""
    path = Path(folder) / META_FILE
    entry = {ITERATION: result.get(ITERATION, 0), "env_steps": result.get(ENV_STEPS),
             "before": result.get(META_BEFORE), "after": result.get(META_AFTER),
             "delta_norm": result.get(META_DELTA_NORM),
             "delta_cosine": result.get(META_DELTA_COSINE)}
    entries = [e for e in read_json(path) or [] if e[ITERATION] < entry[ITERATION]]
    write_json(path, [*entries, entry])


def adaptation_gain(entries: list[dict[str, Any]]) -> dict[str, float]:
    """Mean support->query coverage gain, ||delta|| and cosine between the tasks' deltas
    over the last half of a MetaPOCA run's meta-iterations (nan where nothing was
    recorded: no entries, one task per iteration, runs older than the cosine)."""
    last = entries[len(entries) // 2:]

    def mean(values: list[Any]) -> float:
        ok = [float(v) for v in values if v is not None and v == v]  # v == v: not nan
        return sum(ok) / len(ok) if ok else float("nan")

    return {"gain": mean([e["after"] - e["before"] for e in last
                          if e.get("after") is not None and e.get("before") is not None]),
            "delta_norm": mean([e.get("delta_norm") for e in last]),
            "delta_cosine": mean([e.get("delta_cosine") for e in last]),
            "iterations": len(last)}


def record_nodes(folder: Path, iteration: int, nodes: dict[str, Any] | None) -> None:
    """Add to a run folder's NODES_FILE when the run's placement changes (its start, and
    a restore onto other nodes): entries ``{"from_iteration": k, "trainable": ...,
    "env_runners": [...]}``."""
    if not nodes:
        return
    path = Path(folder) / NODES_FILE
    entries = read_json(path) or []
    last = entries[-1] if entries else {}
    if {k: last.get(k) for k in nodes} != nodes:
        write_json(path, [*entries, {"from_iteration": iteration, **nodes}])


def jsonable(data: Any) -> Any:
    """``data`` as plain JSON values: numpy numbers and arrays as lists, other objects as text."""
    return json.loads(json.dumps(data, default=lambda o: o.tolist() if hasattr(o, "tolist")
                                 else str(o)))


def write_json(path: Path, data: Any) -> None:
    """JSON with NaN and numpy numbers written as floats."""
    Path(path).write_text(json.dumps(data, indent=1, default=float))


def write_yaml(path: Path, data: dict[str, Any]) -> None:
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))


def read_yaml(path: Path) -> Any:
    """A YAML file's content, or None if it is missing or malformed (a run still starting)."""
    try:
        return yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError):
        return None


def read_json(path: Path) -> Any:
    """A JSON file's content, or None if it is missing or malformed."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def read_evals(folder: Path) -> list[dict[str, Any]]:
    return read_json(Path(folder) / EVAL_FILE) or []


class FolderBusy(RuntimeError):
    """Another process holds the lock of a run or study folder (``folder_lock``)."""


_HELD_LOCKS = threading.local()  # per thread: the lock files it holds (folder_lock)


@contextmanager
def folder_lock(parent: Path, name: str, wait_s: float = 0.0) -> Iterator[None]:
    """An exclusive lock on ``parent/.NAME.lock``, held by one process at a time and
    released when it ends (killed or not): two processes resuming one run or study would
    train the same trials twice into the same files. Waits up to ``wait_s`` (for a run
    still stopping), then raises ``FolderBusy``. Re-entrant in a thread: the job runner
    holds a run's lock around ``launch.train``, which takes it again (a second flock of
    the same file by one process would wait on itself)."""
    import fcntl

    parent.mkdir(parents=True, exist_ok=True)
    lock = (parent / f".{name}.lock").resolve()
    held = _HELD_LOCKS.__dict__.setdefault("paths", set())
    if lock in held:
        yield
        return
    with open(lock, "a+") as f:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise FolderBusy(f"{lock} is held by another process") from None
                time.sleep(1.0)
        held.add(lock)
        try:
            yield
        finally:
            held.discard(lock)


def is_run_folder(folder: Path) -> bool:
    return (Path(folder) / RUN_FILE).is_file()


def trial_run_dir(study_dir: Path, trial_id: str) -> Path:
    """The run folder of one study trial."""
    return Path(study_dir) / TRIALS_DIR / trial_id


def tune_trial_dir(run_dir: Path) -> Path:
    """Tune's trial folder of a run folder (progress, checkpoints)."""
    run_dir = Path(run_dir)
    trial = (read_yaml(run_dir / RUN_FILE) or {}).get("tune_trial")
    if trial:  # a study trial: STUDY/trials/<id> -> STUDY/tune/<id>
        return run_dir.parent.parent / TUNE_DIR / trial
    return run_dir / TUNE_DIR / TRAIN_TRIAL


def run_dir_of(path: Path) -> Path | None:
    """The run folder that ``path`` (a checkpoint, a Tune trial folder) belongs to."""
    path = Path(path)
    for parent in [path, *path.parents]:
        if is_run_folder(parent):
            return parent
        if parent.parent.name == TUNE_DIR and (parent.parent.parent / STUDY_FILE).is_file():
            folder = trial_run_dir(parent.parent.parent, parent.name)
            return folder if is_run_folder(folder) else None
    return None


def run_meta_of(path: Path) -> dict[str, Any]:
    """The RUN_FILE of the run that ``path`` belongs to, or {}."""
    folder = run_dir_of(path)
    return (read_yaml(folder / RUN_FILE) or {}) if folder else {}


def progress_rows(folder: Path) -> list[dict[str, Any]]:
    """Every Tune result of the trials anywhere under ``folder``, one per iteration in
    order, flattened with "/" as progress.csv names columns
    (``learners/critic/explained_variance_v``).

    Neither of Tune's logs holds every iteration. After a driver resume Tune appends
    PROGRESS_FILE rows with the first new result's keys under the file's old header, so
    those rows do not line up with it (they are skipped where their length shows it). After
    a trial restore, RESULT_FILE is copied back from a storage copy taken before the last
    result was logged, losing it. So each iteration comes from RESULT_FILE where it is
    there and from an aligned PROGRESS_FILE row otherwise; an iteration logged twice (run
    again after a restore) keeps its last result, the one training went on from."""
    trials = sorted({p.parent for name in (RESULT_FILE, PROGRESS_FILE)
                     for p in Path(folder).glob(f"**/{name}")})
    rows: list[dict[str, Any]] = []
    for trial in trials:
        by_iteration = {int(float(r[ITERATION])): r for r in _aligned_csv(trial / PROGRESS_FILE)
                        if r.get(ITERATION)}
        if (trial / RESULT_FILE).is_file():
            with open(trial / RESULT_FILE) as f:
                for line in filter(str.strip, f):
                    result = json.loads(line)
                    result.pop("config", None)
                    if ITERATION in result:
                        by_iteration[int(result[ITERATION])] = _flat(result)
        rows += [by_iteration[i] for i in sorted(by_iteration)]
    return rows


def _aligned_csv(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV file that have as many fields as its header."""
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        header, *rows = list(csv.reader(f)) or [[]]
    return [dict(zip(header, row)) for row in rows if len(row) == len(header)]


def _flat(result: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested result as one level, keys joined with "/" (Tune's flatten_dict)."""
    out: dict[str, Any] = {}
    for key, value in result.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}/"))
        else:
            out[prefix + key] = value
    return out


def critic_diagnostics(rows: list[dict[str, Any]]) -> dict[str, list[tuple[int, float]]]:
    """POCA's explained variances over training from progress rows: ``V`` and ``b_<kind>``
    -> [(env steps, value)] (empty for runs without a POCA critic)."""
    out: dict[str, list[tuple[int, float]]] = {}
    for row in sorted(rows, key=lambda r: float(r.get(ENV_STEPS) or 0)):
        for key, value in row.items():
            parts = key.split("/")
            if len(parts) != 3 or parts[0] != LEARNERS or value in ("", None):
                continue
            name = ("V" if parts[2] == EV_VALUE else
                    f"b_{parts[1]}" if parts[2] == EV_BASELINE else None)
            if name is not None and not math.isnan(float(value)):
                out.setdefault(name, []).append((int(float(row[ENV_STEPS])), float(value)))
    return out


def progress_tail(folder: Path, rows: list[dict[str, Any]] | None = None
                  ) -> tuple[int, float]:
    """(env steps, wall seconds) of the last Tune progress row anywhere under ``folder``
    (or of ``rows`` already read from it)."""
    rows = progress_rows(folder) if rows is None else rows
    if not rows:
        return 0, math.nan
    last = max(rows, key=lambda r: float(r.get(ENV_STEPS) or 0))
    return int(float(last.get(ENV_STEPS) or 0)), float(last.get(TIME_TOTAL) or math.nan)

