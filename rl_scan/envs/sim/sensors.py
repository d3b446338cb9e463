"""Raycast sensors: cast every robot's fan, scan cells on first hit, encode observations.

Per ray the observation is ML-Agents' RayPerceptionSensor encoding with four tags:
``[unscanned cell, scanned cell, robot, other] one-hot, miss flag, hit fraction``
(6 floats; miss flag 1 and fraction 1 when nothing is within range). "other" is the
floor, the arena walls/ceiling and the underside of objects (not a cell). A ray that scans
a cell reports it as *unscanned*: that is what it found (and what earned the reward);
from the next step on rays report it as scanned.
"""

from __future__ import annotations

import math

import numba as nb

from rl_scan.envs.sim.grid import NO_CELL, NO_FACE
from rl_scan.envs.sim.raycast import BOUNDARY, MISS, cast_ray
from rl_scan.envs.sim.robots import QUAD

TAG_UNSCANNED, TAG_SCANNED, TAG_ROBOT, TAG_OTHER = 0, 1, 2, 3
N_TAGS = 4
NO_TAG = -1  # a miss: no one-hot entry is set
MISS_FLAG, HIT_FRACTION = N_TAGS, N_TAGS + 1  # columns of a ray block after the tags
RAY_FEATURES = N_TAGS + 2
HIT_ROBOT = min(MISS, BOUNDARY) - 1  # hit code of a robot sphere, beside cast_ray's codes


@nb.njit(cache=True)
def sense(grid, objects, team, state, buffers, scan):
    """Cast all rays, write ray blocks to ``obs[i, :n_rays * RAY_FEATURES]``, count new cells.

    Each ray of a scanning robot (``scan`` and ``state.scanning``) scans the cell it hits
    first; every ray marks the hit object as seen (by a quad too, for the object channel).
    """
    pos, yaw, pitch, radius = state.pos, state.yaw, state.pitch, team.radius
    cell_state, obs, new_cells = state.cell_state, buffers.obs, buffers.new_cells
    near = buffers.near
    n = pos.shape[0]
    for i in range(n):
        k = team.kind[i]
        cy, sy = math.cos(yaw[i]), math.sin(yaw[i])
        cp, sp = math.cos(pitch[i]), math.sin(pitch[i])
        ox, oy, oz = pos[i, 0], pos[i, 1], pos[i, 2]
        rng = team.sensor_range[k]
        scans = scan and state.scanning[i] != 0
        new_cells[i] = 0
        n_near = 0  # only robots within reach of this fan are tested per ray
        for o in range(n):
            if o != i:
                qx, qy, qz = ox - pos[o, 0], oy - pos[o, 1], oz - pos[o, 2]
                reach = rng + radius[o]
                if qx * qx + qy * qy + qz * qz < reach * reach:
                    near[n_near] = o
                    n_near += 1
        for r in range(team.n_rays[k]):
            lx, ly, lz = team.ray_dirs[k, r, 0], team.ray_dirs[k, r, 1], team.ray_dirs[k, r, 2]
            bx, bz = lx * cp - lz * sp, lx * sp + lz * cp
            dx, dy, dz = bx * cy - ly * sy, bx * sy + ly * cy, bz
            t, code, face = cast_ray(grid, (ox, oy, oz), (dx, dy, dz), rng)
            tag = NO_TAG
            if code == BOUNDARY:
                tag = TAG_OTHER
            for m in range(n_near):  # other robots are spheres
                o = near[m]
                qx, qy, qz = ox - pos[o, 0], oy - pos[o, 1], oz - pos[o, 2]
                b = qx * dx + qy * dy + qz * dz
                disc = b * b - (qx * qx + qy * qy + qz * qz - radius[o] * radius[o])
                if disc >= 0.0:
                    to = -b - math.sqrt(disc)
                    if 0.0 < to < t:
                        t, code, tag = to, HIT_ROBOT, TAG_ROBOT
            if code >= 0:
                slot = objects.voxel_slot[code]
                obj = objects.slot_object[slot]
                state.obj_seen[obj] = 1
                if k == QUAD:
                    state.obj_seen_by_quad[obj] = 1
                c = objects.slot_cells[slot, face] if face != NO_FACE else NO_CELL
                if c == NO_CELL:
                    tag = TAG_OTHER
                elif cell_state[c]:
                    tag = TAG_SCANNED
                else:
                    tag = TAG_UNSCANNED
                    if scans:
                        cell_state[c] = 1
                        state.obj_left[obj] -= 1
                        new_cells[i] += 1
            base = r * RAY_FEATURES
            for q in range(N_TAGS):
                obs[i, base + q] = 0.0
            if tag != NO_TAG:
                obs[i, base + tag] = 1.0
            obs[i, base + MISS_FLAG] = 1.0 if code == MISS else 0.0
            obs[i, base + HIT_FRACTION] = t / rng
