"""A study's condition taken from another study that trained the same trial (reports.borrow):
borrowed only when algorithm, settings, preset, EnvConfig and evaluation schedule agree, compared
like an own condition, marked, and never written to the report's runs file."""

from __future__ import annotations

import json

import yaml

from rl_scan import results as R
from rl_scan.reports.borrow import trial_key
from rl_scan.reports.build import build_report


def _study(root, name: str, kind: str, finals: dict[str, list[float]], env: dict | None = None,
           last_step: int = 1_000_000, episodes: int = 10, lr: float = 3e-4):
    """A study folder as ``rl-scan ablate KIND --name NAME`` writes it."""
    study = root / name
    study.mkdir(parents=True)
    (study / R.STUDY_FILE).write_text(yaml.safe_dump(
        {"study": kind, "trials": sum(map(len, finals.values())), "env_config": env or {},
         "evaluation_episodes": episodes}))
    for cond, values in finals.items():
        for seed, final in enumerate(values):
            run = R.trial_run_dir(study, f"{cond.replace('/', '-')}_{seed}")
            run.mkdir(parents=True)
            (run / R.RUN_FILE).write_text(yaml.safe_dump(
                {"algo": cond.split("/")[0], "seed": seed,
                 "params": {"condition": cond, "seed": seed},
                 "preset_config": {"evaluation_episodes": episodes, "lr": lr,
                                   "learner_cpus": 1 + seed % 2},  # placement: not compared
                 "env_config": {"scenario": "ablation"}}))
            (run / R.EVAL_FILE).write_text(json.dumps([
                {"training_iteration": 10, "env_steps": last_step // 2, "coverage": final / 2},
                {"training_iteration": 20, "env_steps": last_step + 37 * seed,  # the last
                 "coverage": final}]))  # batch ends a few steps past the budget


def test_the_same_trial_under_another_name_has_the_same_key():
    # individual rewards are the default: the algo study's poca is the reward study's
    assert trial_key("study:algo", "poca", {}) == trial_key("study:reward", "poca/individual",
                                                            {})
    assert trial_key("study:algo", "poca", {}) != trial_key("study:reward", "poca/team", {})
    assert trial_key("study:algo", "ppo", {}) != trial_key("study:reward", "poca/individual",
                                                           {})
    assert trial_key("study:algo", "poca", {"comm_scheme": 3}) != trial_key(
        "study:reward", "poca/individual", {})
    assert trial_key("study:algo", "a3c", {}) is None  # not a condition of the study
    assert trial_key("study:hpo", "lr=0.001", {}) is None  # a search study has none


def test_a_reward_study_borrows_its_individual_reward_runs_from_an_algo_study(tmp_path):
    results = tmp_path / "results"
    _study(results, "reward-1M", "reward", {"poca/team": [0.9, 0.8], "ppo/team": [0.6, 0.7]})
    _study(results, "algo-1M", "algo", {"poca": [0.7, 0.75, 0.65], "ppo": [0.5, 0.95, 0.55]})
    # the same trials with another comm scheme, half the budget or another lr: never borrowed
    # (each has more poca runs than algo-1M, so it would be chosen if it were the same trial)
    _study(results, "algo-comm3", "algo", {"poca": [0.1] * 4}, env={"comm_scheme": 3})
    _study(results, "algo-500k", "algo", {"poca": [0.2] * 4}, last_step=500_000)
    _study(results, "algo-lr1e-3", "algo", {"poca": [0.3] * 4}, lr=1e-3)
    out = build_report(results, tmp_path / "report", reference=False)
    md = (out / "report.md").read_text()
    assert "22 runs read from" in md and "6 of them shown again" in md
    reward = md[md.index("## reward-1M"):]
    reward = reward[:reward.index("\n## ")]
    # poca/individual = algo-1M's 3 poca runs: final 70.0 +- 5.0
    assert "| poca/individual | 3/3 | 70.0 ± 5.0 |" in reward
    assert "| ppo/individual | 3/3 |" in reward
    assert ("**poca/individual** = algo-1M's poca; **ppo/individual** = algo-1M's ppo."
            in reward)
    assert "Partial" not in reward  # its own 4 runs are all it planned
    # P(poca/team > poca/individual): 0.9 and 0.8 beat each of 0.7, 0.75, 0.65
    assert "| poca/team > poca/individual | 1.00 [1.00, 1.00] |" in reward
    # ppo/team (0.6, 0.7) vs ppo/individual (0.5, 0.95, 0.55): 4 of 6 pairs
    assert "| ppo/team > ppo/individual | 0.67 [" in reward
    assert "| poca_0 (algo-1M) | poca/individual, 0 |" in reward  # the run table says whose
    saved = json.loads((out / R.REPORT_RUNS_FILE).read_text())["runs"]
    assert len(saved) == 4 + 6 + 4 + 4 + 4  # each run once, as its own study's
    exported = json.loads((out / "marl_eval.json").read_text())["rl-scan"]["ablation"]
    assert "reward-1M:poca/individual" not in exported
    again = (build_report(out, tmp_path / "again", reference=False) / "report.md").read_text()
    assert "| poca/individual | 3/3 | 70.0 ± 5.0 |" in again  # borrowed again on rebuild


def test_a_study_that_trained_a_condition_keeps_its_own(tmp_path):
    results = tmp_path / "results"
    _study(results, "reward-1M", "reward", {"poca/team": [0.9], "poca/individual": [0.3]})
    _study(results, "algo-1M", "algo", {"poca": [0.7, 0.75, 0.65]})
    md = (build_report(results, tmp_path / "report", reference=False) / "report.md").read_text()
    assert "| poca/individual | 1/1 | 30.0 ± 0.0 |" in md
    assert "Borrowed runs" not in md
