"""The scanning world: a voxelized scenario, a team of robots and one numba call per step.

``World.step(actions)`` runs ``step_world``: kinematics with the safety set, all ray
fans, cell scanning, rewards and the whole observation matrix, without Python per robot
or per ray. Robots are ordered as the team's agent ids (wheeled first, then quads).
The kernels share six records of arrays, built once per world and updated in place:
``VoxelGrid`` and ``Objects`` (the scene), ``Team`` (fixed robot parameters), ``State``
(what a step changes), ``ObsColumns`` (the observation layout) and ``Buffers`` (per-step
input, outputs and scratch).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np

from rl_scan.config import ConfigError
from rl_scan.envs.sim.comms import (
    MATE_FEATURES,
    NO_BLOCK,
    OBJECT_FEATURES,
    OWN_FEATURES,
    scheme_shares,
    write_state_and_comm,
)
from rl_scan.envs.sim.dynamics import COLLIDE_NONE, collision_at, move_robots
from rl_scan.envs.sim.env_config import EnvConfig
from rl_scan.envs.sim.grid import (
    FREE,
    N_FACES,
    NO_CELL,
    Cells,
    GridShape,
    Objects,
    VoxelGrid,
    exposed_cells,
)
from rl_scan.envs.sim.objects import voxelize
from rl_scan.envs.sim.raycast import occupied_box
from rl_scan.envs.sim.robots import ACTION_WIDTH, KINDS, QUAD, WHEELED, Team, build_team
from rl_scan.envs.sim.scenarios import Scenario
from rl_scan.envs.sim.sensors import RAY_FEATURES, sense


class State(NamedTuple):
    """Everything a step changes and the next step reads; reset() rewrites it."""

    pos: np.ndarray
    """(n, 3) robot positions, metres."""
    vel: np.ndarray
    """(n, 3) world-frame velocities of the last step, m/s."""
    yaw: np.ndarray
    """(n,) radians in [-pi, pi]."""
    pitch: np.ndarray
    """(n,) radians."""
    cell_state: np.ndarray
    """(cells,) uint8, 1 = scanned."""
    obj_left: np.ndarray
    """(objects,) int64 unscanned cells per object."""
    obj_seen: np.ndarray
    """(objects,) uint8, 1 = some ray has hit the object."""
    obj_seen_by_quad: np.ndarray
    """(objects,) uint8, 1 = some quad's ray has hit it (the object channel reports these)."""
    scanning: np.ndarray
    """(n,) uint8, 1 = the robot's rays scan cells (0: a quad landed, its flight time spent)."""


class ObsColumns(NamedTuple):
    """Where each robot's blocks start in its observation row, and what the channels carry."""

    own: np.ndarray
    """(n,) int64 column of the own-state block (after the ray blocks)."""
    comm: np.ndarray
    """(n,) int64 column of the teammates' block."""
    objects: np.ndarray
    """(n,) int64 column of the object-information block, or NO_BLOCK."""
    shares: np.ndarray
    """(kinds, 2) int64 comm scheme switches, see ``comms.scheme_shares``."""
    object_slots: int
    """Objects described by the object-information block."""


class Buffers(NamedTuple):
    """Arrays a step overwrites: its input, its outputs and scratch space (no state)."""

    actions: np.ndarray
    """(n, ACTION_WIDTH) actions in [-1, 1]."""
    obs: np.ndarray
    """(n, widest observation) float32 observation rows."""
    new_cells: np.ndarray
    """(n,) int64 cells each robot scanned this step."""
    collided: np.ndarray
    """(n,) int64 COLLIDE_* code of each robot's move this step."""
    near: np.ndarray
    """(n,) int64 scratch: robots within reach of a fan."""
    object_dist: np.ndarray
    """(max(objects, 1),) scratch: squared distances to the objects."""


@dataclass(frozen=True)
class ObsLayout:
    """Observation size per kind and the kernels' view of the layout."""

    dims: dict[str, int]
    columns: ObsColumns


def observation_layout(config: EnvConfig) -> ObsLayout:
    """Sizes: rays + own state + teammates' shared info + object info (wheeled only)."""
    shares = scheme_shares(config.comm_scheme)
    counts = {"wheeled": config.team.wheeled, "quad": config.team.quad}
    per_mate = {kind: MATE_FEATURES * int(shares[k].sum()) for k, kind in enumerate(KINDS)}
    dims, own, comm, objects = {}, {}, {}, {}
    for kind in KINDS:
        mates = sum(per_mate[k] * (counts[k] - (k == kind)) for k in KINDS)
        has_obj = kind == "wheeled" and config.object_info and counts["quad"] > 0
        own[kind] = getattr(config, kind).n_rays * RAY_FEATURES
        comm[kind] = own[kind] + OWN_FEATURES[kind]
        objects[kind] = comm[kind] + mates if has_obj else NO_BLOCK
        obj = OBJECT_FEATURES * config.object_info_slots if has_obj else 0
        dims[kind] = int(comm[kind] + mates + obj)
    kinds = ["wheeled"] * counts["wheeled"] + ["quad"] * counts["quad"]

    def per_robot(column: dict[str, int]) -> np.ndarray:
        return np.array([column[k] for k in kinds], dtype=np.int64)

    return ObsLayout(dims=dims, columns=ObsColumns(
        own=per_robot(own), comm=per_robot(comm), objects=per_robot(objects), shares=shares,
        object_slots=config.object_info_slots))


