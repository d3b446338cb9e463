"""The scanning world: a voxelized scenario, a team of robots and one numba call per step.

``World.step(actions)`` runs ``step_world``: kinematics with the safety set, all ray
fans, cell scanning, rewards and the whole observation matrix, without Python per robot
or per ray. Robots are ordered as the team's agent ids (wheeled first, then quads).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from rl_scan.config import ConfigError
from rl_scan.envs.sim.comms import OBJECT_FEATURES, scheme_flags, write_state_and_comm
from rl_scan.envs.sim.dynamics import COLLIDE_NONE, collision_at, move_robots
from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.grid import Cells, GridShape, exposed_cells
from rl_scan.envs.sim.objects import voxelize
from rl_scan.envs.sim.raycast import occupied_box
from rl_scan.envs.sim.robots import KINDS, QUAD, WHEELED
from rl_scan.envs.sim.scenarios import Scenario
from rl_scan.envs.sim.sensors import RAY_FEATURES, sense

OWN_FEATURES = {"wheeled": 8, "quad": 9}


@dataclass(frozen=True)
class ObsLayout:
    """Observation size per kind and the column offsets of each robot's blocks."""

    dims: dict[str, int]
    own_off: np.ndarray
    comm_off: np.ndarray
    obj_off: np.ndarray  # -1: no object-information block


def observation_layout(config: EnvConfig) -> ObsLayout:
    """Sizes: rays*6 + own state + teammates' shared info + object info (wheeled only)."""
    flags = scheme_flags(config.comm_scheme)
    counts = {"wheeled": config.team.wheeled, "quad": config.team.quad}
    per_mate = {"wheeled": 3 * (flags[0] + flags[1]), "quad": 3 * (flags[2] + flags[3])}
    dims, offs = {}, {}
    for kind in KINDS:
        spec = getattr(config, kind)
        rays = spec.n_rays * RAY_FEATURES
        mates = sum(per_mate[k] * (counts[k] - (k == kind)) for k in KINDS)
        has_obj = kind == "wheeled" and config.object_info and counts["quad"] > 0
        obj = OBJECT_FEATURES * config.object_info_slots if has_obj else 0
        own = rays
        comm = own + OWN_FEATURES[kind]
        dims[kind] = int(comm + mates + obj)
        offs[kind] = (own, comm, comm + mates if has_obj else -1)
    kinds = ["wheeled"] * counts["wheeled"] + ["quad"] * counts["quad"]
    return ObsLayout(dims=dims,
                     own_off=np.array([offs[k][0] for k in kinds], dtype=np.int64),
                     comm_off=np.array([offs[k][1] for k in kinds], dtype=np.int64),
                     obj_off=np.array([offs[k][2] for k in kinds], dtype=np.int64))


