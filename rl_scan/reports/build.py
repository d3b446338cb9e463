"""``rl-scan report RESULTS_DIR``: Markdown + self-contained HTML report with PNG figures.

Per group of runs (an ablation study, a meta-MRSS experiment, loose training runs):
  * learning curves: evaluation coverage over env steps, mean +- std over seeds and a 95 %
    CI band (the t interval of the mean over seeds), the scripted greedy team as a reference
    line;
  * a table per condition: runs, final coverage mean +- std, IQM with a stratified
    bootstrap 95 % CI, success rate with a Wilson 95 % CI over evaluation episodes, and
    the convergence verdict by the rule stated in the report (``CONVERGED``);
  * probability of improvement for the paper's comparisons (POCA vs PPO, hetero vs homo,
    meta-MRSS vs each baseline) and a verdict on each of the paper's claims (``claims``);
  * compute: env steps/s end to end and wall time per run, hardware, package versions.
Headline scores are final-checkpoint scores (the last evaluation of each run). Runs still
going are reported as far as they got, and missing runs are listed. Raw per-run metrics
are exported in marl-eval's JSON layout (``marl_eval.json``).
"""

from __future__ import annotations

import json
import math
import os
import platform
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan.metrics import SPEED_AT
from rl_scan.reports.borrow import borrow_runs, borrowed_lines
from rl_scan.reports.claims import improvement_lines
from rl_scan.reports.collect import (
    MARL_EVAL_FILE,
    Collection,
    RunRecord,
    add_comparison,
    add_runs,
    collect,
    runs_file,
)
from rl_scan.reports.figures import CONVERGED, plot_curves
from rl_scan.reports.hetero_map import hetero_map_lines
from rl_scan.reports.html import to_html
from rl_scan.reports.stats import (
    iqm,
    mean_std,
    stratified_bootstrap_ci,
    wilson_interval,
)
from rl_scan.reports.tables import (
    adaptation_lines,
    best_checkpoint_table,
    critic_lines,
    fmt,
    meta_lines,
)
from rl_scan.results import EPISODE_RETURN, REPORT_RUNS_FILE, read_json
from rl_scan.studies import ReportSpec

RULE = (f"A condition **converged** if the mean over seeds of its final evaluation coverage "
        f"is at least {CONVERGED:.0%}; otherwise it **failed**.")
SPEED = (f"**Learning / adaptation speed** is defined up front as the env steps of the first "
         f"of two consecutive evaluations of a run whose mean coverage reaches {SPEED_AT:.0%} "
         "(one noisy evaluation does not count). A run that never gets there counts as the "
         "env steps of its last evaluation (censored: a lower bound on its speed), so a "
         "condition's mean is over all its runs, with how many reached it.")
DIFFERENCES = (
    "Differences from the paper's set-up: our simulator is a voxel re-implementation of "
    "their Unity scenes (same sensor encoding, robot kinds and reward terms, arena "
    "20 x 20 x 8 m, 0.5 m cells), budgets are those of the preset named in each section "
    "(the paper trained for 8-14 M env steps), and every figure here comes from runs on "
    "this machine.")


