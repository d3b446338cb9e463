"""The heterogeneity map: a resumable Optuna study of greedy-team coverages per grid point."""

from __future__ import annotations

import json

import optuna
import pytest

from rl_scan import results as R
from rl_scan.config import ConfigError
from rl_scan.tuning import hetero

SMALL_AXES = {"wheeled_sensor": ("fan",), "quad_speed": (0.1,), "quad_range": (3.5,),
              "flight_time": (0.0, 20.0)}


def test_each_point_is_mixed_minus_the_best_homogeneous_team_and_a_rerun_resumes(
        tmp_path, monkeypatch):
    monkeypatch.setattr(hetero, "AXES", SMALL_AXES)
    folder = hetero.hetero_map(tmp_path, "map", scenes=1)
    data = json.loads((folder / R.HETERO_MAP).read_text())
    assert len(data["points"]) == 2
    by_budget = {p["params"]["flight_time"]: p for p in data["points"]}
    for point in by_budget.values():
        env = hetero.point_env(point["params"])
        mean = {team: hetero.greedy_coverage(env, size, ["train:0"])["time_averaged"][0]
                for team, size in hetero.TEAMS.items()}
        assert point["value"] == pytest.approx(mean["mixed"] - max(mean["quads"],
                                                                   mean["wheeled"]))
    # a 20 s flight budget (10 steps) costs the all-quad team coverage
    assert by_budget[20.0]["mean"]["quads"] < by_budget[0.0]["mean"]["quads"]

    study = optuna.load_study(study_name="map", storage=f"sqlite:///{folder / R.OPTUNA_DB}")
    first = [t.number for t in study.trials]
    hetero.hetero_map(tmp_path, "map", scenes=1, resume=True)  # nothing left to do
    assert [t.number for t in optuna.load_study(
        study_name="map", storage=f"sqlite:///{folder / R.OPTUNA_DB}").trials] == first


def test_bad_map_input_fails_before_any_point(tmp_path, monkeypatch):
    monkeypatch.setattr(hetero, "AXES", SMALL_AXES)
    with pytest.raises(ConfigError, match=r"scenes=0 is invalid"):
        hetero.hetero_map(tmp_path, "map", scenes=0)
    assert not (tmp_path / "map").exists()
    with pytest.raises(ConfigError, match=r"no hetero-map study to resume"):
        hetero.hetero_map(tmp_path, "map", scenes=1, resume=True)
    (tmp_path / "map").mkdir()
    with pytest.raises(ConfigError, match=r"exists: pass --resume"):
        hetero.hetero_map(tmp_path, "map", scenes=1)


def test_a_point_trains_with_the_overrides_the_map_evaluated():
    from rl_scan.cli.env_args import parse_set
    from rl_scan.envs.sim.env_config import make_env_config

    point = {"wheeled_sensor": "sphere", "quad_speed": 0.2, "quad_range": 2.0,
             "flight_time": 300.0}
    args = hetero.set_args(point)
    assert make_env_config(parse_set(args[1::2])) == make_env_config(hetero.point_env(point))


def _team_study(root, name: str, env: dict, finals: dict[str, list[float]]) -> None:
    """A team study folder as ``rl-scan ablate team --set ...`` writes it."""
    import yaml

    study = root / name
    study.mkdir(parents=True)
    (study / R.STUDY_FILE).write_text(yaml.safe_dump(
        {"study": "team", "trials": sum(map(len, finals.values())), "env_config": env}))
    for cond, values in finals.items():
        for seed, final in enumerate(values):
            run = R.trial_run_dir(study, f"{cond}_{seed}")
            run.mkdir(parents=True)
            (run / R.RUN_FILE).write_text(yaml.safe_dump(
                {"algo": "poca", "seed": seed, "params": {"condition": cond, "seed": seed},
                 "env_config": {"scenario": "ablation"}}))
            (run / R.EVAL_FILE).write_text(json.dumps([{
                "training_iteration": 100, "env_steps": 400_000, "coverage": final}]))


