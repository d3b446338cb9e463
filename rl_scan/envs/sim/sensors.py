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

from rl_scan.envs.sim.raycast import BOUNDARY, MISS, cast_ray

TAG_UNSCANNED, TAG_SCANNED, TAG_ROBOT, TAG_OTHER = 0, 1, 2, 3
N_TAGS = 4
RAY_FEATURES = N_TAGS + 2


@nb.njit(cache=True)
def sense(occ, nx, ny, nz, cell, box, voxel_slot, slot_obj, slot_cells, cell_state, obj_left,
          obj_seen, obj_seen_by_quad, kind, pos, yaw, pitch, radius, ray_dirs, n_rays,
          sensor_range, quad_kind, scan, obs, new_cells, near):
    """Cast all rays, write ray blocks to ``obs[i, :n_rays*6]``, count newly scanned cells."""
    n = pos.shape[0]
    for i in range(n):
        k = kind[i]
        cy, sy = math.cos(yaw[i]), math.sin(yaw[i])
        cp, sp = math.cos(pitch[i]), math.sin(pitch[i])
        ox, oy, oz = pos[i, 0], pos[i, 1], pos[i, 2]
        rng = sensor_range[k]
        new_cells[i] = 0
        n_near = 0  # only robots within reach of this fan are tested per ray
        for o in range(n):
            if o != i:
                qx, qy, qz = ox - pos[o, 0], oy - pos[o, 1], oz - pos[o, 2]
                reach = rng + radius[o]
                if qx * qx + qy * qy + qz * qz < reach * reach:
                    near[n_near] = o
                    n_near += 1
        for r in range(n_rays[k]):
            lx, ly, lz = ray_dirs[k, r, 0], ray_dirs[k, r, 1], ray_dirs[k, r, 2]
            bx, bz = lx * cp - lz * sp, lx * sp + lz * cp
            dx, dy, dz = bx * cy - ly * sy, bx * sy + ly * cy, bz
            t, code, face = cast_ray(occ, nx, ny, nz, cell, box, ox, oy, oz, dx, dy, dz, rng)
            tag = -1
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
                        t, code, tag = to, MISS - 10, TAG_ROBOT
            if code >= 0:
                slot = voxel_slot[code]
                obj = slot_obj[slot]
                obj_seen[obj] = 1
                if k == quad_kind:
                    obj_seen_by_quad[obj] = 1
                c = slot_cells[slot, face] if face >= 0 else -1
                if c < 0:
                    tag = TAG_OTHER
                elif cell_state[c]:
                    tag = TAG_SCANNED
                else:
                    tag = TAG_UNSCANNED
                    if scan:
                        cell_state[c] = 1
                        obj_left[obj] -= 1
                        new_cells[i] += 1
            base = r * 6
            for q in range(N_TAGS):
                obs[i, base + q] = 0.0
            if tag >= 0:
                obs[i, base + tag] = 1.0
            obs[i, base + 4] = 1.0 if code == MISS else 0.0
            obs[i, base + 5] = t / rng
