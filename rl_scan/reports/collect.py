"""Read every run under a folder into ``RunRecord``s, grouped as the report shows them.

A run is any run folder of ``rl_scan.results`` (it has a RUN_FILE), and its group is
where it sits: the trials of one ablation study, one kind of run of a meta-MRSS
experiment (pre-training or adaptation), or loose training runs ("runs"). Each group
gets the ``ReportSpec`` of the study registry (comparisons, the paper's column). Runs
still going (or killed) are read as far as they got; ``planned`` says what a study or
experiment meant to run so a report can say what is missing.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from rl_scan import metrics as M
from rl_scan import results as R
from rl_scan.config import ConfigError
from rl_scan.studies import META_MRSS_REPORT, STUDIES, ReportSpec

LOOSE = "runs"  # the group of training runs that belong to no study or experiment


@dataclass
class RunRecord:
    """One training run (one seed of one condition) and its evaluation curve."""

    group: str  # what it belongs to: "ablate-comm-quick", "meta-mrss/adapt", "runs", ...
    condition: str  # e.g. "3", "poca", "meta-mrss", "poca on ablation"
    seed: int
    path: Path
    evals: list[dict[str, Any]] = field(default_factory=list)  # EVAL_FILE entries
    eval_episodes: int = 0  # evaluation episodes behind each entry
    env_steps: int = 0
    time_total_s: float = math.nan
    scenario: str = ""
    algo: str = ""
    best_eval: dict[str, Any] | None = None  # BEST_EVAL_FILE (evaluate --best)
    critic: dict[str, list[tuple[int, float]]] = field(default_factory=dict)
    """POCA's explained variances over training ("V", "b_<kind>"), from Tune's progress."""
    meta: list[dict[str, Any]] = field(default_factory=list)
    """A MetaPOCA run's META_FILE entries (one per meta-iteration), kept in runs.json so a
    rebuilt report still tables the adaptation gain."""
    learning: dict[str, Any] = field(default_factory=dict)
    """Its preset's settings that shape what it learns (``results.learning_settings``);
    empty in runs.json files written before them."""
    borrowed_from: tuple[str, str] | None = None
    """(group, condition) this run was trained as, if another study's trial of the same
    config stands in for one its group did not train (``reports.borrow``; never saved)."""

    @property
    def curve(self) -> list[tuple[int, float]]:
        return [(int(e["env_steps"]), float(e["coverage"])) for e in self.evals]

    @property
    def final_coverage(self) -> float:
        return float(self.evals[-1]["coverage"]) if self.evals else math.nan

    @property
    def final_success(self) -> float:
        return float(self.evals[-1].get("success", math.nan)) if self.evals else math.nan

    @property
    def final_scan_steps(self) -> float:
        """Episode steps to 95 % coverage at the final evaluation, an episode that never
        gets there counted as its whole length (censored; NaN without the figures): how fast
        the trained team scans, which final coverage stops showing once every team ends
        near 100 %."""
        last = self.evals[-1] if self.evals else {}
        key = M.STEPS_TO[M.SUCCESS_COVERAGE]
        reached, length = last.get(M.REACHED[key]), last.get(M.EPISODE_STEPS)
        if reached is None or length is None:
            return math.nan
        steps = float(last[key]) if reached else 0.0
        return reached * steps + (1.0 - reached) * float(length)

    def steps_to(self, coverage: float) -> float:
        """Env steps of the first of two consecutive evaluations at or above ``coverage``
        (``metrics.steps_to_reach``; NaN if never): the report's learning speed."""
        first = M.steps_to_reach(self.curve, coverage)
        return math.nan if first is None else float(first)

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.time_total_s if self.time_total_s else math.nan

    def to_json(self) -> dict[str, Any]:
        data = {**asdict(self), "path": str(self.path)}
        data.pop("borrowed_from")  # derived on every build (reports.borrow)
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RunRecord:
        critic = {k: [tuple(p) for p in v] for k, v in (data.get("critic") or {}).items()}
        return cls(**{**data, "path": Path(data["path"]), "critic": critic})


