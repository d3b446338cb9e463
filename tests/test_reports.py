"""Reports built from synthetic study folders: every figure written, tables, claims and
the marl-eval export correct, rebuilt from runs.json, compared and joined from parts
(the statistics' hand-computed checks are in test_report_stats.py, meta-MRSS reports
in test_report_meta.py)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import yaml

from rl_scan import results as R
from rl_scan.config import ConfigError
from rl_scan.reports.build import build_report, condition_rows, greedy_reference
from rl_scan.reports.collect import collect
from rl_scan.reports.stats import wilson_interval


def _study(root, finals: dict[str, list[float]], episodes: int = 3, kind: str = "algo"):
    """A study folder as ``rl-scan ablate`` writes it (rl_scan.results' layout)."""
    study = root / f"ablate-{kind}-quick"
    study.mkdir(parents=True)
    (study / R.STUDY_FILE).write_text(yaml.safe_dump(
        {"study": kind, "preset": "quick", "trials": 10, "evaluation_episodes": episodes}))
    for cond, values in finals.items():
        for seed, final in enumerate(values):
            trial_id = f"{cond}_{seed}"
            run = R.trial_run_dir(study, trial_id)
            run.mkdir(parents=True)
            (run / R.RUN_FILE).write_text(yaml.safe_dump(
                {"algo": cond, "seed": seed, "params": {"condition": cond, "seed": seed},
                 "preset_config": {"evaluation_episodes": episodes},
                 "env_config": {"scenario": "ablation"}, "tune_trial": trial_id}))
            evals = [{"training_iteration": 5, "env_steps": 20000, "coverage": final / 2,
                      "success": 0.0},
                     {"training_iteration": 10, "env_steps": 40000, "coverage": final,
                      "success": 1.0 if final >= 0.95 else 0.0}]
            (run / R.EVAL_FILE).write_text(json.dumps(evals))
            tune_trial = R.tune_trial_dir(run)
            tune_trial.mkdir(parents=True)
            (tune_trial / R.RESULT_FILE).write_text(json.dumps(
                {"training_iteration": 10, R.ENV_STEPS: 40000, "time_total_s": 100.0}) + "\n")
    return study


def test_report_on_a_synthetic_study(tmp_path):
    _study(tmp_path, {"poca": [0.96, 0.90, 0.98, 0.70], "ppo": [0.50, 0.60, 0.97, 0.40]})
    rows = {r["condition"]: r for r in condition_rows(collect(tmp_path).runs)}
    poca = rows["poca"]
    assert poca["final_mean"] == pytest.approx(0.885)
    assert poca["final_std"] == pytest.approx(math.sqrt(
        sum((x - 0.885) ** 2 for x in [0.96, 0.90, 0.98, 0.70]) / 3))  # sample std
    assert poca["iqm"] == pytest.approx((0.90 + 0.96) / 2)
    # success: 2 of poca's runs reached 95 % -> 2 x 3 of 12 episodes
    assert poca["success"] == pytest.approx(0.5) and poca["episodes"] == 12
    assert poca["success_ci"] == pytest.approx(wilson_interval(6, 12))
    assert poca["converged"] and not rows["ppo"]["converged"]
    out = build_report(tmp_path, reference=False)
    md = (out / "report.md").read_text()
    assert (out / "figures" / "ablate-algo-quick.png").stat().st_size > 10_000
    assert "Partial:** 8 of 10 planned runs" in md  # the study planned 10 trials
    # P(poca > ppo): poca wins 13 of the 16 pairs (.97 beats all four poca runs but .98)
    assert "| poca > ppo | 0.81" in md
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html and "<table>" in html
    marl = json.loads((out / "marl_eval.json").read_text())
    runs = marl["rl-scan"]["ablation"]["ablate-algo-quick:poca"]
    assert len(runs) == 4
    step = runs["run_0"]["step_1"]  # trial folders sorted: poca seed 0 first
    assert step["step_count"] == 40000 and step["coverage"] == [0.96]
    assert runs["run_0"]["absolute_metrics"] == {"coverage": [0.96], "success": [1.0]}


def test_the_greedy_reference_line_is_the_greedy_teams_mean_coverage(tmp_path):
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.episode import run_episode
    from rl_scan.envs.heuristics import GreedyTeam

    _study(tmp_path, {"poca": [0.9, 0.8], "ppo": [0.7, 0.6]})
    md = (build_report(tmp_path) / "report.md").read_text()
    core = ScanCore({"scenario": "ablation"})
    greedy = np.mean([run_episode(core, GreedyTeam(core), seed=s)["coverage"]
                      for s in range(3)])
    assert 0.9 < greedy <= 1.0
    assert f"Scripted greedy team on ablation: {100 * greedy:.1f} % coverage." in md
    assert math.isnan(greedy_reference(str(tmp_path / "moved.yaml")))  # no line, no error


def test_a_report_rebuilds_from_its_own_folder(tmp_path):
    """Every table regenerates from a report's runs.json; from marl_eval.json alone (older
    reports) the coverage statistics and P(X > Y) do."""
    _study(tmp_path / "results", {"poca": [0.96, 0.90, 0.98, 0.70],
                                  "ppo": [0.50, 0.60, 0.97, 0.40]})
    first = build_report(tmp_path / "results", tmp_path / "first", reference=False)
    again = build_report(first, tmp_path / "again", reference=False)
    tables = [[line for line in (d / "report.md").read_text().splitlines()
               if line.startswith("|") and "Python" not in line and "load" not in line]
              for d in (first, again)]
    assert tables[0] == tables[1] and any("| poca > ppo | 0.81" in t for t in tables[0])
    old = tmp_path / "old"
    old.mkdir()
    shutil.copy(first / "marl_eval.json", old)  # a report from before runs.json
    md = (build_report(old, tmp_path / "from_marl", reference=False) / "report.md").read_text()
    assert "Rebuilt from an earlier report's `marl_eval.json`" in md
    assert "| poca > ppo | 0.81" in md
    poca = next(line for line in tables[0] if line.startswith("| poca |"))
    assert poca.split("|")[3] in md  # the same final coverage mean ± std


def test_comm_report_compares_scheme_1_with_each_scheme_on_one_panel_each(tmp_path):
    from PIL import Image

    finals = {c: [0.5, 0.6] for c in ("2", "3", "4", "5", "6", "7", "1-noinfo")}
    finals["1"] = [0.55, 0.9]
    finals["6"] = [0.9, 0.95]
    out = build_report(_study(tmp_path, finals, kind="comm").parent, reference=False)
    md = (out / "report.md").read_text()
    # P(1 > 2): (.55 vs .5, .6) -> 1 + 0, (.9 vs .5, .6) -> 1 + 1: 3 of 4 pairs
    # P(1 > 6): only (.9 vs .9) ties: 0.5 of 4 pairs
    assert "| 1 > 2 | 0.75" in md and "| 1 > 6 | 0.12" in md and "| 1 > 1-noinfo | 0.75" in md
    assert "| 6 | 2/2 | 92.5 ± 3.5 |" in md and "| succeed |" in md  # paper's Table II
    # eight conditions: a 4 x 2 grid of panels, not eight tangled curves in one
    width, height = Image.open(out / "figures" / "ablate-comm-quick.png").size
    assert width > 1.8 * 770 and height > 1.2 * 462


def test_report_refuses_a_folder_without_runs(tmp_path):
    with pytest.raises(ValueError, match="holds no rl-scan runs"):
        build_report(tmp_path)


def _run(root, name: str, algo: str, seed: int, curve: list[float], best=None):
    run = root / name
    (run / R.TUNE_DIR / R.TRAIN_TRIAL).mkdir(parents=True)
    (run / R.RUN_FILE).write_text(yaml.safe_dump(
        {"algo": algo, "seed": seed, "preset_config": {"evaluation_episodes": 3},
         "env_config": {"scenario": "ablation"}}))
    (run / R.EVAL_FILE).write_text(json.dumps(
        [{"training_iteration": 5 * (i + 1), "env_steps": 20000 * (i + 1), "coverage": c,
          "success": float(c >= 0.95)} for i, c in enumerate(curve)]))
    if best is not None:
        (run / R.BEST_EVAL_FILE).write_text(json.dumps(best))


def test_loose_runs_get_speed_poca_vs_ppo_and_the_secondary_best_table(tmp_path):
    # speed: the first of two consecutive evaluations at 80 % (20k steps apart), censored
    _run(tmp_path, "poca_s0", "poca", 0, [0.5, 0.85, 0.9])  # at 40k
    _run(tmp_path, "poca_s1", "poca", 1, [0.81, 0.7, 0.96],  # never: 0.81 alone is noise
         best={"env_steps": 60000, "eval_coverage": 0.96, "coverage": [0.9, 1.0, 0.95, 0.85],
               "success": [0.0, 1.0, 1.0, 0.0]})
    _run(tmp_path, "ppo_s0", "ppo", 0, [0.3, 0.5, 0.6])  # never
    _run(tmp_path, "ppo_s1", "ppo", 1, [0.4, 0.85, 0.82])  # at 40k
    (tmp_path / "bench_env.json").write_text(json.dumps(
        {"load_avg_1m": 0.08, "core_steps_per_s": 25996.8, "rllib_steps_per_s": 18203.3,
         "pettingzoo_steps_per_s": 18138.9}))
    (tmp_path / "bench_train.json").write_text(json.dumps(
        {"load_avg_1m": 0.15, "runs": {"poca/fast": {"env_steps_per_s": 604.2,
                                                     "tree_pss_mb": 1877.4}}}))
    rows = {r["condition"]: r for r in condition_rows(collect(tmp_path).runs)}
    # censored: the run that never gets there counts as its last evaluation (60k)
    assert rows["poca on ablation"]["speed"] == (40000 + 60000) / 2 and rows[
        "poca on ablation"]["speed_reached"] == 1
    assert rows["ppo on ablation"]["speed"] == (60000 + 40000) / 2 and rows[
        "ppo on ablation"]["speed_reached"] == 1
    md = (build_report(tmp_path, reference=False) / "report.md").read_text()
    assert md.count("| 50,000 (1/2) |") == 2
    # finals poca (0.9, 0.96) vs ppo (0.6, 0.82): poca wins all 4 pairs
    assert "| poca on ablation > ppo on ablation | 1.00" in md
    # best checkpoint of poca_s1: mean 0.925, sample std 0.0645, 2 of 4 successes
    assert "| poca_s1 | poca on ablation | 60,000 | 96.0 | 92.5 ± 6.5 | 50.0 [15.0, 85.0] (4) |" \
        in md
    assert "poca_s0 |" not in md.split("Secondary")[1].split("| run | condition, seed")[0]
    assert "core 25,997, RLlib env 18,203, PettingZoo 18,139 env steps/s" in md
    assert "(load 0.15) | poca/fast: 604 env steps/s, PSS 1,877 MB |" in md


def test_an_earlier_report_is_drawn_tabled_and_compared_beside_new_runs(tmp_path):
    """--compare: the committed example's curves join the report (same table, figure and
    P(X > Y)), read from its marl_eval.json alone."""
    from pathlib import Path

    example = Path(__file__).parents[1] / "reports" / "examples" / "poca_vs_ppo"
    _run(tmp_path, "poca_s0", "poca", 0, [0.5, 0.97, 0.999])
    _run(tmp_path, "poca_s1", "poca", 1, [0.6, 0.9, 0.98])
    md = (build_report(tmp_path, reference=False, compare=example) / "report.md").read_text()
    # the committed example's own row (report.md there: 99.3 ± 0.3, 366,667 (3/3))
    assert "| poca on ablation [poca_vs_ppo] | 3/3 | 99.3 ± 0.3 |" in md
    assert "| 366,667 (3/3) | converged |" in md
    # finals (0.999, 0.98) against the example's three: 0.999 beats all, 0.98 none
    finals = sorted(r.final_coverage for r in collect(tmp_path).runs)
    assert finals == [0.98, 0.999]
    assert "| poca on ablation > poca on ablation [poca_vs_ppo] | 0.50" in md
    with pytest.raises(ConfigError, match="compare="):
        build_report(tmp_path, reference=False, compare=tmp_path / "nothing.json")


def test_report_html_renders_in_headless_chromium(tmp_path, chromium):
    """The self-contained HTML shows its tables and its (inlined) figure."""
    _study(tmp_path, {"poca": [0.96, 0.90], "ppo": [0.50, 0.60]})
    out = build_report(tmp_path, reference=False)
    dom = chromium.dom(out / "report.html")
    assert dom.count('src="data:image/png;base64,') == 1 and "<table>" in dom
    assert "<td>poca</td>" in dom and "<td>converged</td>" in dom
    pixels = chromium.screenshot(out / "report.html", tmp_path / "shot.png")
    # matplotlib's first two colours: the poca (blue) and ppo (orange) curves are on screen
    blue = (abs(pixels[:, 0] - 31) < 30) & (abs(pixels[:, 1] - 119) < 30) & (pixels[:, 2] > 150)
    orange = (pixels[:, 0] > 220) & (abs(pixels[:, 1] - 127) < 30) & (pixels[:, 2] < 60)
    assert blue.sum() > 100 and orange.sum() > 100


def test_a_partial_meta_mrss_experiment_says_what_is_missing(tmp_path):
    exp = tmp_path / "mm"
    (exp / R.ADAPT_DIR).mkdir(parents=True)
    (exp / R.PROTOCOL_FILE).write_text(yaml.safe_dump(
        {"methods": ["meta-mrss", "poca"], "tests": ["test:0", "test:1"], "seeds": 1,
         "planned_runs": {R.PRETRAIN_DIR: 1, R.ADAPT_DIR: 4}}))
    _run(exp / R.ADAPT_DIR, "poca_test0_s0", "poca", 0, [0.3, 0.5])
    data = collect(tmp_path)
    assert data.planned == {"mm/adapt": 4} and data.runs[0].condition == "poca"
    md = (build_report(tmp_path, reference=False) / "report.md").read_text()
    assert "Partial:** 1 of 4 planned runs" in md


def test_curve_band_aligns_evaluations_a_few_steps_apart():
    from pathlib import Path

    from rl_scan.reports.collect import RunRecord
    from rl_scan.reports.figures import curve_band

    runs = [RunRecord("runs", "poca", seed, Path(f"r{seed}"),
                      evals=[{"env_steps": s, "coverage": c} for s, c in curve])
            for seed, curve in enumerate([[(20_004, 0.5), (780_003, 0.9)],
                                          [(20_000, 0.7), (780_026, 0.95)]])]
    steps, mean, _, _, count = curve_band(runs)
    assert steps.tolist() == [20_000, 780_000] and count.tolist() == [2, 2]
    assert mean.tolist() == pytest.approx([0.6, 0.925])


def test_critic_diagnostics_are_read_from_progress_and_tabled(tmp_path):
    """POCA's explained variances (Tune's flattened learners/<module>/<key> columns) per
    condition: last value averaged over runs, and when V first explained half."""
    for seed, values in enumerate([[(0.1, 0.2), (0.6, 0.7), (0.8, 0.9)],
                                   [(0.2, 0.1), (0.4, 0.3), (0.55, 0.5)]]):
        _run(tmp_path, f"poca_s{seed}", "poca", seed, [0.5, 0.7, 0.9])
        lines = [json.dumps({"training_iteration": i + 1, R.ENV_STEPS: 20000 * (i + 1),
                             "time_total_s": 10 * (i + 1), R.LEARNERS: {
                                 "critic": {R.EV_VALUE: v}, "quad": {R.EV_BASELINE: b}}})
                 for i, (v, b) in enumerate(values)]
        trial = tmp_path / f"poca_s{seed}" / R.TUNE_DIR / R.TRAIN_TRIAL
        (trial / R.RESULT_FILE).write_text("\n".join(lines) + "\n")
    runs = collect(tmp_path).runs
    assert runs[0].critic == {"V": [(20000, 0.1), (40000, 0.6), (60000, 0.8)],
                              "b_quad": [(20000, 0.2), (40000, 0.7), (60000, 0.9)]}
    md = (build_report(tmp_path, reference=False) / "report.md").read_text()
    # last V: (0.8 + 0.55) / 2, last b_quad: (0.9 + 0.5) / 2; EV V >= 0.5 at 40k and 60k
    assert "| EV V | EV b_quad | env steps to EV V >= 0.5 (reached) |" in md
    assert "| poca on ablation | 0.68 | 0.70 | 50,000 (2/2) |" in md


def test_a_hetero_map_alone_makes_a_report_with_its_heatmap_and_winning_region(tmp_path):
    def point(sensor, budget, mixed, quads, wheeled):
        return {"params": {"wheeled_sensor": sensor, "quad_speed": 0.1, "quad_range": 3.5,
                           "flight_time": budget},
                "value": mixed - max(quads, wheeled), "final": {"mixed": 1.0, "quads": 1.0,
                                                                 "wheeled": 0.5},
                "mean": {"mixed": mixed, "quads": quads, "wheeled": wheeled}}

    study = tmp_path / "map"
    study.mkdir()
    (study / R.HETERO_MAP).write_text(json.dumps({
        "axes": {"wheeled_sensor": ["fan", "sphere"], "quad_speed": [0.1],
                 "quad_range": [3.5], "flight_time": [0.0, 100.0]},
        "teams": {"mixed": [2, 2], "quads": [0, 4], "wheeled": [4, 0]},
        "scenes": ["train:0", "train:1"],
        "points": [point("fan", 0.0, 0.80, 0.85, 0.5), point("fan", 100.0, 0.75, 0.60, 0.5),
                   point("sphere", 0.0, 0.82, 0.85, 0.6)]}))
    md = (build_report(tmp_path) / "report.md").read_text()
    assert "The mixed team wins at **1 of 3** points; largest margin +15.0 points" in md
    assert "| fan | 0.1 | 3.5 | 100.0 | 75.0 | 60.0 | 50.0 | +15.0 |" in md
    assert (tmp_path / "report" / "figures" / "hetero_map_map.png").stat().st_size > 0


def test_each_paper_claim_gets_the_verdict_its_ci_implies(tmp_path):
    from rl_scan.reports.claims import (
        REPRODUCED,
        REVERSED,
        TOO_FEW,
        UNDECIDED,
        improvement_rows,
        verdict,
    )
    from rl_scan.reports.stats import fewest_runs_per_task, probability_of_improvement_ci
    from rl_scan.studies import ReportSpec

    assert [verdict(ci) for ci in ((0.51, 0.9), (0.1, 0.49), (0.2, 0.8), (0.5, 0.9))] == [
        REPRODUCED, REVERSED, UNDECIDED, UNDECIDED]
    assert verdict((0.0, 0.0), runs=2) == TOO_FEW  # 1 or 2 runs: a degenerate CI
    # 5 scenes x 1 seed: 5 runs a side, but one a task; the stratified CI collapses
    x, y, scenes = [0.9, 0.8, 0.7, 0.6, 0.5], [0.85, 0.9, 0.6, 0.5, 0.4], list(range(5))
    assert probability_of_improvement_ci(x, y, scenes, scenes) == (0.8, 0.8)  # 4 of 5 wins
    assert fewest_runs_per_task(x, y, scenes, scenes) == 1
    assert fewest_runs_per_task(x * 3, y * 3, scenes * 3, scenes * 3) == 3
    assert fewest_runs_per_task(x * 3, y, scenes * 3, scenes) == 1
    spec = ReportSpec(comparisons=(("x", "y"),), claims={"x > y": "x beats y"})
    rows = [{"condition": "x", "finals": [v + 0.5 for v in x], "tasks": scenes},
            {"condition": "y", "finals": y, "tasks": scenes}]
    assert improvement_rows(spec, rows)[0]["verdict"] == TOO_FEW  # CI (1, 1), 5 runs a side
    rows = [{**r, "finals": r["finals"] * 3, "tasks": scenes * 3} for r in rows]
    assert improvement_rows(spec, rows)[0]["verdict"] == REPRODUCED
    # the paper: 2 + 2 beat 4 quads; here 4 quads win every pair (P = 0, CI [0, 0])
    _study(tmp_path / "results", {"2,2": [0.6, 0.7, 0.65], "0,4": [0.9, 0.95, 0.92],
                                  "4,0": [0.5, 0.6, 0.7]}, kind="team")
    out = build_report(tmp_path / "results", tmp_path / "first", reference=False)
    md = (out / "report.md").read_text()
    assert "| 2,2 > 0,4 | 0.00 [0.00, 0.00] | 2 wheeled + 2 quads scan more than 4 quads" in md
    assert "(Sec. IV-B) | reversed |" in md and "**reversed** if it lies below 0.5" in md
    # 2,2 > 4,0 is ours, no verdict: .6 wins 1.5 pairs (a tie), .7 2.5, .65 2: 6 of 9
    assert "| 2,2 > 4,0 | 0.67 " in md and "(ours: not a claim of the paper) | - |" in md
    again = (build_report(out, tmp_path / "again", reference=False) / "report.md").read_text()
    assert "(Sec. IV-B) | reversed |" in again  # claims survive the rebuild from runs.json


def test_a_study_run_in_parts_reports_as_one(tmp_path):
    """--add: seed 0 in one folder and seeds 1-3 in another (two sessions, one --name) give
    the tables of the whole study; a run here replaces its namesake in the added folder."""
    finals = {"poca": [0.96, 0.90, 0.98, 0.70], "ppo": [0.50, 0.60, 0.97, 0.40]}
    whole = _study(tmp_path / "whole", finals)
    for part, keep in (("first", lambda seed: seed == 0), ("rest", lambda seed: seed > 0)):
        shutil.copytree(whole, tmp_path / part / whole.name)
        for run in (tmp_path / part / whole.name / R.TRIALS_DIR).iterdir():
            if not keep(int(run.name.split("_")[1])):
                shutil.rmtree(run)
    first = build_report(tmp_path / "first", tmp_path / "first_report", reference=False)
    merged = build_report(tmp_path / "rest", tmp_path / "merged", reference=False, add=[first])
    one = build_report(tmp_path / "whole", tmp_path / "one", reference=False)
    tables = [[line for line in (d / "report.md").read_text().splitlines()
               if line.startswith("| poca")] for d in (merged, one)]
    assert tables[0] == tables[1] and "| poca > ppo | 0.81" in "\n".join(tables[0])
    # the whole study added to its own part: the part's 6 runs replace their namesakes
    again = build_report(tmp_path / "rest", tmp_path / "again", reference=False, add=[one])
    text = (again / "report.md").read_text()
    assert "8 runs read from" in text and "(6 added runs replaced" in text
    other = _study(tmp_path / "other", {"poca": [0.5]})
    (other / R.STUDY_FILE).write_text(yaml.safe_dump(
        {"study": "algo", "trials": 1, "env_config": {"comm_scheme": 3}}))
    with pytest.raises(ConfigError, match="env settings"):
        build_report(tmp_path / "rest", tmp_path / "bad", reference=False, add=[other.parent])
    (tmp_path / "empty").mkdir()
    for nothing in (tmp_path / "empty", tmp_path / "nothing.json"):
        with pytest.raises(ConfigError, match="add="):
            build_report(tmp_path / "rest", tmp_path / "bad", reference=False, add=[nothing])