def condition_rows(runs: list[RunRecord]) -> list[dict[str, Any]]:
    """One row of statistics per condition (final-checkpoint scores over seeds)."""
    by_cond: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        by_cond[r.condition].append(r)
    rows = []
    for cond, rs in sorted(by_cond.items()):
        scored = [r for r in rs if r.evals]
        finals = [r.final_coverage for r in scored]
        # strata = tasks: the scenario each run was evaluated on
        strata: dict[str, list[float]] = defaultdict(list)
        for r in scored:
            strata[r.scenario].append(r.final_coverage)
        # success over the final evaluations' episodes of the runs that have a figure;
        # reports rebuilt from marl_eval.json know the rates but not the episode counts
        with_success = [r for r in scored if not math.isnan(r.final_success)]
        episodes = sum(r.eval_episodes for r in with_success)
        successes = sum(r.final_success * r.eval_episodes for r in with_success)
        rate = (successes / episodes if episodes else
                float(np.mean([r.final_success for r in with_success])) if with_success
                else math.nan)
        mean, std = mean_std(finals)
        speeds = [r.steps_to(SPEED_AT) for r in scored]
        reached = [x for x in speeds if not math.isnan(x)]
        censored = [r.evals[-1]["env_steps"] if math.isnan(x) else x
                    for r, x in zip(scored, speeds)]
        rows.append({
            "condition": cond, "runs": len(rs), "scored": len(scored),
            "final_mean": mean, "final_std": std, "iqm": iqm(finals) if finals else math.nan,
            "iqm_ci": stratified_bootstrap_ci(list(strata.values())),
            "success": rate, "episodes": episodes,
            "success_ci": wilson_interval(successes, episodes),
            "converged": (not math.isnan(mean)) and mean >= CONVERGED,
            "speed": float(np.mean(censored)) if censored else math.nan,
            "speed_reached": len(reached), "finals": finals,
            "scan_steps": [r.final_scan_steps for r in scored],
            "tasks": [r.scenario for r in scored]})
    return rows


def greedy_reference(scenario: str, episodes: int = 3) -> float:
    """Mean final coverage of the scripted greedy team on a scenario (nan for a scenario
    this checkout cannot build, e.g. a YAML file that has moved: the line is optional)."""
    from rl_scan.config import ConfigError
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.episode import run_episode
    from rl_scan.envs.heuristics import GreedyTeam

    try:
        core = ScanCore({"scenario": scenario})
    except ConfigError:
        return math.nan
    return float(np.mean([run_episode(core, GreedyTeam(core), seed=s)["coverage"]
                          for s in range(episodes)]))


def _table(rows: list[dict[str, Any]], spec: ReportSpec) -> list[str]:
    head = ["condition", "runs", "final coverage % (mean ± std)", "IQM % [95 % CI]",
            "success % [95 % CI] (episodes)", f"env steps to {SPEED_AT:.0%}, censored (reached)",
            "verdict"]
    if spec.paper_column:
        head.append(spec.paper_column)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lo, hi = r["iqm_ci"]
        slo, shi = r["success_ci"]
        cells = [r["condition"], f"{r['scored']}/{r['runs']}",
                 f"{fmt(r['final_mean'])} ± {fmt(r['final_std'])}",
                 f"{fmt(r['iqm'])} [{fmt(lo)}, {fmt(hi)}]",
                 (f"{fmt(r['success'])} [{fmt(slo)}, {fmt(shi)}] ({r['episodes']})"
                  if r["episodes"] else f"{fmt(r['success'])} (runs' mean)"),
                 f"{fmt(r['speed'], False)} ({r['speed_reached']}/{r['scored']})",
                 "converged" if r["converged"] else "failed"]
        if spec.paper_column:
            cells.append(spec.paper.get(r["condition"], "(not in the paper)"))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def marl_eval_json(runs: list[RunRecord]) -> dict[str, Any]:
    """marl-eval's layout: env -> task -> algorithm -> run -> step_k / absolute_metrics."""
    out: dict[str, Any] = {"rl-scan": {}}
    counters: dict[tuple, int] = defaultdict(int)
    for r in runs:
        if r.borrowed_from:  # exported once, as its own study's
            continue
        task = r.scenario or "unknown"
        algo = f"{r.group}:{r.condition}"
        key = (task, algo)
        run_id = f"run_{counters[key]}"
        counters[key] += 1
        steps = {f"step_{i}": {"step_count": int(e["env_steps"]),
                               "coverage": [float(e["coverage"])],
                               "return": [float(e.get(EPISODE_RETURN) or math.nan)]}
                 for i, e in enumerate(r.evals)}
        if r.evals:
            steps["absolute_metrics"] = {"coverage": [r.final_coverage],
                                         "success": [r.final_success]}
        out["rl-scan"].setdefault(task, {}).setdefault(algo, {})[run_id] = steps
    return out