def test_team_studies_trained_at_map_points_are_marked_and_tabled(tmp_path, monkeypatch):
    import shutil

    from rl_scan.reports.build import build_report

    monkeypatch.setattr(hetero, "AXES", SMALL_AXES)
    results = tmp_path / "results"
    hetero.hetero_map(results, "map", scenes=1)
    short = {"wheeled_sensor": "fan", "quad_speed": 0.1, "quad_range": 3.5, "flight_time": 20.0}
    _team_study(results, "team-20s", hetero.point_env(short),
                {"2,2": [0.8, 0.9], "0,4": [0.7, 0.75], "4,0": [0.5, 0.6]})
    _team_study(results, "team-default", {},  # the default EnvConfig is the point at 0 s
                {"2,2": [0.6, 0.7], "0,4": [0.9, 0.8]})
    _team_study(results, "team-comm3", {"comm_scheme": 3}, {"2,2": [0.9], "0,4": [0.1]})
    # at the 20 s point, without a 4 wheeled team of its own (team-20s has one: the same env)
    _team_study(results, "team-20s-b", hetero.point_env(short), {"2,2": [0.65], "0,4": [0.4]})
    # 4 wheeled robots with another sensor: a different env for them, never borrowed
    sphere = {**short, "wheeled_sensor": "sphere"}
    _team_study(results, "team-sphere", hetero.point_env(sphere), {"4,0": [0.99, 0.99, 0.99]})
    out = build_report(results, tmp_path / "report", reference=False)
    md = (out / "report.md").read_text()
    # mixed 85.0 vs the better homogeneous team (4 quads, 72.5): +12.5, both mixed runs
    # beat both quad runs: P = 1
    assert ("| team-20s | fan, 0.1, 3.5, 20.0 | 400,000 | 0,4: 2, 2,2: 2, 4,0: 2 | 85.0 | "
            "72.5 (0,4) | +12.5 | 1.00 [1.00, 1.00] |") in md
    # the default point's 4 wheeled robots are team-20s's: they do not read the quads' flight
    # time, and 4 wheeled robots with sphere sensors (team-sphere) are another env
    assert ("| team-default | fan, 0.1, 3.5, 0.0 | 400,000 | 0,4: 2, 2,2: 2, 4,0: 2 (from "
            "team-20s) | 65.0 | 85.0 (0,4) |") in md
    # a borrowed team can be the best homogeneous one: 65.0 vs 4 wheeled 55.0
    assert ("| team-20s-b | fan, 0.1, 3.5, 20.0 | 400,000 | 0,4: 1, 2,2: 1, 4,0: 2 (from "
            "team-20s) | 65.0 | 55.0 (4,0) | +10.0 | 1.00 [1.00, 1.00] |") in md
    assert "team-comm3 | fan" not in md  # another comm scheme is no point of this map
    shutil.copy(results / "map" / R.HETERO_MAP, out)  # the committed example's layout
    again = (build_report(out, tmp_path / "again", reference=False) / "report.md").read_text()
    assert "| team-20s | fan, 0.1, 3.5, 20.0 | 400,000 |" in again  # rebuilt from runs.json


@pytest.mark.parametrize("team, other_kind", [
    ((4, 0), {"quad": {"max_speed": 0.2, "sensor_range": 2.0}, "quad_flight_time": 100.0}),
    ((0, 4), {"wheeled": {"elevations": [-60.0, 0.0, 60.0], "sensor_range": 3.0}}),
])
def test_a_homogeneous_team_never_reads_the_other_kinds_settings(team, other_kind):
    """Why a trained point may borrow a homogeneous team from another point
    (``borrow.UNREAD_WITHOUT``): step by step, the same observations and rewards."""
    import numpy as np

    from rl_scan.config import deep_merge
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import GreedyTeam
    from rl_scan.envs.sim.env_config import make_env_config
    from rl_scan.reports.borrow import trial_key

    base = {"team": {"wheeled": team[0], "quad": team[1]}, "max_steps": 60}
    cores = [ScanCore(make_env_config(deep_merge(base, extra))) for extra in ({}, other_kind)]
    condition = f"{team[0]},{team[1]}"
    assert trial_key("study:team", condition, other_kind) == trial_key(
        "study:team", condition, {})
    assert trial_key("study:team", "2,2", other_kind) != trial_key("study:team", "2,2", {})
    obs = [core.reset(seed=3, options={"scenario": "train:4"}) for core in cores]
    greedy = GreedyTeam(cores[0])
    for _ in range(60):
        actions = greedy.act(obs[0])
        steps = [core.step(actions) for core in cores]
        obs = [step[0] for step in steps]
        assert obs[0].keys() == obs[1].keys()
        for agent in obs[0]:
            np.testing.assert_array_equal(obs[0][agent], obs[1][agent])
        assert steps[0][1] == steps[1][1]
    assert cores[0].world.n_scanned == cores[1].world.n_scanned > 0
