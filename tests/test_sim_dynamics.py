"""Kinematics and the safety set: limits, blocked collisions, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rl_scan.envs.core import ScanCore
from rl_scan.envs.sim.dynamics import COLLIDE_NONE, COLLIDE_OBJECT, collision_at
from rl_scan.envs.sim.robots import QUAD, WHEELED

DT = 2.0


def _no_overlap(world) -> bool:
    g = world.grid
    return all(collision_at(world.occ, g.nx, g.ny, g.nz, g.cell_size, world.pos, world.radius,
                            i, *world.pos[i]) == COLLIDE_NONE for i in range(world.n_robots))


@pytest.mark.parametrize("scenario", ["ablation", "test:1", "train:7"])
def test_random_motion_respects_limits_and_never_enters_anything(scenario):
    core = ScanCore({"scenario": scenario, "max_steps": 400})
    core.reset(seed=1)
    w = core.world
    rng = np.random.default_rng(2)
    wheeled_z = w.pos[w.kind == WHEELED, 2].copy()
    collisions = 0
    for _ in range(400):
        acts = {a: rng.uniform(-1.3, 1.3, sp.shape) for a, sp in core.action_spaces.items()}
        pos0, yaw0, pitch0 = w.pos.copy(), w.yaw.copy(), w.pitch.copy()
        core.step(acts)
        assert _no_overlap(w)
        for i in range(w.n_robots):
            spec = core.config.quad if w.kind[i] == QUAD else core.config.wheeled
            d = w.pos[i] - pos0[i]
            # body-frame components, using the yaw after the turn (the kernel turns first)
            c, s = math.cos(w.yaw[i]), math.sin(w.yaw[i])
            fwd, left = d[0] * c + d[1] * s, -d[0] * s + d[1] * c
            lim = spec.max_speed * DT + 1e-9
            assert abs(fwd) <= lim and abs(left) <= lim
            assert abs(d[2]) <= spec.max_vertical_speed * DT + 1e-9
            dyaw = math.atan2(math.sin(w.yaw[i] - yaw0[i]), math.cos(w.yaw[i] - yaw0[i]))
            assert abs(dyaw) <= min(spec.max_yaw_rate * DT, math.pi) + 1e-9
            lo, hi = np.radians(spec.pitch_limits)
            assert lo - 1e-9 <= w.pitch[i] <= hi + 1e-9
            assert abs(w.pitch[i] - pitch0[i]) <= spec.max_pitch_rate * DT + 1e-9
        collisions += int((w.collided != 0).sum())
        if not core.done:
            continue
        break
    assert np.allclose(w.pos[w.kind == WHEELED, 2], wheeled_z)  # wheeled robots stay on the ground
    assert collisions > 0  # random driving does bump into things: the check was exercised


def test_a_colliding_move_is_blocked_whole_and_costs_one():
    core = ScanCore({"scenario": "ablation", "start_jitter": 0.0})
    core.reset(seed=0)
    w = core.world
    w.pos[0] = [4.55, 7.0, w.pos[0, 2]]  # 0.2 m in front of cube 0's -x face at x = 5
    w.yaw[0] = 0.0
    before = w.pos[0].copy()
    zero = {a: np.zeros(sp.shape) for a, sp in core.action_spaces.items()}
    _, rew, *_ = core.step({**zero, "wheeled_0": np.array([1.0, 0.0, 0.0])})
    assert w.collided[0] == COLLIDE_OBJECT
    assert np.array_equal(w.pos[0], before) and np.all(w.vel[0] == 0)
    assert rew["wheeled_0"] == -1.0 + w.new_cells[0]
    # backing away is free
    core.step({**zero, "wheeled_0": np.array([-1.0, 0.0, 0.0])})
    assert w.collided[0] == 0 and w.pos[0, 0] == pytest.approx(4.55 - 0.4)


def test_quads_cannot_leave_through_floor_or_ceiling():
    core = ScanCore({"scenario": "ablation", "start_jitter": 0.0})
    core.reset(seed=0)
    w = core.world
    q = core.agent_ids.index("quad_0")
    zero = {a: np.zeros(sp.shape) for a, sp in core.action_spaces.items()}
    for up in (-1.0, 1.0):
        for _ in range(60):
            core.step({**zero, "quad_0": np.array([0, 0, 0, up, 0.0])})
        r = w.radius[q]
        assert r <= w.pos[q, 2] <= w.grid.extent[2] - r
        assert w.collided[q] != 0  # it ended pressed against the bound


def test_same_seed_same_episode_different_seed_different():
    def episode(seed):
        core = ScanCore({"scenario": "ablation", "max_steps": 40})
        obs = core.reset(seed=seed)
        rng = np.random.default_rng(0)
        trace = [np.concatenate(list(obs.values()))]
        while not core.done:
            acts = {a: rng.uniform(-1, 1, sp.shape) for a, sp in core.action_spaces.items()}
            obs, rew, *_ = core.step(acts)
            trace.append(np.concatenate([*obs.values(), list(rew.values())]))
        return trace

    a, b, c = episode(5), episode(5), episode(6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])  # start jitter depends on the seed


@pytest.mark.parametrize("budget", [20 * DT, 0.0])
def test_a_quad_out_of_flight_time_holds_still_and_scans_nothing(budget):
    """quad_flight_time = 20 steps: quads fly and scan 20 steps, then hold their place and
    scan nothing while the wheeled robots go on; 0 (the default) is no limit."""
    from rl_scan.envs.heuristics import GreedyTeam

    core = ScanCore({"scenario": "train:3", "quad_flight_time": budget, "dt": DT})
    obs = core.reset(seed=0)
    w, greedy = core.world, GreedyTeam(core)
    quads = w.kind == QUAD
    scanned = {"flying": 0, "landed": 0}
    moved_after = np.zeros(w.n_robots, dtype=bool)
    for t in range(60):
        pos = w.pos.copy()
        obs, *_ = core.step(greedy.act(obs))
        phase = "flying" if t < 20 else "landed"
        scanned[phase] += int(w.new_cells[quads].sum())
        if t >= 20:
            moved_after |= np.any(w.pos != pos, axis=1)
    assert scanned["flying"] > 0
    assert moved_after[~quads].any()
    if budget:
        assert scanned["landed"] == 0 and not moved_after[quads].any()
        assert not w.scanning[quads].any() and w.scanning[~quads].all()
    else:
        assert scanned["landed"] > 0 and moved_after[quads].any()