@dataclass
class Collection:
    runs: list[RunRecord] = field(default_factory=list)
    planned: dict[str, int] = field(default_factory=dict)  # group -> runs it meant to have
    reports: dict[str, ReportSpec] = field(default_factory=dict)  # group -> what to compare
    kinds: dict[str, str] = field(default_factory=dict)
    """group -> what it is: "study:<name>", "meta:<pretrain|adapt>" or "runs" (loose)."""
    envs: dict[str, dict[str, Any]] = field(default_factory=dict)
    """study group -> the EnvConfig overrides every trial of it ran with (``--set``)."""
    rebuilt_from: str = ""
    """The earlier report file these runs were read from ("" for run folders)."""


def read_run(folder: Path, group: str, condition: str) -> RunRecord:
    meta = R.read_yaml(folder / R.RUN_FILE) or {}
    rows = R.progress_rows(R.tune_trial_dir(folder))  # read once: tail and diagnostics
    steps, seconds = R.progress_tail(folder, rows)
    critic = R.critic_diagnostics(rows)
    return RunRecord(group=group, condition=condition, seed=int(meta.get("seed", 0)),
                     path=folder, evals=R.read_evals(folder),
                     eval_episodes=int((meta.get("preset_config") or {}).get(
                         "evaluation_episodes", 0)), learning=R.learning_settings(meta),
                     env_steps=steps, time_total_s=seconds,
                     scenario=(meta.get("env_config") or {}).get("scenario", ""),
                     algo=meta.get("algo", ""),
                     best_eval=R.read_json(folder / R.BEST_EVAL_FILE), critic=critic,
                     meta=R.read_json(folder / R.META_FILE) or [])


def trial_condition(params: dict[str, Any]) -> str:
    """A study trial's condition label: its condition, or its searched values."""
    if "condition" in params:
        return str(params["condition"])
    return ", ".join(f"{k}={_short(v)}" for k, v in sorted(params.items()) if k != "seed")


def _short(v: Any) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def _place(folder: Path, meta: dict[str, Any], out: Collection) -> tuple[str, str]:
    """(group, condition) of a run folder; records the group's plan and kind."""
    parent, top = folder.parent, folder.parent.parent
    if parent.name == R.TRIALS_DIR and (top / R.STUDY_FILE).is_file():
        study = R.read_yaml(top / R.STUDY_FILE) or {}
        out.planned[top.name] = int(study.get("trials", 0))
        out.kinds[top.name] = f"study:{study.get('study', '')}"
        out.envs[top.name] = study.get("env_config") or {}
        return top.name, trial_condition(meta.get("params") or {})
    if parent.name in (R.PRETRAIN_DIR, R.ADAPT_DIR):  # a meta-MRSS experiment
        group = f"{top.name}/{parent.name}"
        plan = R.read_yaml(top / R.PROTOCOL_FILE) or {}
        planned = (plan.get("planned_runs") or {}).get(parent.name)
        if planned:
            out.planned[group] = int(planned)
        out.kinds[group] = f"meta:{parent.name}"
        return group, folder.name.split("_")[0]  # the method
    out.kinds[LOOSE] = LOOSE
    return LOOSE, f"{meta.get('algo', '?')} on {(meta.get('env_config') or {}).get('scenario')}"


def _specs(out: Collection) -> None:
    """Each group's ReportSpec: the one kept by the report this was rebuilt from (with
    the registry's claims and speed ratio if it predates them), else the one of its kind."""
    for group, kind in out.kinds.items():
        known = _spec_of_kind(out, group, kind)
        kept = out.reports.get(group)
        out.reports[group] = known if kept is None else replace(
            kept, claims=kept.claims or known.claims,
            speed_ratio=kept.speed_ratio or known.speed_ratio)