def bench_lines(results_dir: Path) -> list[str]:
    """Figures of any ``rl-scan bench env|train --json`` files in the results folder."""
    lines = []
    for path in sorted(results_dir.glob("**/bench*.json")):
        data = read_json(path)
        if not isinstance(data, dict):
            continue
        load = data.get("load_avg_1m", math.nan)
        if "core_steps_per_s" in data:
            lines += [f"| env only, `{path.name}` (load {load:.2f}) | core "
                      f"{data['core_steps_per_s']:,.0f}, RLlib env "
                      f"{data.get('rllib_steps_per_s', math.nan):,.0f}, PettingZoo "
                      f"{data.get('pettingzoo_steps_per_s', math.nan):,.0f} env steps/s "
                      "(one core, random actions) |"]
        for label, run in (data.get("runs") or {}).items():
            memory = (f"PSS {run['tree_pss_mb']:,.0f} MB" if "tree_pss_mb" in run
                      else f"peak RSS {run.get('peak_rss_mb', math.nan):,.0f} MB")
            lines += [f"| training end to end, `{path.name}` (load {load:.2f}) | {label}: "
                      f"{run.get('env_steps_per_s', math.nan):,.0f} env steps/s, {memory} |"]
    return (["", "| benchmark | figures |", "|---|---|", *lines, ""] if lines else [])


def hardware() -> dict[str, str]:
    cpu = "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in
                   Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    import ray
    import torch

    import rl_scan

    return {"cpu": cpu, "cores": str(os.cpu_count()), "python": platform.python_version(),
            "rl_scan": rl_scan.__version__, "ray": ray.__version__, "torch": torch.__version__}


def _shown(path: Path) -> Path:
    """``path`` relative to the working folder where it lies under it."""
    return path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path


