"""What reports read from a run: Tune's results of a restored trial, and scan speed (episode
steps to 95 % at the final evaluation, censored at the episode length) with P(X faster
than Y) for a study's pairs (hand-computed values)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from rl_scan import results as R
from rl_scan.reports.build import condition_rows
from rl_scan.reports.claims import scan_speed_lines
from rl_scan.reports.collect import RunRecord
from rl_scan.studies import STUDIES


def _run(condition: str, seed: int, **final) -> RunRecord:
    first = {"env_steps": 4000, "coverage": 0.2, "reached_95": 0.0, "episode_steps": 500.0}
    last = {"env_steps": 8000, "coverage": 0.97, "episode_steps": 500.0, **final}
    return RunRecord(group="ablate-team-x", condition=condition, seed=seed, path=Path("."),
                     evals=[first, last], scenario="ablation")


def test_scan_steps_count_episodes_that_never_reach_95_percent_as_their_whole_length():
    # half the episodes reach 95 % at step 200 on average, half run all 500 steps
    assert _run("2,2", 0, reached_95=0.5, steps_to_95=200.0).final_scan_steps == 350.0
    assert _run("2,2", 0, reached_95=1.0, steps_to_95=180.0).final_scan_steps == 180.0
    assert _run("2,2", 0, reached_95=0.0).final_scan_steps == 500.0  # no steps_to_95 then
    assert math.isnan(_run("2,2", 0).final_scan_steps)  # a file that predates the figure


def test_the_team_report_compares_scan_speed_pair_by_pair():
    runs = [_run("2,2", s, reached_95=1.0, steps_to_95=v) for s, v in enumerate([100, 200, 300])]
    runs += [_run("0,4", s, reached_95=1.0, steps_to_95=v) for s, v in enumerate([250, 400, 500])]
    runs += [_run("4,0", s, reached_95=0.0) for s in range(3)]
    rows = condition_rows(runs)
    assert {r["condition"]: r["scan_steps"] for r in rows}["0,4"] == [250.0, 400.0, 500.0]
    lines = scan_speed_lines(STUDIES["team"].report, rows)
    # 2,2 faster in 8 of the 9 pairs with 0,4 (300 is slower than 250 only); every 4,0 run
    # is censored at 500: 2,2 faster in all 9
    assert "| 2,2 vs 0,4 | 200 ± 100 | 383 ± 126 | 0.89 [" in "\n".join(lines)
    assert "| 2,2 vs 4,0 | 200 ± 100 | 500 ± 0 | 1.00 [1.00, 1.00] |" in lines
    assert any("censored" in line for line in lines)


def test_no_scan_speed_table_where_a_run_lacks_the_figure():
    runs = [_run("2,2", s, reached_95=1.0, steps_to_95=100.0) for s in range(3)]
    runs += [_run("0,4", s) for s in range(3)]  # rebuilt from a file without reached_95
    assert scan_speed_lines(STUDIES["team"].report, condition_rows(runs)) == []


def test_equal_scan_speeds_are_a_coin_flip():
    runs = [_run(c, s, reached_95=1.0, steps_to_95=300.0) for c in ("2,2", "0,4")
            for s in range(3)]
    (line,) = [x for x in scan_speed_lines(STUDIES["team"].report, condition_rows(runs))
               if x.startswith("| 2,2 vs 0,4")]
    assert line.endswith("| 0.50 [0.50, 0.50] |")


def test_a_restored_trials_results_are_read_by_key_with_its_repeated_iterations_once(tmp_path):
    """Tune appends a restored trial's progress.csv rows under the old header with other
    columns; result.json keeps every key. Iterations 2-3 ran twice (killed after 3,
    restored from the checkpoint at 1): the second run of them is what training went on
    from."""
    ev = f"{R.LEARNERS}/critic/{R.EV_VALUE}"
    first = [{"training_iteration": i, R.ENV_STEPS: 100 * i, "time_total_s": 10.0 * i}
             for i in (1, 2, 3)]
    restored = [{"training_iteration": i, R.ENV_STEPS: 100 * i, "time_total_s": 10.0 * i + 5,
                 "evaluation": {"coverage": 0.5}, R.LEARNERS: {"critic": {R.EV_VALUE: i / 10}}}
                for i in (2, 3, 4)]
    (tmp_path / R.RESULT_FILE).write_text(
        "".join(json.dumps({**r, "config": {"lr": 1}}) + "\n" for r in first + restored))
    rows = R.progress_rows(tmp_path)
    assert [r["training_iteration"] for r in rows] == [1, 2, 3, 4]
    assert rows[1]["time_total_s"] == 25.0 and rows[1][ev] == 0.2
    assert "config/lr" not in rows[0] and rows[3]["evaluation/coverage"] == 0.5
    assert R.progress_tail(tmp_path, rows) == (400, 45.0)
    assert R.critic_diagnostics(rows) == {"V": [(200, 0.2), (300, 0.3), (400, 0.4)]}


def test_iterations_missing_from_result_json_come_from_progress_csvs_aligned_rows(tmp_path):
    """A trial restore copies result.json back from a copy taken before its last result
    (iteration 1 lost here); progress.csv still has it. A row longer than the header (a
    driver resume) cannot be read and is skipped."""
    (tmp_path / R.PROGRESS_FILE).write_text(
        f"training_iteration,{R.ENV_STEPS},time_total_s\n1,100,10.0\n"
        "2,200,20.0,0.5,extra\n")
    (tmp_path / R.RESULT_FILE).write_text("".join(json.dumps(
        {"training_iteration": i, R.ENV_STEPS: 100 * i, "time_total_s": 10.0 * i + 1}) + "\n"
        for i in (2, 3)))
    rows = R.progress_rows(tmp_path)
    assert [int(float(r["training_iteration"])) for r in rows] == [1, 2, 3]
    assert [float(r["time_total_s"]) for r in rows] == [10.0, 21.0, 31.0]
    assert R.progress_tail(tmp_path, rows) == (300, 31.0)
