"""Scenario sampling (determinism, no overlaps, held-out test set) and input errors."""

from __future__ import annotations

import numpy as np
import pytest

from rl_scan.config import ConfigError
from rl_scan.envs.core import ScanCore
from rl_scan.envs.sim.env_config import make_env_config
from rl_scan.envs.sim.scenarios import N_TRAIN, ScenarioDistribution, load_scenario

EXTENT, CELL = np.array([20.0, 20.0, 8.0]), 0.5


def _load(name):
    return load_scenario(name, ScenarioDistribution(), EXTENT, CELL)


def test_named_scenarios_are_deterministic_and_distinct():
    assert _load("train:5") == _load("train:5")
    assert _load("train:5").objects != _load("train:6").objects
    train = {_load(f"train:{i}").objects for i in range(N_TRAIN)}
    assert len(train) == N_TRAIN
    for j in range(5):
        assert _load(f"test:{j}").objects not in train  # held out: never a train scene


@pytest.mark.parametrize("name", ["train:0", "train:42", "train:999", "test:0", "test:4"])
def test_sampled_scenes_fit_without_overlap_and_starts_are_free(name):
    core = ScanCore({"scenario": name, "team": {"wheeled": 4, "quad": 4}})
    core.reset(seed=0)  # raises if a start collides
    w = core.world
    dist = ScenarioDistribution()
    assert dist.n_objects[0] <= w.n_objects <= dist.n_objects[1]
    assert np.all(w.obj_total > 0)  # every object was voxelized and has cells
    # footprint gaps >= min_gap between the voxel footprints of different objects
    cols = [np.argwhere((w.object_id == o).any(axis=2)) for o in range(w.n_objects)]
    for a in range(w.n_objects):
        for b in range(a + 1, w.n_objects):
            d = np.abs(cols[a][:, None, :] - cols[b][None, :, :]).max(axis=2).min()
            assert (d - 1) * CELL >= dist.min_gap - 1e-9  # free cells between them


def test_ablation_scene_is_the_papers():
    w = ScanCore({}).world
    assert w.n_objects == 4 and list(w.obj_total) == [180, 180, 180, 180]


@pytest.mark.parametrize("overrides,needle", [
    ({"max_step": 3}, "unknown config key 'max_step' (did you mean 'max_steps'?)"),
    ({"scenario": "train:1000"}, "scenario='train:1000' is invalid"),
    ({"scenario": "test:5"}, "scenario='test:5' is invalid"),
    ({"comm_scheme": 8}, "comm_scheme=8 is invalid: allowed one of [1, 2, 3, 4, 5, 6, 7]"),
    ({"team": {"wheeled": 0, "quad": 0}}, "between 1 and 8 robots"),
    ({"arena": [20.25, 20, 8]}, "arena.x=20.25 is invalid: allowed a multiple of"),
    ({"dt": -1}, "dt=-1.0 is invalid"),
    ({"quad": {"sensor_range": 0}}, "quad.sensor_range=0.0 is invalid"),
    ({"team": {"wheeled": "two"}}, "team.wheeled='two' is invalid: allowed an integer"),
    ({"scenario": "train:0", "scenario_distribution": {"n_objects": [40, 60]}},
     "scenario_distribution.n_objects=[40, 60] is invalid: allowed at most"),
])
def test_bad_config_names_field_value_and_allowed(overrides, needle):
    with pytest.raises(ConfigError) as e:
        ScanCore(overrides)
    assert needle in str(e.value)


def _yaml(tmp_path, text):
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    return str(path)


def test_yaml_scenario_errors(tmp_path):
    neg = _yaml(tmp_path, "objects:\n  - {shape: box, size: [-1, 2, 2], position: [5, 5]}\n")
    with pytest.raises(ConfigError, match=r"objects\[0\]\.size\.x=-1\.0 is invalid"):
        ScanCore({"scenario": neg})
    overlap = _yaml(tmp_path, "objects:\n  - {shape: box, size: [3, 3, 3], position: [10, 10]}"
                              "\n  - {shape: box, size: [3, 3, 3], position: [11, 10]}\n")
    with pytest.raises(ConfigError, match=r"objects\[1\] overlaps objects\[0\]"):
        ScanCore({"scenario": overlap})
    outside = _yaml(tmp_path, "objects:\n  - {shape: box, size: [3, 3, 3], position: [19, 10]}\n")
    with pytest.raises(ConfigError, match=r"objects\[0\].*does not fit in the 20 x 20 x 8 m"):
        ScanCore({"scenario": outside})
    mesh = _yaml(tmp_path, "objects:\n  - {shape: mesh, path: gone.stl, position: [10, 10]}\n")
    with pytest.raises(ConfigError, match="gone.stl' does not exist"):
        ScanCore({"scenario": mesh})
    typo = _yaml(tmp_path, "objects:\n  - {shape: box, sizes: [3, 3, 3]}\n")
    with pytest.raises(ConfigError, match=r"unknown config key 'objects\[0\]\.sizes'"):
        ScanCore({"scenario": typo})


def test_yaml_scenario_with_relative_mesh_path(tmp_path):
    import trimesh

    trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "part.stl")
    scene = _yaml(tmp_path, "objects:\n  - {shape: mesh, path: part.stl, size: [3, 3, 3],"
                            " position: [10, 10]}\n")
    assert ScanCore({"scenario": scene}).world.n_cells == 180


def test_config_round_trips_through_plain_dicts():
    from rl_scan.config import to_dict

    cfg = make_env_config({"team": {"wheeled": 1, "quad": 3}, "quad": {"sensor_range": 3.0}})
    assert make_env_config(to_dict(cfg)) == cfg
