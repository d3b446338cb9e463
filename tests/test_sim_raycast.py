"""Exact raycasting: the numba DDA against a brute-force slab test, and the sensor encoding."""

from __future__ import annotations

import numpy as np
import pytest

from rl_scan.envs.core import ScanCore
from rl_scan.envs.sim.raycast import BOUNDARY, MISS, cast_rays, cast_rays_brute_force
from rl_scan.envs.sim.sensors import (
    HIT_FRACTION,
    MISS_FLAG,
    N_TAGS,
    RAY_FEATURES,
    TAG_OTHER,
    TAG_ROBOT,
    TAG_SCANNED,
    TAG_UNSCANNED,
)


def _random_rays(rng, occ3, cell, n):
    shape = np.array(occ3.shape)
    origins = rng.random((n, 3)) * shape * cell
    free = ~occ3[tuple(np.minimum((origins / cell).astype(int), shape - 1).T)]
    origins = origins[free]
    n = len(origins)
    dirs = rng.normal(size=(n, 3))
    axis = rng.random(n) < 0.15  # axis-aligned rays (two zero components)
    dirs[axis] = 0.0
    dirs[axis, rng.integers(0, 3, axis.sum())] = rng.choice([-1.0, 1.0], axis.sum())
    flat = (rng.random(n) < 0.15) & ~axis  # horizontal rays (one zero component)
    dirs[flat, 2] = 0.0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins, dirs, rng.uniform(0.3, 6.0, n)


def _mismatches(occ3, cell, origins, dirs, max_t):
    n = len(origins)
    t, code, face = np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)
    cast_rays(occ3.reshape(-1).astype(np.uint8), np.array(occ3.shape), cell, origins, dirs,
              max_t, t, code, face)
    bad = 0
    for i in range(n):
        rt, rcode, rface = cast_rays_brute_force(occ3, cell, origins[i], dirs[i], max_t[i])
        bad += (rcode != code[i]) or (rface != face[i]) or abs(rt - t[i]) > 1e-9
    return bad, code


def test_dda_matches_brute_force_on_random_grids():
    rng = np.random.default_rng(0)
    total = 0
    for density in (0.01, 0.05, 0.2):
        occ3 = rng.random((24, 20, 12)) < density
        origins, dirs, max_t = _random_rays(rng, occ3, 0.5, 2500)
        bad, code = _mismatches(occ3, 0.5, origins, dirs, max_t)
        assert bad == 0
        assert (code >= 0).any() and (code == BOUNDARY).any() and (code == MISS).any()
        total += len(origins)
    assert total >= 6000


@pytest.mark.parametrize("scenario", ["ablation", "test:0", "train:3"])
def test_dda_matches_brute_force_on_scenario_grids(scenario):
    """Sparse scenes exercise the occupied-box clipping (rays starting outside the box)."""
    world = ScanCore({"scenario": scenario}).world
    occ3 = world.object_id >= 0
    rng = np.random.default_rng(1)
    origins, dirs, max_t = _random_rays(rng, occ3, world.grid.cell_size, 2000)
    bad, code = _mismatches(occ3, world.grid.cell_size, origins, dirs, max_t)
    assert bad == 0 and len(origins) > 1800 and (code >= 0).sum() > 50


def _ray_block(obs, ray):
    return obs[ray * RAY_FEATURES:(ray + 1) * RAY_FEATURES]


def _fan_index(core, robot_kind, elevation_idx, azimuth_deg):
    spec = getattr(core.config, robot_kind)
    per_fan = int(360 / spec.azimuth_step)
    return elevation_idx * per_fan + int(azimuth_deg / spec.azimuth_step)


def test_sensor_tags_unscanned_then_scanned_robot_and_miss():
    core = ScanCore({"scenario": "ablation", "start_jitter": 0.0})
    core.reset(seed=0)
    w = core.world
    # wheeled_0 at 1 m in front of the -x face of cube 0 (x in [5, 8], y in [5.5, 8.5]),
    # facing +x; the horizontal forward ray (elevation 0, azimuth 0) hits that face.
    w.pos[0] = [4.0, 7.0, w.pos[0, 2]]
    w.yaw[0] = 0.0
    # wheeled_1 1 m behind wheeled_0 (azimuth 180 from wheeled_0).
    w.pos[1] = [3.0, 7.0, w.pos[1, 2]]
    w.yaw[1] = 0.0
    zero = {a: np.zeros(sp.shape) for a, sp in core.action_spaces.items()}
    obs, rew, *_ = core.step(zero)
    fwd = _ray_block(obs["wheeled_0"], _fan_index(core, "wheeled", 0, 0))
    assert fwd[TAG_UNSCANNED] == 1 and fwd[:N_TAGS].sum() == 1 and fwd[MISS_FLAG] == 0
    assert fwd[HIT_FRACTION] == pytest.approx((5.0 - 4.0) / 2.0)  # 1 m of a 2 m range
    assert rew["wheeled_0"] > 0
    obs, rew, *_ = core.step(zero)
    fwd = _ray_block(obs["wheeled_0"], _fan_index(core, "wheeled", 0, 0))
    assert fwd[TAG_SCANNED] == 1 and rew["wheeled_0"] == 0  # nothing new in view
    back = _ray_block(obs["wheeled_0"], _fan_index(core, "wheeled", 0, 180))
    assert back[TAG_ROBOT] == 1
    assert back[HIT_FRACTION] == pytest.approx((1.0 - w.radius[1]) / 2.0)
    # wheeled_1's backward ray: the arena wall is 3 m away, beyond the 2 m range -> miss.
    miss = _ray_block(obs["wheeled_1"], _fan_index(core, "wheeled", 0, 180))
    assert miss[:N_TAGS].sum() == 0 and miss[MISS_FLAG] == 1 and miss[HIT_FRACTION] == 1


def test_floor_and_walls_are_tag_other():
    core = ScanCore({"scenario": "ablation", "start_jitter": 0.0})
    core.reset(seed=0)
    w = core.world
    q = core.agent_ids.index("quad_0")
    w.pos[q] = [1.0, 5.0, 1.0]  # 1 m from the -x wall, 5 m from the -y wall, 1 m up
    w.yaw[q], w.pitch[q] = np.pi, 0.0  # facing -x
    obs, *_ = core.step({a: np.zeros(sp.shape) for a, sp in core.action_spaces.items()})
    wall = _ray_block(obs["quad_0"], _fan_index(core, "quad", 1, 0))  # elevation 0, forward
    assert wall[TAG_OTHER] == 1 and wall[HIT_FRACTION] == pytest.approx(1.0 / 3.5)
    down = _ray_block(obs["quad_0"], _fan_index(core, "quad", 0, 90))  # -30 deg, to the side
    assert down[TAG_OTHER] == 1 and down[HIT_FRACTION] == pytest.approx(2.0 / 3.5)  # 1 m / sin 30