@nb.njit(cache=True)
def step_world(grid, objects, team, state, columns, buffers, dt, move, scan):
    """One world step (or, with move=False and scan=False, just the observation)."""
    if move:
        move_robots(grid, team, state, buffers.actions, dt, buffers.collided)
    sense(grid, objects, team, state, buffers, scan)
    write_state_and_comm(grid, objects, team, state, columns, buffers)


@nb.njit(cache=True)
def step_world_fields(records, dt, move, scan):
    """``step_world`` with its six records passed as plain tuples of their fields.

    Numba's dispatcher types a namedtuple argument by spelling out its class and field
    names on every call: about 0.1 us a field, 3-4 us (over 10 %) of a step here. A plain
    tuple is typed from its items alone, and rebuilding the records here costs nothing.
    """
    grid, objects, team, state, columns, buffers = records
    step_world(VoxelGrid(*grid), Objects(*objects), Team(*team), State(*state),
               ObsColumns(*columns), Buffers(*buffers), dt, move, scan)


def _alias(record: str, field: str) -> property:
    """A read-only attribute forwarding to a record's field (the array itself, not a copy)."""
    return property(lambda world: getattr(getattr(world, record), field),
                    doc=f"``{record}.{field}``, under the name the env's readers use.")


class World:
    """A scenario voxelized into the arena plus the team's state; reset() then step()."""

    # Record fields under the names the adapters, scripted teams, renderer and tests read.
    occ, shape_arr = _alias("voxels", "occ"), _alias("voxels", "shape")
    obj_total, obj_centre = _alias("objects", "n_cells"), _alias("objects", "centre")
    obj_top = _alias("objects", "top")
    kind, radius = _alias("team", "kind"), _alias("team", "radius")
    ray_dirs, n_rays = _alias("team", "ray_dirs"), _alias("team", "n_rays")
    sensor_range = _alias("team", "sensor_range")
    pos, vel = _alias("state", "pos"), _alias("state", "vel")
    yaw, pitch = _alias("state", "yaw"), _alias("state", "pitch")
    cell_state, obj_left = _alias("state", "cell_state"), _alias("state", "obj_left")
    obj_seen, obj_seen_by_quad = _alias("state", "obj_seen"), _alias("state", "obj_seen_by_quad")
    scanning = _alias("state", "scanning")
    obs, new_cells = _alias("buffers", "obs"), _alias("buffers", "new_cells")
    collided = _alias("buffers", "collided")

    def __init__(self, config: EnvConfig, scenario: Scenario):
        self.config, self.scenario = config, scenario
        shape = tuple(int(round(a / config.cell_size)) for a in config.arena)
        self.grid = GridShape(*shape, cell_size=config.cell_size)
        self.object_id = self._voxelize_objects()
        self.cells: Cells = exposed_cells(self.object_id, config.cell_size)
        self.n_objects = len(self.scenario.objects)
        self.voxels = self._build_voxels()
        self.objects = self._build_objects()
        self._build_team()
        self.layout = observation_layout(config)
        n = self.n_robots
        self.state = State(pos=np.zeros((n, 3)), vel=np.zeros((n, 3)), yaw=np.zeros(n),
                           pitch=np.zeros(n),
                           cell_state=np.zeros(len(self.cells), dtype=np.uint8),
                           obj_left=self.objects.n_cells.copy(),
                           obj_seen=np.zeros(self.n_objects, dtype=np.uint8),
                           obj_seen_by_quad=np.zeros(self.n_objects, dtype=np.uint8),
                           scanning=np.ones(n, dtype=np.uint8))
        self.steps_taken = 0
        # steps a quad flies per episode (None: unlimited)
        self.flight_steps = (int(config.quad_flight_time // config.dt)
                             if config.quad_flight_time > 0 else None)
        width = max(self.layout.dims.values())
        self.buffers = Buffers(actions=np.zeros((n, ACTION_WIDTH)),
                               obs=np.zeros((n, width), dtype=np.float32),
                               new_cells=np.zeros(n, dtype=np.int64),
                               collided=np.zeros(n, dtype=np.int64),
                               near=np.zeros(n, dtype=np.int64),
                               object_dist=np.zeros(max(self.n_objects, 1)))
        # Arrays are updated in place, so the kernel's arguments are built once.
        self._fields = tuple(tuple(record) for record in (
            self.voxels, self.objects, self.team, self.state, self.layout.columns,
            self.buffers))

    # ----------------------------------------------------------------- building
    def _voxelize_objects(self) -> np.ndarray:
        grid, extent = self.grid, self.grid.extent
        object_id = np.full(grid.shape, FREE, dtype=np.int64)
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

    def _build_voxels(self) -> VoxelGrid:
        occ = (self.object_id.reshape(-1) >= 0).astype(np.uint8)
        return VoxelGrid(occ=occ, shape=np.array(self.grid.shape, dtype=np.int64),
                         cell=self.grid.cell_size, box=occupied_box(occ, *self.grid.shape),
                         extent=self.grid.extent)

    def _build_objects(self) -> Objects:
        flat = self.object_id.reshape(-1)
        slots = np.flatnonzero(flat >= 0)
        voxel_slot = np.full(flat.shape, FREE, dtype=np.int64)
        voxel_slot[slots] = np.arange(len(slots))
        slot_object = flat[slots].astype(np.int64)
        slot_cells = np.full((len(slots), N_FACES), NO_CELL, dtype=np.int64)
        slot_cells[voxel_slot[self.cells.voxel], self.cells.face] = np.arange(len(self.cells))
        n_cells = np.bincount(self.cells.obj, minlength=self.n_objects).astype(np.int64)
        idx = np.stack(np.unravel_index(slots, self.grid.shape), axis=1)
        centre, top = np.zeros((self.n_objects, 3)), np.zeros(self.n_objects)
        for o in range(self.n_objects):
            mine = idx[slot_object == o]
            centre[o] = (mine.mean(axis=0) + 0.5) * self.grid.cell_size
            top[o] = (mine[:, 2].max() + 1) * self.grid.cell_size
        return Objects(voxel_slot=voxel_slot, slot_object=slot_object, slot_cells=slot_cells,
                       n_cells=n_cells, centre=centre, top=top)

    def _build_team(self) -> None:
        cfg = self.config
        self.agent_ids = cfg.team.agent_ids
        self.n_robots = len(self.agent_ids)
        if len(self.scenario.starts) < self.n_robots:
            raise ConfigError(f"scenario {self.scenario.name!r} has {len(self.scenario.starts)} "
                              f"start positions; team needs {self.n_robots}")
        kind = np.array([WHEELED] * cfg.team.wheeled + [QUAD] * cfg.team.quad, np.int64)
        specs = [getattr(cfg, k) for k in KINDS]
        self.team: Team = build_team(specs, kind)
        self.altitude = np.array([specs[k].altitude for k in kind])

    # ------------------------------------------------------------------ running
    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """Put robots on their starts (facing the arena centre) and observe without scanning."""
        n, state = self.n_robots, self.state
        state.pos[:, :2] = np.array(self.scenario.starts[:n], dtype=np.float64)
        state.pos[:, 2] = self.altitude
        if self.config.start_jitter > 0:
            self._jitter_starts(rng)
        centre = self.voxels.extent[:2] / 2
        state.yaw[:] = np.arctan2(centre[1] - state.pos[:, 1], centre[0] - state.pos[:, 0])
        state.pitch[:] = 0.0
        state.vel[:] = 0.0
        for i in range(n):
            if self._collides(i):
                raise ConfigError(f"start of {self.agent_ids[i]} at "
                                  f"{state.pos[i].round(2).tolist()} in scenario "
                                  f"{self.scenario.name!r} collides")
        state.cell_state[:] = 0
        state.obj_left[:] = self.objects.n_cells
        state.obj_seen[:] = 0
        state.obj_seen_by_quad[:] = 0
        state.scanning[:] = 1
        self.steps_taken = 0
        self.buffers.collided[:] = 0
        self._run(np.zeros((n, ACTION_WIDTH)), move=False, scan=False)
        return self.buffers.obs

    def _jitter_starts(self, rng: np.random.Generator) -> None:
        pos = self.state.pos
        base = pos.copy()
        for i in range(self.n_robots):
            for _ in range(100):
                pos[i, :2] = base[i, :2] + rng.uniform(-1, 1, 2) * self.config.start_jitter
                if not self._collides(i):
                    break
            else:
                pos[i] = base[i]

    def _collides(self, i: int) -> bool:
        g, pos = self.grid, self.state.pos
        return collision_at(self.voxels.occ, g.nx, g.ny, g.nz, g.cell_size, pos[: i + 1],
                            self.team.radius, i, *pos[i]) != COLLIDE_NONE

    def step(self, actions: np.ndarray) -> np.ndarray:
        """Advance one step with actions (n_robots, ACTION_WIDTH) in [-1, 1]; returns obs."""
        self._run(actions, move=True, scan=True)
        self.steps_taken += 1
        return self.buffers.obs

    def _land_spent_quads(self, actions: np.ndarray) -> None:
        """Past the flight budget quads hold still and stop scanning (``quad_flight_time``)."""
        if self.flight_steps is not None and self.steps_taken >= self.flight_steps:
            quads = self.team.kind == QUAD
            actions[quads] = 0.0
            self.state.scanning[quads] = 0

    def _run(self, actions: np.ndarray, move: bool, scan: bool) -> None:
        self.buffers.actions[:] = actions
        if move:
            self._land_spent_quads(self.buffers.actions)
        step_world_fields(self._fields, self.config.dt, move, scan)

    @property
    def n_cells(self) -> int:
        return len(self.cells)

    @property
    def n_scanned(self) -> int:
        return int(self.n_cells - self.state.obj_left.sum())