def build_report(results_dir: str | Path, out_dir: str | Path | None = None,
                 reference: bool = True, compare: str | Path | None = None,
                 add: Sequence[str | Path] = ()) -> Path:
    """Write report.md, report.html, figures/*.png and marl_eval.json; returns out_dir.

    ``compare``: an earlier report (its folder or marl_eval.json) whose runs join the same
    groups, labelled with its folder name, each condition compared with its namesake.
    ``add``: results or report folders whose runs join as runs of their own groups
    (``collect.add_runs``: the parts of one study); a run here replaces its namesake."""
    results_dir = Path(results_dir).resolve()
    if not results_dir.is_dir():
        raise ValueError(f"results_dir={str(results_dir)!r} is not a folder")
    out = Path(out_dir).resolve() if out_dir else results_dir / "report"
    data: Collection = collect(results_dir)
    skipped = sum(add_runs(data, source) for source in add)  # refused before writing
    borrowed = len(borrow_runs(data))
    (out / "figures").mkdir(parents=True, exist_ok=True)
    maps = hetero_map_lines(results_dir, out / "figures", data)
    if not data.runs and not maps:
        raise ValueError(f"results_dir={str(results_dir)!r} holds no rl-scan runs or studies")
    if compare is not None:
        add_comparison(data, compare)
    shown = _shown(results_dir)
    sources = "".join(f", `{_shown(Path(a).resolve())}`" for a in add)
    md = [f"# rl-scan report: {results_dir.name}", "",
          f"{len(data.runs) - borrowed} runs read from `{shown}`{sources}"
          + (f" ({skipped} added runs replaced by their namesakes here)" if skipped else "")
          + (f", {borrowed} of them shown again as a condition of another study that did "
             "not train it (\"Borrowed runs\")" if borrowed else "")
          + ". Scores are final-checkpoint "
          "scores (each run's last evaluation); bands are ± 1 sample std (light) and the 95 % t "
          "interval of the mean (dark, n - 1 degrees of freedom) over seeds. P(X > Y) is "
          "rliable's probability of improvement: per task (scenario) over all pairs of runs, "
          "averaged over the tasks both conditions ran, with a bootstrap CI stratified by "
          "task. Final coverage is the mean ± sample std (n - 1) over a condition's runs "
          "(seeds, and scenes where there are several). Success is the share of the final "
          "evaluations' episodes that reached 95 % coverage, pooled over the runs that have "
          "one, with a Wilson interval that treats those episodes as independent trials. "
          + RULE, "", SPEED, "", DIFFERENCES, ""]
    if data.rebuilt_from == MARL_EVAL_FILE:
        md += [f"Rebuilt from an earlier report's `{MARL_EVAL_FILE}`, which keeps each run's "
               "evaluation curve and final success but not its wall time, evaluation "
               "episode count (so no success CI) or critic diagnostics.", ""]
    groups: dict[str, list[RunRecord]] = defaultdict(list)
    for r in data.runs:
        groups[r.group].append(r)
    figures = []
    for group, runs in sorted(groups.items()):
        spec = data.reports.get(group, ReportSpec())
        md += [f"## {group}", ""]
        planned = data.planned.get(group)
        missing = [r for r in runs if not r.evals]
        own = sum(not r.borrowed_from for r in runs)
        if planned and own < planned:
            md.append(f"**Partial:** {own} of {planned} planned runs have started.")
        if missing:
            md.append(f"**Missing evaluations:** {len(missing)} run(s) have none yet: "
                      + ", ".join(f"`{r.path.name}`" for r in missing[:10]))
        scenarios = sorted({r.scenario for r in runs if r.scenario})
        ref = (greedy_reference(scenarios[0]) if reference and len(scenarios) == 1
               else None)
        fig = plot_curves(runs, group, out / "figures" / f"{group.replace('/', '_')}.png", ref)
        figures.append(fig)
        md += ["", f"![{group}](figures/{fig.name})", ""]
        rows = condition_rows(runs)
        md += _table(rows, spec)
        md += borrowed_lines(runs)
        md += adaptation_lines(runs, rows, spec)
        md += best_checkpoint_table(runs)
        md += critic_lines(runs)
        md += meta_lines(runs)
        if ref is not None and not math.isnan(ref):
            md += ["", f"Scripted greedy team on {scenarios[0]}: {100 * ref:.1f} % coverage."]
        md += improvement_lines(spec, rows)
        if data.rebuilt_from != MARL_EVAL_FILE:  # which keeps no wall times
            md += ["", "| run | condition, seed | env steps | wall time | env steps/s (end to "
                   "end) |", "|---|---|---|---|---|"]
            md += [f"| {r.path.name}{f' ({r.borrowed_from[0]})' if r.borrowed_from else ''} | "
                   f"{r.condition}, {r.seed} | {r.env_steps:,} | "
                   f"{fmt(r.time_total_s, False)} s | {fmt(r.env_steps_per_s, False)} |"
                   for r in sorted(runs, key=lambda r: (r.condition, r.seed))]
        md.append("")
    md += maps
    hw = hardware()
    md += ["## Compute", "", "| item | value |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in hw.items()]
    bench = bench_lines(results_dir)
    md += bench or ["", "No benchmark JSON under the results folder: env-only speed comes from "
                    "`rl-scan bench env --json F`, end-to-end training speed from "
                    "`rl-scan bench train --json F` (put F in the results folder).", ""]
    (out / "report.md").write_text("\n".join(md))
    (out / MARL_EVAL_FILE).write_text(json.dumps(marl_eval_json(data.runs), default=float))
    (out / REPORT_RUNS_FILE).write_text(json.dumps(runs_file(data), default=float))
    (out / "report.html").write_text(to_html("\n".join(md), out))
    return out