def _spec_of_kind(out: Collection, group: str, kind: str) -> ReportSpec:
    """A study's from the registry, meta-MRSS adaptation's, and for loose runs POCA vs PPO
    on each scenario both ran on."""
    if kind.startswith("study:"):
        known = STUDIES.get(kind[len("study:"):])
        return known.report if known else ReportSpec()
    if kind.startswith("meta:"):
        return META_MRSS_REPORT if kind == f"meta:{R.ADAPT_DIR}" else ReportSpec()
    conditions = {r.condition for r in out.runs if r.group == group}
    return ReportSpec(comparisons=tuple(
        (c, "ppo" + c[len("poca"):]) for c in sorted(conditions)
        if c.startswith("poca on ") and "ppo" + c[len("poca"):] in conditions))


def collect(root: str | Path) -> Collection:
    """Every run under ``root`` (``root`` itself may be one), or, for a report folder
    without run folders, the runs its REPORT_RUNS_FILE (or, for reports written before
    that file existed, its marl_eval.json) recorded."""
    root = Path(root).resolve()
    out = Collection()
    for run_file in sorted(root.glob(f"**/{R.RUN_FILE}")):
        folder = run_file.parent
        group, condition = _place(folder, R.read_yaml(run_file) or {}, out)
        out.runs.append(read_run(folder, group, condition))
    if not out.runs and (root / R.REPORT_RUNS_FILE).is_file():
        data = R.read_json(root / R.REPORT_RUNS_FILE) or {}
        out.runs = [RunRecord.from_json(r) for r in data.get("runs", [])]
        out.planned, out.kinds = data.get("planned", {}), data.get("kinds", {})
        out.envs = data.get("envs", {})
        out.reports = {group: ReportSpec(**{
                           **spec, "comparisons": tuple(tuple(p) for p in spec["comparisons"]),
                           "speed_ratio": tuple(spec.get("speed_ratio") or ()) or None})
                       for group, spec in data.get("reports", {}).items()}
        out.rebuilt_from = R.REPORT_RUNS_FILE
    elif not out.runs and (root / MARL_EVAL_FILE).is_file():
        out.runs = read_marl_eval(root)
        out.kinds = {r.group: _kind_from_name(r.group) for r in out.runs}
        out.rebuilt_from = MARL_EVAL_FILE
    _specs(out)
    return out


def add_comparison(data: Collection, compare: str | Path) -> None:
    """Add an earlier report's runs (``read_marl_eval``) and compare each condition of
    this report with its namesake there."""
    path = Path(compare).resolve()
    label = (path if path.is_dir() else path.parent).name
    earlier = read_marl_eval(path, label)
    ours = {(r.group, r.condition) for r in data.runs}
    for group in {r.group for r in earlier}:
        spec = data.reports.get(group, ReportSpec())
        pairs = tuple(sorted({(c, f"{c} [{label}]") for g, c in ours
                              if g == group and any(e.condition == f"{c} [{label}]"
                                                    for e in earlier)}))
        data.reports[group] = replace(spec, comparisons=spec.comparisons + pairs)
    data.runs += earlier


