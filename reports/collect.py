"""Read every result under a folder into ``RunRecord``s, whatever produced it.

Understood layouts (all written by rl-scan):
  * a training run folder (``run.yaml``; ``rl-scan train``/``meta-train``/``adapt``);
  * an ablation study folder (``study.yaml``; ``rl-scan ablate``), one record per trial;
  * a meta-MRSS experiment folder (``pretrain/`` and ``adapt/`` run folders).
Runs still going (or killed) are read as far as they got; ``planned`` says what a study
meant to run so a report can say what is missing.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rl_scan.metrics import BEST_EVAL_FILE, EVAL_FILE, PROTOCOL_FILE
from rl_scan.tuning.presets import get_preset


@dataclass
class RunRecord:
    """One training run (one seed of one condition) and its evaluation curve."""

    group: str  # what it belongs to: "ablate-comm", "meta-mrss/adapt", "runs", ...
    condition: str  # e.g. "comm=3", "poca", "meta-mrss on test:0"
    seed: int
    path: Path
    evals: list[dict[str, Any]] = field(default_factory=list)  # eval_metrics.json entries
    eval_episodes: int = 0  # evaluation episodes behind each entry
    env_steps: int = 0
    time_total_s: float = math.nan
    scenario: str = ""
    algo: str = ""
    best_eval: dict[str, Any] | None = None  # best_checkpoint_eval.json (evaluate --best)

    @property
    def curve(self) -> list[tuple[int, float]]:
        return [(int(e["env_steps"]), float(e["coverage"])) for e in self.evals]

    @property
    def final_coverage(self) -> float:
        return float(self.evals[-1]["coverage"]) if self.evals else math.nan

    @property
    def final_success(self) -> float:
        return float(self.evals[-1].get("success", math.nan)) if self.evals else math.nan

    def steps_to(self, coverage: float) -> float:
        """Env steps of the first evaluation whose mean coverage reached ``coverage``
        (NaN if none did): the report's learning / adaptation speed."""
        return next((float(s) for s, c in self.curve if c >= coverage), math.nan)

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.time_total_s if self.time_total_s else math.nan


@dataclass
class Collection:
    runs: list[RunRecord] = field(default_factory=list)
    planned: dict[str, int] = field(default_factory=dict)  # group -> runs it meant to have
    studies: dict[str, dict[str, Any]] = field(default_factory=dict)  # group -> study.yaml


def read_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _progress_tail(folder: Path) -> tuple[int, float]:
    """(env steps, wall seconds) of the last progress.csv row under ``folder``."""
    rows: list[dict[str, str]] = []
    for path in sorted(folder.glob("**/progress.csv")):
        with open(path) as f:
            rows += list(csv.DictReader(f))
    if not rows:
        return 0, math.nan
    last = max(rows, key=lambda r: float(r.get("num_env_steps_sampled_lifetime") or 0))
    return (int(float(last.get("num_env_steps_sampled_lifetime") or 0)),
            float(last.get("time_total_s") or math.nan))


def read_run(folder: Path, group: str, condition: str | None = None) -> RunRecord:
    meta = yaml.safe_load((folder / "run.yaml").read_text()) or {}
    steps, seconds = _progress_tail(folder / "tune")
    env = meta.get("env_config", {})
    return RunRecord(group=group, condition=condition or meta.get("algo", "?"),
                     seed=int(meta.get("seed", 0)), path=folder,
                     evals=read_json(folder / EVAL_FILE) or [],
                     eval_episodes=int(meta.get("preset_config", {}).get(
                         "evaluation_episodes", 0)),
                     env_steps=steps, time_total_s=seconds,
                     scenario=env.get("scenario", ""), algo=meta.get("algo", ""),
                     best_eval=read_json(folder / BEST_EVAL_FILE))


def read_study(folder: Path) -> tuple[list[RunRecord], dict[str, Any]]:
    study = yaml.safe_load((folder / "study.yaml").read_text()) or {}
    preset = get_preset(study.get("preset", "quick"), study.get("preset_overrides") or {})
    group = folder.name
    records = []
    for trial in sorted(p for p in (folder / "tune").glob("*") if p.is_dir()):
        cond = read_json(trial / "condition.json")
        if cond is None:
            continue
        params = cond.get("params", {})
        label = (str(params["condition"]) if "condition" in params else
                 ", ".join(f"{k}={_short(v)}" for k, v in sorted(params.items()) if k != "seed"))
        steps, seconds = _progress_tail(trial)
        records.append(RunRecord(group=group, condition=label, seed=int(params.get("seed", 0)),
                                 path=trial, evals=read_json(trial / EVAL_FILE) or [],
                                 eval_episodes=preset.evaluation_episodes, env_steps=steps,
                                 time_total_s=seconds,
                                 scenario=cond.get("env_config", {}).get("scenario", "ablation"),
                                 algo=cond.get("algo", ""),
                                 best_eval=read_json(trial / BEST_EVAL_FILE)))
    return records, study


def _short(v: Any) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def collect(root: str | Path) -> Collection:
    """Every run and study under ``root`` (``root`` itself may be one of them)."""
    root = Path(root).resolve()
    out = Collection()
    for study_file in sorted(root.glob("**/study.yaml")):
        records, study = read_study(study_file.parent)
        out.runs += records
        out.studies[study_file.parent.name] = study
        out.planned[study_file.parent.name] = int(study.get("trials", len(records)))
    for run_file in sorted(root.glob("**/run.yaml")):
        folder = run_file.parent
        if folder.parent.name in ("pretrain", "adapt"):  # a meta-MRSS experiment
            group = f"{folder.parent.parent.name}/{folder.parent.name}"
            record = read_run(folder, group, folder.name.split("_")[0])  # the method
            plan = read_yaml(folder.parent.parent / PROTOCOL_FILE) or {}
            planned = (plan.get("planned_runs") or {}).get(folder.parent.name)
            if planned:
                out.planned[group] = int(planned)
        else:
            record = read_run(folder, "runs", None)
            record.condition = f"{record.algo} on {record.scenario}"
        out.runs.append(record)
    return out
