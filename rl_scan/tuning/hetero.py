"""``rl-scan experiment hetero-map``: where a mixed team pays (issue #18).

The paper gives the quads a longer sensor (3.5 m) than the wheeled robots (2 m) and half
their speed, but leaves open the wheeled "cube-view" sensor's geometry and any cost of
flying; in this simulator those decide whether 2 wheeled + 2 quads beat 4 quads. The map
is an Optuna study (SQLite, ``optuna.db`` in the study folder) whose trials are the points
of a grid over those assumed parameters (``AXES``). At every point the scripted greedy
team (``rl_scan.envs.heuristics``: cheap and privileged, an upper reference, not a learner)
plays the same scenes as 2 + 2, 0 + 4 and 4 + 0; a trial's value is the mixed team's mean
time-averaged coverage minus the best homogeneous team's (final coverage saturates: the
greedy team finishes most scenes, so how fast it scans is what separates the teams). A
point is added to the study only once it is whole, so re-running the command resumes:
finished points are kept. ``hetero_map.json``
(``R.HETERO_MAP``) holds every point for ``rl-scan report``. Trained points are ordinary
``rl-scan ablate team`` studies run with a point's ``--set`` overrides (``set_args``).
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from rl_scan import results as R
from rl_scan.config import ConfigError, check_range
from rl_scan.envs.sim.scenarios import N_TRAIN

AXES: dict[str, tuple] = {
    "wheeled_sensor": ("fan", "sphere"),
    "quad_speed": (0.1, 0.2),
    "quad_range": (2.0, 3.5),
    "flight_time": (0.0, 400.0, 200.0, 100.0),
}
"""The grid (32 points). wheeled_sensor: the wheeled fan's elevations (``WHEELED_SENSORS``);
quad_speed: the quad's max speed, m/s (paper 0.1: half the wheeled 0.2); quad_range: its
sensor range, m (paper 3.5; 2.0 = the wheeled one); flight_time: seconds a quad flies per
episode (0 = unlimited, the default; an episode lasts 500 x 2 s = 1,000 s)."""
WHEELED_SENSORS = {"fan": (0.0, 20.0, 40.0), "sphere": (-60.0, -30.0, 0.0, 30.0, 60.0, 90.0)}
"""Elevations, degrees: today's fan, and a full sphere standing in for the cube-view sensor."""
TEAMS = {"mixed": (2, 2), "quads": (0, 4), "wheeled": (4, 0)}
"""(wheeled, quads) of each team the greedy plays at every point."""


def point_env(point: dict[str, Any]) -> dict[str, Any]:
    """The EnvConfig overrides of a grid point."""
    return {"wheeled": {"elevations": list(WHEELED_SENSORS[point["wheeled_sensor"]])},
            "quad": {"max_speed": float(point["quad_speed"]),
                     "sensor_range": float(point["quad_range"])},
            "quad_flight_time": float(point["flight_time"])}


def set_args(point: dict[str, Any]) -> list[str]:
    """The point as ``--set KEY=VALUE`` arguments (to train it with ``rl-scan ablate team``)."""
    env = point_env(point)
    elevations = ",".join(f"{e:g}" for e in env["wheeled"]["elevations"])
    return ["--set", f"wheeled.elevations=[{elevations}]",
            "--set", f"quad.max_speed={env['quad']['max_speed']:g}",
            "--set", f"quad.sensor_range={env['quad']['sensor_range']:g}",
            "--set", f"quad_flight_time={env['quad_flight_time']:g}"]


def grid_points() -> list[dict[str, Any]]:
    return [dict(zip(AXES, values)) for values in itertools.product(*AXES.values())]


