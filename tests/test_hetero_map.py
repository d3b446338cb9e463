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