def add_runs(data: Collection, source: str | Path) -> int:
    """Add the runs of ``source`` (a results folder, or a report folder's REPORT_RUNS_FILE)
    to ``data`` as runs of their own groups, unlabelled (``--compare`` labels them): a
    study run in parts (other seeds or conditions, in other sessions or on other
    machines, under one ``--name``) reports as one. A run of the same group, condition,
    seed and scenario already in ``data`` is kept and its namesake skipped; returns how
    many were.
    """
    path = Path(source).resolve()
    if not path.is_dir():
        raise ConfigError(f"add={str(path)!r} is invalid: allowed a results folder or a "
                          f"report folder with its {R.REPORT_RUNS_FILE}")
    earlier = collect(path)
    if not earlier.runs or earlier.rebuilt_from == MARL_EVAL_FILE:
        raise ConfigError(f"add={str(path)!r} is invalid: it holds no run folders and no "
                          f"{R.REPORT_RUNS_FILE} (reports older than that file can only be "
                          "compared: --compare)")
    for group, env in earlier.envs.items():
        if group in data.envs and data.envs[group] != env:
            raise ConfigError(f"add={str(path)!r} is invalid: its study {group!r} ran with "
                              f"env settings {env}, the one here with {data.envs[group]}; "
                              "allowed only parts of one study")
    here = {_run_key(r) for r in data.runs}
    new = [r for r in earlier.runs if _run_key(r) not in here]
    data.runs += new
    for group, planned in earlier.planned.items():
        data.planned[group] = max(planned, data.planned.get(group, 0))
    for mine, theirs in ((data.kinds, earlier.kinds), (data.envs, earlier.envs),
                         (data.reports, earlier.reports)):
        for group, value in theirs.items():
            mine.setdefault(group, value)
    return len(earlier.runs) - len(new)


def _run_key(run: RunRecord) -> tuple[str, str, int, str]:
    """What makes a run a namesake of another: its group, condition and seed, and its
    scenario (a meta-MRSS adaptation group holds one run per method, seed and test scene)."""
    return run.group, run.condition, run.seed, run.scenario


def _kind_from_name(group: str) -> str:
    """A group's kind from its default name (reports older than REPORT_RUNS_FILE)."""
    if group.startswith("ablate-") and group.count("-") >= 2:
        return "study:" + group.split("-")[1]
    if "/" in group:
        return "meta:" + group.rsplit("/", 1)[1]
    return LOOSE


def runs_file(data: Collection) -> dict[str, Any]:
    """REPORT_RUNS_FILE's content: every run as read, and each group's plan and kind."""
    return {"runs": [r.to_json() for r in data.runs if not r.borrowed_from],
            "planned": data.planned,
            "kinds": data.kinds, "envs": data.envs,
            "reports": {group: asdict(spec) for group, spec in data.reports.items()}}


MARL_EVAL_FILE = "marl_eval.json"


def read_marl_eval(path: str | Path, label: str | None = None) -> list[RunRecord]:
    """The runs of an earlier report's ``marl_eval.json`` (a report folder or the file),
    as records whose condition ends in ``[label]`` (if given): curves without their run
    folders, wall times or evaluation episode counts, which the file does not keep."""
    path = Path(path)
    file = path / MARL_EVAL_FILE if path.is_dir() else path
    data = R.read_json(file) if file.is_file() else None
    if not isinstance(data, dict) or not isinstance(data.get("rl-scan"), dict):
        raise ConfigError(f"compare={str(path)!r} is invalid: allowed a report folder or a "
                          "marl_eval.json written by `rl-scan report`")
    runs = []
    for task, algos in data["rl-scan"].items():
        for key, algo_runs in algos.items():
            group, _, condition = key.partition(":")
            for seed, (run_id, steps) in enumerate(sorted(algo_runs.items())):
                evals = [{"env_steps": s["step_count"], "coverage": s["coverage"][0],
                          R.EPISODE_RETURN: s.get("return", [math.nan])[0]}
                         for k, s in sorted(steps.items(), key=lambda kv: _step_index(kv[0]))
                         if k.startswith("step_")]
                final = steps.get("absolute_metrics", {})
                if evals and final.get("success"):
                    evals[-1]["success"] = final["success"][0]
                runs.append(RunRecord(
                    group=group, condition=f"{condition} [{label}]" if label else condition,
                    seed=seed, path=Path(label or group) / f"{condition.replace(' ', '_')}_"
                                                            f"{run_id}", evals=evals,
                    env_steps=int(evals[-1]["env_steps"]) if evals else 0, scenario=task))
    return runs


def _step_index(key: str) -> int:
    return int(key.split("_")[1]) if key.startswith("step_") else -1