def greedy_coverage(env: dict[str, Any], team: tuple[int, int], scenes: list[str]
                    ) -> dict[str, list[float]]:
    """The greedy team on each scene (reset seed = the scene's index): its final coverage
    and its time-averaged coverage (the mean over the episode's ``max_steps`` of the
    coverage reached, held after a finish), which also tells how fast it scans."""
    from rl_scan.config import deep_merge
    from rl_scan.envs.core import ScanCore
    from rl_scan.envs.heuristics import GreedyTeam
    from rl_scan.envs.sim.env_config import make_env_config

    config = make_env_config(deep_merge(env, {"team": {"wheeled": team[0], "quad": team[1]}}))
    core = ScanCore(config)
    final, averaged = [], []
    for i, scene in enumerate(scenes):
        obs = core.reset(seed=i, options={"scenario": scene})
        greedy, total, done = GreedyTeam(core), 0.0, False
        while not done:
            obs, _, term, trunc, _ = core.step(greedy.act(obs))
            coverage = core.world.n_scanned / core.world.n_cells
            total += coverage
            done = term or trunc
        final.append(coverage)
        averaged.append((total + coverage * (config.max_steps - core.t)) / config.max_steps)
    return {"final": final, "time_averaged": averaged}


def _distributions() -> dict[str, Any]:
    import optuna

    return {k: optuna.distributions.CategoricalDistribution(list(v)) for k, v in AXES.items()}


def hetero_map(results_dir: str | Path = "results", name: str = "hetero-map", *,
               scenes: int = 8, resume: bool = False) -> Path:
    """Evaluate every grid point not yet in the study (see the module doc); returns the
    study folder."""
    import optuna

    from rl_scan.tuning.launch import check_output_folder

    check_range("scenes", scenes, 1, N_TRAIN)
    folder = Path(results_dir) / name
    check_output_folder(folder, R.OPTUNA_DB, "hetero-map study", resume)
    folder.mkdir(parents=True, exist_ok=True)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name=name, storage=f"sqlite:///{folder / R.OPTUNA_DB}",
                                direction="maximize", load_if_exists=True)
    scene_names = [f"train:{i}" for i in range(scenes)]
    kept = study.user_attrs.get("scenes")
    if kept is not None and kept != scene_names:
        raise ConfigError(f"scenes={scenes} is invalid: allowed {len(kept)}, the number this "
                          f"study in {str(folder)!r} was started with")
    study.set_user_attr("scenes", scene_names)
    distributions = _distributions()
    done = {tuple(t.params[k] for k in AXES) for t in study.trials
            if t.state == optuna.trial.TrialState.COMPLETE}
    points = grid_points()
    for n, point in enumerate(points, 1):
        if tuple(point.values()) in done:
            continue
        start = time.time()
        env = point_env(point)
        coverage = {team: greedy_coverage(env, size, scene_names)
                    for team, size in TEAMS.items()}
        mean = {team: float(np.mean(c["time_averaged"])) for team, c in coverage.items()}
        final = {team: float(np.mean(c["final"])) for team, c in coverage.items()}
        value = mean["mixed"] - max(mean["quads"], mean["wheeled"])
        study.add_trial(optuna.trial.create_trial(
            params=point, distributions=distributions, value=value,
            user_attrs={"coverage": coverage, "mean": mean, "final": final}))
        print(f"point {n:2d}/{len(points)}  " + "  ".join(f"{k}={v:g}" if not isinstance(v, str)
                                                        else f"{k}={v}" for k, v in point.items())
              + "  time-averaged " + "  ".join(f"{t} {m:.3f}" for t, m in mean.items())
              + f"  mixed - best homo {value:+.3f}  ({time.time() - start:.0f} s)", flush=True)
    write_map(study, folder / R.HETERO_MAP)
    return folder


def write_map(study, path: Path) -> None:
    """Every finished point, its EnvConfig overrides (the report finds the trained team
    studies run at a point by them), its teams' coverages and its value, for the report."""
    import optuna

    points = [{"params": t.params, "env": point_env(t.params), "value": t.value,
               **t.user_attrs}
              for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    data = {"axes": {k: list(v) for k, v in AXES.items()}, "teams": TEAMS,
            "scenes": study.user_attrs.get("scenes"), "points": points}
    path.write_text(json.dumps(data, indent=1))
