"""``rl-scan report RESULTS_DIR``: Markdown + self-contained HTML report with PNG figures.

Per group of runs (an ablation study, a meta-MRSS experiment, loose training runs):
  * learning curves: evaluation coverage over env steps, mean +- std over seeds and a 95 %
    CI band (mean +- 1.96 standard errors), the scripted greedy team as a reference line;
  * a table per condition: runs, final coverage mean +- std, IQM with a stratified
    bootstrap 95 % CI, success rate with a Wilson 95 % CI over evaluation episodes, and
    the convergence verdict by the rule stated in the report (``CONVERGED``);
  * probability of improvement for the paper's comparisons (POCA vs PPO, hetero vs homo,
    meta-MRSS vs each baseline);
  * compute: env steps/s end to end and wall time per run, hardware, package versions.
Headline scores are final-checkpoint scores (the last evaluation of each run). Runs still
going are reported as far as they got, and missing runs are listed. Raw per-run metrics
are exported in marl-eval's JSON layout (``marl_eval.json``).
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import platform
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan.reports.collect import Collection, RunRecord, collect, read_json
from rl_scan.reports.stats import (
    iqm,
    mean_std,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap_ci,
    wilson_interval,
)

CONVERGED = 0.80
RULE = (f"A condition **converged** if the mean over seeds of its final evaluation coverage "
        f"is at least {CONVERGED:.0%}; otherwise it **failed**.")
SPEED_AT = 0.80
SPEED = (f"**Learning / adaptation speed** is defined up front as the env steps of a run's "
         f"first evaluation whose mean coverage reaches {SPEED_AT:.0%}; a condition reports the "
         "mean over the runs that reached it and how many did.")
PAPER_TABLE_II = {"1": "succeed", "2": "failed", "3": "failed", "4": "failed",
                  "5": "failed", "6": "succeed", "7": "failed"}
PAPER_META = {"meta-mrss": "87.12 %", "dr": "68.54 %", "poca": "60.16 %",
              "transfer": "71.74 %"}
COMPARISONS = {  # group kind -> (better, other) pairs for probability of improvement
    "algo": [("poca", "ppo")],
    "team": [("2,2", "0,4"), ("2,2", "4,0")],
    "adapt": [("meta-mrss", "dr"), ("meta-mrss", "transfer"), ("meta-mrss", "poca")],
    # the paper's pick (scheme 1 with object information) against every other scheme
    "comm": [("1", c) for c in ("2", "3", "4", "5", "6", "7", "1-noinfo")],
}
DIFFERENCES = (
    "Differences from the paper's set-up: our simulator is a voxel re-implementation of "
    "their Unity scenes (same sensor encoding, robot kinds and reward terms, arena "
    "20 x 20 x 8 m, 0.5 m cells), budgets are those of the preset named in each section "
    "(the paper trained for 8-14 M env steps), and every figure here comes from runs on "
    "this machine.")


def group_kind(group: str) -> str:
    for kind in ("comm", "algo", "team", "hpo"):
        if group.startswith(f"ablate-{kind}"):
            return kind
    return "adapt" if group.endswith("/adapt") else "runs"


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
        episodes = sum(r.eval_episodes for r in scored)
        successes = sum(r.final_success * r.eval_episodes for r in scored
                        if not math.isnan(r.final_success))
        mean, std = mean_std(finals)
        speeds = [r.steps_to(SPEED_AT) for r in scored]
        reached = [x for x in speeds if not math.isnan(x)]
        rows.append({
            "condition": cond, "runs": len(rs), "scored": len(scored),
            "final_mean": mean, "final_std": std, "iqm": iqm(finals) if finals else math.nan,
            "iqm_ci": stratified_bootstrap_ci(list(strata.values())),
            "success": successes / episodes if episodes else math.nan,
            "success_ci": wilson_interval(successes, episodes), "episodes": episodes,
            "converged": (not math.isnan(mean)) and mean >= CONVERGED,
            "speed": float(np.mean(reached)) if reached else math.nan,
            "speed_reached": len(reached), "finals": finals})
    return rows


def improvement_rows(kind: str, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    finals = {r["condition"]: r["finals"] for r in rows}
    pairs = COMPARISONS.get(kind, [])
    if kind == "runs":  # loose training runs: POCA vs PPO on each scenario both ran on
        pairs = [(c, "ppo" + c[len("poca"):]) for c in finals if c.startswith("poca on ")]
    out = []
    for a, b in pairs:
        if finals.get(a) and finals.get(b):
            out.append({"x": a, "y": b, "p": probability_of_improvement(finals[a], finals[b]),
                        "ci": probability_of_improvement_ci(finals[a], finals[b])})
    return out


def curve_band(runs: list[RunRecord]) -> tuple[np.ndarray, ...]:
    """Steps, mean, std, 95 % CI half-width and run count of coverage at each evaluated
    step (runs of unequal length: the statistics use the runs that reached the step)."""
    curves = [dict(r.curve) for r in runs if r.evals]
    steps = sorted(set().union(*[set(c) for c in curves])) if curves else []
    if not steps:
        return (np.array([]),) * 5
    mean, std, half, count = [], [], [], []
    for s in steps:
        v = np.array([c[s] for c in curves if s in c])
        mean.append(v.mean())
        std.append(v.std())
        half.append(1.96 * v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else 0.0)
        count.append(len(v))
    return tuple(np.array(x) for x in (steps, mean, std, half, count))


PANELS_FROM = 5  # conditions from which each gets its own panel (one plot is unreadable)


def plot_curves(runs: list[RunRecord], title: str, out: Path,
                reference: float | None = None) -> Path:
    """Mean +- std (light) and 95 % CI (dark) of coverage per condition, and each run
    when there are few; one panel per condition when there are many (Table II's 8)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    by_cond: dict[str, list[RunRecord]] = defaultdict(list)
    for r in runs:
        by_cond[r.condition].append(r)
    conds = sorted(by_cond)
    panels = len(conds) >= PANELS_FROM
    cols = min(4, len(conds)) if panels else 1
    rows = -(-len(conds) // cols) if panels else 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols + 0.8, 2.6 * rows + 0.9)
                             if panels else (7, 4.2), dpi=110, sharex=True, sharey=True,
                             squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, cond in enumerate(conds):
        ax = axes.flat[i] if panels else axes.flat[0]
        rs, color = by_cond[cond], colors[i % len(colors)]
        steps, mean, std, half, _ = curve_band(rs)
        if not len(steps):
            continue
        ax.plot(steps, mean, color=color, label=f"{cond} (n={len(rs)})", lw=1.8)
        if 1 < len(rs) <= 5:  # few seeds: show each run too
            for r in rs:
                if r.evals:
                    x, y = zip(*r.curve)
                    ax.plot(x, y, color=color, lw=0.6, alpha=0.5)
        ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.15)
        ax.fill_between(steps, mean - half, mean + half, color=color, alpha=0.3)
        if panels:
            ax.set_title(f"{cond} (n={len(rs)})", fontsize=9)
    for i, ax in enumerate(axes.flat):
        if panels and i >= len(conds):
            ax.set_visible(False)
            continue
        if reference is not None and not math.isnan(reference):
            ax.axhline(reference, color="k", ls="--", lw=1, label="scripted greedy team")
        ax.axhline(CONVERGED, color="grey", ls=":", lw=1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(_steps_label))
        ax.tick_params(labelsize=7 if panels else 9, labelbottom=True)
    for ax in axes[-1]:
        ax.set_xlabel("env steps", fontsize=8 if panels else 10)
    for ax in axes[:, 0]:
        ax.set_ylabel("evaluation coverage", fontsize=8 if panels else 10)
    if panels:
        fig.suptitle(f"{title}: mean ± std (light), 95 % CI (dark), each seed (thin); "
                     "dashed: greedy team, dotted: 80 %", fontsize=9)
    else:
        axes[0, 0].set_title(title)
        axes[0, 0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def _steps_label(x: float, _pos=None) -> str:
    return f"{x / 1e6:g}M" if abs(x) >= 1e6 else f"{x / 1e3:g}k" if x else "0"


def greedy_reference(scenario: str, episodes: int = 3) -> float:
    """Mean final coverage of the scripted greedy team on a scenario (nan if unknown)."""
    try:
        from rl_scan.envs.core import ScanCore
        from rl_scan.envs.heuristics import GreedyTeam, run_episode

        core = ScanCore({"scenario": scenario})
        return float(np.mean([run_episode(core, GreedyTeam(core), seed=s)["coverage"]
                              for s in range(episodes)]))
    except Exception:  # noqa: BLE001 - a reference line is optional
        return math.nan


def _fmt(x: float, pct: bool = True) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{100 * x:.1f}" if pct else f"{x:,.0f}"


def _table(rows: list[dict[str, Any]], kind: str) -> list[str]:
    head = ["condition", "runs", "final coverage % (mean ± std)", "IQM % [95 % CI]",
            "success % [95 % CI] (episodes)", f"env steps to {SPEED_AT:.0%} (reached)",
            "verdict"]
    if kind == "comm":
        head.append("paper (Table II)")
    if kind == "adapt":
        head.append("paper success")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lo, hi = r["iqm_ci"]
        slo, shi = r["success_ci"]
        cells = [r["condition"], f"{r['scored']}/{r['runs']}",
                 f"{_fmt(r['final_mean'])} ± {_fmt(r['final_std'])}",
                 f"{_fmt(r['iqm'])} [{_fmt(lo)}, {_fmt(hi)}]",
                 f"{_fmt(r['success'])} [{_fmt(slo)}, {_fmt(shi)}] ({r['episodes']})",
                 f"{_fmt(r['speed'], False)} ({r['speed_reached']}/{r['scored']})",
                 "converged" if r["converged"] else "failed"]
        if kind == "comm":
            cells.append(PAPER_TABLE_II.get(r["condition"], "(not in the paper)"))
        if kind == "adapt":
            cells.append(PAPER_META.get(r["condition"], "-"))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def best_checkpoint_table(runs: list[RunRecord]) -> list[str]:
    """Secondary numbers: each run's best kept checkpoint re-evaluated (evaluate --best)."""
    rows = [r for r in runs if r.best_eval]
    if not rows:
        return []
    lines = ["", "Secondary (not the headline): each run's best kept checkpoint, chosen by its "
             "training-time evaluation and re-evaluated on more episodes with "
             "`rl-scan evaluate RUN --best`. Choosing the best is biased upwards; the "
             "headline above uses final checkpoints.", "",
             "| run | condition | checkpoint at env steps | training-time eval % | "
             "re-evaluated coverage % (mean ± std) | success % [95 % CI] (episodes) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        b = r.best_eval
        cov, succ = b.get("coverage", []), b.get("success", [])
        mean, std = mean_std(cov)
        wins = int(sum(succ))
        lo, hi = wilson_interval(wins, len(succ))
        lines.append(f"| {r.path.name} | {r.condition} | {int(b.get('env_steps', 0)):,} | "
                     f"{_fmt(b.get('eval_coverage', math.nan))} | {_fmt(mean)} ± {_fmt(std)} | "
                     f"{_fmt(wins / len(succ) if succ else math.nan)} [{_fmt(lo)}, {_fmt(hi)}] "
                     f"({len(succ)}) |")
    return lines


def marl_eval_json(runs: list[RunRecord]) -> dict[str, Any]:
    """marl-eval's layout: env -> task -> algorithm -> run -> step_k / absolute_metrics."""
    out: dict[str, Any] = {"rl-scan": {}}
    counters: dict[tuple, int] = defaultdict(int)
    for r in runs:
        task = r.scenario or "unknown"
        algo = f"{r.group}:{r.condition}"
        key = (task, algo)
        run_id = f"run_{counters[key]}"
        counters[key] += 1
        steps = {f"step_{i}": {"step_count": int(e["env_steps"]),
                               "coverage": [float(e["coverage"])],
                               "return": [float(e.get("episode_return_mean") or math.nan)]}
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
            lines += [f"| training end to end, `{path.name}` (load {load:.2f}) | {label}: "
                      f"{run.get('env_steps_per_s', math.nan):,.0f} env steps/s, peak RSS "
                      f"{run.get('peak_rss_mb', math.nan):,.0f} MB |"]
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


def build_report(results_dir: str | Path, out_dir: str | Path | None = None,
                 reference: bool = True) -> Path:
    """Write report.md, report.html, figures/*.png and marl_eval.json; returns out_dir."""
    results_dir = Path(results_dir).resolve()
    if not results_dir.is_dir():
        raise ValueError(f"results_dir={str(results_dir)!r} is not a folder")
    out = Path(out_dir).resolve() if out_dir else results_dir / "report"
    (out / "figures").mkdir(parents=True, exist_ok=True)
    data: Collection = collect(results_dir)
    if not data.runs:
        raise ValueError(f"results_dir={str(results_dir)!r} holds no rl-scan runs or studies")
    md = [f"# rl-scan report: {results_dir.name}", "",
          f"{len(data.runs)} runs read from `{results_dir}`. Scores are final-checkpoint "
          "scores (each run's last evaluation); bands are ± 1 std (light) and a 95 % CI of "
          "the mean (dark) over seeds. " + RULE, "", SPEED, "", DIFFERENCES, ""]
    groups: dict[str, list[RunRecord]] = defaultdict(list)
    for r in data.runs:
        groups[r.group].append(r)
    figures = []
    for group, runs in sorted(groups.items()):
        kind = group_kind(group)
        md += [f"## {group}", ""]
        planned = data.planned.get(group)
        missing = [r for r in runs if not r.evals]
        if planned and len(runs) < planned:
            md.append(f"**Partial:** {len(runs)} of {planned} planned runs have started.")
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
        md += _table(rows, kind)
        md += best_checkpoint_table(runs)
        if ref is not None and not math.isnan(ref):
            md += ["", f"Scripted greedy team on {scenarios[0]}: {100 * ref:.1f} % coverage."]
        imp = improvement_rows(kind, rows)
        if imp:
            md += ["", "| probability of improvement | P(X > Y) [95 % CI] |", "|---|---|"]
            md += [f"| {i['x']} > {i['y']} | {i['p']:.2f} [{i['ci'][0]:.2f}, {i['ci'][1]:.2f}] |"
                   for i in imp]
        md += ["", "| run | env steps | wall time | env steps/s (end to end) |",
               "|---|---|---|---|"]
        md += [f"| {r.path.name} | {r.env_steps:,} | {_fmt(r.time_total_s, False)} s | "
               f"{_fmt(r.env_steps_per_s, False)} |" for r in runs]
        md.append("")
    hw = hardware()
    md += ["## Compute", "", "| item | value |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in hw.items()]
    bench = bench_lines(results_dir)
    md += bench or ["", "No benchmark JSON under the results folder: env-only speed comes from "
                    "`rl-scan bench env --json F`, end-to-end training speed from "
                    "`rl-scan bench train --json F` (put F in the results folder).", ""]
    (out / "report.md").write_text("\n".join(md))
    (out / "marl_eval.json").write_text(json.dumps(marl_eval_json(data.runs), default=float))
    (out / "report.html").write_text(to_html("\n".join(md), out))
    return out


def to_html(markdown: str, out: Path) -> str:
    """A minimal Markdown -> HTML for our own report (headings, tables, images inlined)."""
    body, table = [], []

    def flush_table():
        if not table:
            return
        rows = [r.strip().strip("|").split("|") for r in table if not set(r) <= set("|-")]
        body.append("<table>" + "".join(
            "<tr>" + "".join(f"<{'th' if i == 0 else 'td'}>{_inline(c.strip())}"
                             f"</{'th' if i == 0 else 'td'}>" for c in row) + "</tr>"
            for i, row in enumerate(rows)) + "</table>")
        table.clear()

    for line in markdown.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush_table()
        if line.startswith("!["):
            src = line[line.index("(") + 1:line.rindex(")")]
            data = base64.b64encode((out / src).read_bytes()).decode()
            body.append(f'<p><img alt="{html.escape(src)}" src="data:image/png;base64,{data}"'
                        ' style="max-width:100%"></p>')
        elif line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{_inline(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            body.append(f"<p>{_inline(line)}</p>")
    flush_table()
    style = ("body{font-family:sans-serif;max-width:1000px;margin:2em auto;padding:0 1em}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
             "padding:4px 8px;font-size:13px}th{background:#f3f3f3}")
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>rl-scan report</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>")


def _inline(text: str) -> str:
    import re

    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", text)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", text)