@nb.njit(cache=True)
def step_world(occ, box, shape, cell, actions, dt, kind, pos, vel, yaw, pitch, radius, kin,
               voxel_slot, slot_obj, slot_cells, cell_state, obj_left, obj_seen,
               obj_seen_by_quad, ray_dirs, n_rays, sensor_range, move, scan, obs, new_cells,
               collided, own_off, comm_off, obj_off, extent, vnorm, vznorm, flags, obj_centre,
               obj_top, obj_total, n_slots, dist_buf, near):
    """One world step (or, with move=False and scan=False, just the observation)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    if move:
        move_robots(occ, nx, ny, nz, cell, actions, dt, kind, pos, vel, yaw, pitch, radius,
                    kin[0], kin[1], kin[2], kin[3], kin[4], kin[5], collided)
    sense(occ, nx, ny, nz, cell, box, voxel_slot, slot_obj, slot_cells, cell_state, obj_left,
          obj_seen, obj_seen_by_quad, kind, pos, yaw, pitch, radius, ray_dirs, n_rays,
          sensor_range, 1, scan, obs, new_cells, near)
    write_state_and_comm(obs, own_off, comm_off, obj_off, kind, pos, vel, yaw, pitch, extent,
                         vnorm, vznorm, 1, flags, obj_seen_by_quad, obj_centre, obj_top,
                         obj_left, obj_total, n_slots, dist_buf)


class World:
    """A scenario voxelized into the arena plus the team's state; reset() then step()."""

    def __init__(self, config: EnvConfig, scenario: Scenario):
        self.config, self.scenario = config, scenario
        shape = tuple(int(round(a / config.cell_size)) for a in config.arena)
        self.grid = GridShape(*shape, cell_size=config.cell_size)
        self.object_id = self._voxelize_objects()
        self.cells: Cells = exposed_cells(self.object_id, config.cell_size)
        self._build_lookup()
        self._build_team()
        self.layout = observation_layout(config)
        self.obs = np.zeros((self.n_robots, max(self.layout.dims.values())), dtype=np.float32)
        self.new_cells = np.zeros(self.n_robots, dtype=np.int64)
        self.collided = np.zeros(self.n_robots, dtype=np.int64)
        self._dist_buf = np.zeros(max(self.n_objects, 1))
        self._near = np.zeros(self.n_robots, dtype=np.int64)
        self._args = None

    # ----------------------------------------------------------------- building
    def _voxelize_objects(self) -> np.ndarray:
        grid, extent = self.grid, self.grid.extent
        object_id = np.full(grid.shape, -1, dtype=np.int64)
        flat = object_id.reshape(-1)
        for i, spec in enumerate(self.scenario.objects):
            r = np.hypot(spec.size[0], spec.size[1]) / 2 if spec.yaw % 90 else 0.0
            half = np.array([max(spec.size[0] / 2, r), max(spec.size[1] / 2, r)])
            lo, hi = np.array(spec.position) - half, np.array(spec.position) + half
            if (np.any(lo < 0) or np.any(hi > extent[:2])
                    or spec.z + spec.size[2] > extent[2]):
                raise ConfigError(
                    f"objects[{i}] ({spec.shape} size={list(spec.size)} at "
                    f"position={list(spec.position)}, z={spec.z}) does not fit in the "
                    f"{extent[0]:g} x {extent[1]:g} x {extent[2]:g} m arena")
            vox = voxelize(spec, grid.shape, grid.cell_size)
            if len(vox) == 0:
                raise ConfigError(f"objects[{i}] ({spec.shape} size={list(spec.size)}) covers "
                                  f"no voxel centre of the {grid.cell_size} m grid: too small")
            clash = flat[vox][flat[vox] >= 0]
            if len(clash):
                raise ConfigError(f"objects[{i}] overlaps objects[{int(clash[0])}] in scenario "
                                  f"{self.scenario.name!r}")
            flat[vox] = i
        return object_id

    def _build_lookup(self) -> None:
        flat = self.object_id.reshape(-1)
        self.occ = (flat >= 0).astype(np.uint8)
        slots = np.flatnonzero(flat >= 0)
        self.voxel_slot = np.full(flat.shape, -1, dtype=np.int64)
        self.voxel_slot[slots] = np.arange(len(slots))
        self.slot_obj = flat[slots].astype(np.int64)
        self.slot_cells = np.full((len(slots), 6), -1, dtype=np.int64)
        self.slot_cells[self.voxel_slot[self.cells.voxel], self.cells.face] = np.arange(
            len(self.cells))
        self.n_objects = len(self.scenario.objects)
        self.obj_total = np.bincount(self.cells.obj, minlength=self.n_objects).astype(np.int64)
        idx = np.stack(np.unravel_index(slots, self.grid.shape), axis=1)
        self.obj_centre = np.zeros((self.n_objects, 3))
        self.obj_top = np.zeros(self.n_objects)
        for o in range(self.n_objects):
            mine = idx[self.slot_obj == o]
            self.obj_centre[o] = (mine.mean(axis=0) + 0.5) * self.grid.cell_size
            self.obj_top[o] = (mine[:, 2].max() + 1) * self.grid.cell_size
        self.shape_arr = np.array(self.grid.shape, dtype=np.int64)
        self.box = occupied_box(self.occ, *self.grid.shape)

    def _build_team(self) -> None:
        cfg = self.config
        self.agent_ids = cfg.team.agent_ids
        self.n_robots = len(self.agent_ids)
        if len(self.scenario.starts) < self.n_robots:
            raise ConfigError(f"scenario {self.scenario.name!r} has {len(self.scenario.starts)} "
                              f"start positions; team needs {self.n_robots}")
        self.kind = np.array([WHEELED] * cfg.team.wheeled + [QUAD] * cfg.team.quad, np.int64)
        specs = [cfg.wheeled, cfg.quad]
        self.radius = np.array([specs[k].radius for k in self.kind])
        self.kin = np.array([[s.max_speed for s in specs], [s.max_vertical_speed for s in specs],
                             [s.max_yaw_rate for s in specs], [s.max_pitch_rate for s in specs],
                             [np.radians(s.pitch_limits[0]) for s in specs],
                             [np.radians(s.pitch_limits[1]) for s in specs]])
        n_max = max(s.n_rays for s in specs)
        self.ray_dirs = np.zeros((2, n_max, 3))
        for k, s in enumerate(specs):
            self.ray_dirs[k, :s.n_rays] = s.ray_directions()
        self.n_rays = np.array([s.n_rays for s in specs], dtype=np.int64)
        self.sensor_range = np.array([s.sensor_range for s in specs])
        self.extent = self.grid.extent
        self.vnorm = np.array([s.max_speed * np.sqrt(2.0) for s in specs])
        self.vznorm = np.array([s.max_vertical_speed for s in specs])
        self.flags = scheme_flags(cfg.comm_scheme)
        self.altitude = np.array([specs[k].altitude for k in self.kind])
        n = self.n_robots
        self.pos, self.vel = np.zeros((n, 3)), np.zeros((n, 3))
        self.yaw, self.pitch = np.zeros(n), np.zeros(n)
        self.cell_state = np.zeros(len(self.cells), dtype=np.uint8)
        self.obj_left = self.obj_total.copy()
        self.obj_seen = np.zeros(self.n_objects, dtype=np.uint8)
        self.obj_seen_by_quad = np.zeros(self.n_objects, dtype=np.uint8)

    # ------------------------------------------------------------------ running
    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """Put robots on their starts (facing the arena centre) and observe without scanning."""
        n = self.n_robots
        self.pos[:, :2] = np.array(self.scenario.starts[:n], dtype=np.float64)
        self.pos[:, 2] = self.altitude
        if self.config.start_jitter > 0:
            self._jitter_starts(rng)
        centre = self.extent[:2] / 2
        self.yaw[:] = np.arctan2(centre[1] - self.pos[:, 1], centre[0] - self.pos[:, 0])
        self.pitch[:] = 0.0
        self.vel[:] = 0.0
        for i in range(n):
            if self._collides(i):
                raise ConfigError(f"start of {self.agent_ids[i]} at {self.pos[i].round(2).tolist()}"
                                  f" in scenario {self.scenario.name!r} collides")
        self.cell_state[:] = 0
        self.obj_left[:] = self.obj_total
        self.obj_seen[:] = 0
        self.obj_seen_by_quad[:] = 0
        self.collided[:] = 0
        self._run(np.zeros((n, 5)), move=False, scan=False)
        return self.obs

    def _jitter_starts(self, rng: np.random.Generator) -> None:
        base = self.pos.copy()
        for i in range(self.n_robots):
            for _ in range(100):
                self.pos[i, :2] = base[i, :2] + rng.uniform(-1, 1, 2) * self.config.start_jitter
                if not self._collides(i):
                    break
            else:
                self.pos[i] = base[i]

    def _collides(self, i: int) -> bool:
        g = self.grid
        return collision_at(self.occ, g.nx, g.ny, g.nz, g.cell_size, self.pos[: i + 1],
                            self.radius, i, *self.pos[i]) != COLLIDE_NONE

    def step(self, actions: np.ndarray) -> np.ndarray:
        """Advance one step with actions (n_robots, 5) in [-1, 1]; returns the obs matrix."""
        self._run(actions, move=True, scan=True)
        return self.obs

    def _run(self, actions: np.ndarray, move: bool, scan: bool) -> None:
        if self._args is None:  # arrays are updated in place, so the tuple is built once
            lay = self.layout
            self._actions = np.zeros((self.n_robots, 5))
            self._args = (self.occ, self.box, self.shape_arr, self.grid.cell_size, self._actions,
                          self.config.dt, self.kind, self.pos, self.vel, self.yaw, self.pitch,
                          self.radius, self.kin, self.voxel_slot, self.slot_obj,
                          self.slot_cells, self.cell_state, self.obj_left, self.obj_seen,
                          self.obj_seen_by_quad, self.ray_dirs, self.n_rays,
                          self.sensor_range)
            self._tail = (self.obs, self.new_cells, self.collided, lay.own_off,
                          lay.comm_off, lay.obj_off, self.extent, self.vnorm, self.vznorm,
                          self.flags, self.obj_centre, self.obj_top, self.obj_total,
                          self.config.object_info_slots, self._dist_buf, self._near)
        self._actions[:] = actions
        step_world(*self._args, move, scan, *self._tail)

    @property
    def n_cells(self) -> int:
        return len(self.cells)

    @property
    def n_scanned(self) -> int:
        return int(self.n_cells - self.obj_left.sum())
