"""Communication schemes (the paper's Table II) and the quad -> wheeled object channel.

A scheme switches four kinds of shared information on or off: the positions and the
velocities of wheeled robots, and the positions and velocities of quadcopters. Every
robot receives, for each teammate whose kind's switch is on, its relative position
and/or its velocity. The paper found schemes 1 and 6 converge; it recommends scheme 1
plus *object information*: quadcopters tell wheeled robots about objects they have seen
(here: for the nearest ``object_info_slots`` such objects, relative x/y, top height,
fraction of cells still unscanned, and a presence flag).

Own state (always present): position / arena extent (3), world velocity / limit (3),
cos and sin of yaw, and (quads only) pitch / 90 degrees.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from rl_scan.envs.sim.robots import KINDS, QUAD

# scheme -> (wheeled positions, wheeled velocity, quad positions, quad velocity): the
# paper's Table II, i.e. per sender kind (KINDS order) the SHARE_POS and SHARE_VEL switch.
SCHEMES = {
    1: (True, True, False, False),
    2: (False, True, False, False),
    3: (False, False, False, False),
    4: (True, False, False, False),
    5: (True, True, True, False),
    6: (True, False, True, True),
    7: (True, True, True, True),
}
SHARE_POS, SHARE_VEL = 0, 1
MATE_FEATURES = 3  # per shared item of a teammate: its relative position, or its velocity
OWN_POS, OWN_VEL, OWN_COS_YAW, OWN_SIN_YAW, OWN_PITCH = 0, 3, 6, 7, 8  # own-state columns
OWN_FEATURES = {"wheeled": OWN_SIN_YAW + 1, "quad": OWN_PITCH + 1}
OBJ_DX, OBJ_DY, OBJ_TOP, OBJ_LEFT, OBJ_PRESENT = range(5)  # object-slot columns
OBJECT_FEATURES = OBJ_PRESENT + 1
NO_BLOCK = -1  # the object-block column of a robot that gets no object information
SQRT2 = math.sqrt(2.0)  # horizontal velocities are scaled by max_speed * SQRT2 (both axes)


def scheme_shares(scheme: int) -> np.ndarray:
    """The scheme's switches as a (kinds, 2) int table: [sender kind, SHARE_POS/SHARE_VEL]."""
    return np.array(SCHEMES[scheme], dtype=np.int64).reshape(len(KINDS), 2)


@nb.njit(cache=True)
def write_state_and_comm(grid, objects, team, state, columns, buffers):
    """Write own state, teammates' shared info and object info into each robot's row."""
    obs, extent, kind = buffers.obs, grid.extent, team.kind
    pos, vel, yaw, pitch = state.pos, state.vel, state.yaw, state.pitch
    max_speed, max_vz = team.max_speed, team.max_vertical_speed
    n = pos.shape[0]
    half_pi = 0.5 * math.pi
    for i in range(n):
        k = kind[i]
        c = columns.own[i]
        for a in range(3):
            obs[i, c + OWN_POS + a] = pos[i, a] / extent[a]
        vnorm = max_speed[k] * SQRT2
        obs[i, c + OWN_VEL] = vel[i, 0] / vnorm
        obs[i, c + OWN_VEL + 1] = vel[i, 1] / vnorm
        obs[i, c + OWN_VEL + 2] = vel[i, 2] / max_vz[k] if max_vz[k] > 0 else 0.0
        obs[i, c + OWN_COS_YAW] = math.cos(yaw[i])
        obs[i, c + OWN_SIN_YAW] = math.sin(yaw[i])
        if k == QUAD:
            obs[i, c + OWN_PITCH] = pitch[i] / half_pi
        c = columns.comm[i]
        for j in range(n):
            if j == i:
                continue
            kj = kind[j]
            if columns.shares[kj, SHARE_POS]:
                for a in range(3):
                    obs[i, c + a] = (pos[j, a] - pos[i, a]) / extent[a]
                c += MATE_FEATURES
            if columns.shares[kj, SHARE_VEL]:
                vnorm = max_speed[kj] * SQRT2
                obs[i, c] = vel[j, 0] / vnorm
                obs[i, c + 1] = vel[j, 1] / vnorm
                obs[i, c + 2] = vel[j, 2] / max_vz[kj] if max_vz[kj] > 0 else 0.0
                c += MATE_FEATURES
        c = columns.objects[i]
        if c == NO_BLOCK:
            continue
        # Nearest objects seen by any quad, by horizontal distance (selection by min search).
        dist = buffers.object_dist
        n_obj = objects.centre.shape[0]
        for o in range(n_obj):
            if state.obj_seen_by_quad[o]:
                ddx, ddy = objects.centre[o, 0] - pos[i, 0], objects.centre[o, 1] - pos[i, 1]
                dist[o] = ddx * ddx + ddy * ddy
            else:
                dist[o] = np.inf
        for s in range(columns.object_slots):
            best, best_d = -1, np.inf
            for o in range(n_obj):
                if dist[o] < best_d:
                    best, best_d = o, dist[o]
            b = c + s * OBJECT_FEATURES
            if best < 0:
                for q in range(OBJECT_FEATURES):
                    obs[i, b + q] = 0.0
                continue
            dist[best] = np.inf
            obs[i, b + OBJ_DX] = (objects.centre[best, 0] - pos[i, 0]) / extent[0]
            obs[i, b + OBJ_DY] = (objects.centre[best, 1] - pos[i, 1]) / extent[1]
            obs[i, b + OBJ_TOP] = objects.top[best] / extent[2]
            obs[i, b + OBJ_LEFT] = state.obj_left[best] / objects.n_cells[best]
            obs[i, b + OBJ_PRESENT] = 1.0
