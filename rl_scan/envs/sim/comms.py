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

# scheme -> (wheeled positions, wheeled velocity, quad positions, quad velocity)
SCHEMES = {
    1: (True, True, False, False),
    2: (False, True, False, False),
    3: (False, False, False, False),
    4: (True, False, False, False),
    5: (True, True, True, False),
    6: (True, False, True, True),
    7: (True, True, True, True),
}
OBJECT_FEATURES = 5


def scheme_flags(scheme: int) -> np.ndarray:
    """The four switches of a scheme as an int array (for the kernel)."""
    return np.array(SCHEMES[scheme], dtype=np.int64)


@nb.njit(cache=True)
def write_state_and_comm(obs, own_off, comm_off, obj_off, kind, pos, vel, yaw, pitch,
                         extent, vnorm, vznorm, quad_kind, flags, obj_seen_by_quad,
                         obj_centre, obj_top, obj_left, obj_total, n_slots, dist_buf):
    """Write own state, teammates' shared info and object info into each robot's row."""
    n = pos.shape[0]
    half_pi = 0.5 * math.pi
    for i in range(n):
        k = kind[i]
        c = own_off[i]
        for a in range(3):
            obs[i, c + a] = pos[i, a] / extent[a]
        obs[i, c + 3] = vel[i, 0] / vnorm[k]
        obs[i, c + 4] = vel[i, 1] / vnorm[k]
        obs[i, c + 5] = vel[i, 2] / vznorm[k] if vznorm[k] > 0 else 0.0
        obs[i, c + 6] = math.cos(yaw[i])
        obs[i, c + 7] = math.sin(yaw[i])
        if k == quad_kind:
            obs[i, c + 8] = pitch[i] / half_pi
        c = comm_off[i]
        for j in range(n):
            if j == i:
                continue
            kj = kind[j]
            base = 2 if kj == quad_kind else 0
            if flags[base]:
                for a in range(3):
                    obs[i, c + a] = (pos[j, a] - pos[i, a]) / extent[a]
                c += 3
            if flags[base + 1]:
                obs[i, c] = vel[j, 0] / vnorm[kj]
                obs[i, c + 1] = vel[j, 1] / vnorm[kj]
                obs[i, c + 2] = vel[j, 2] / vznorm[kj] if vznorm[kj] > 0 else 0.0
                c += 3
        c = obj_off[i]
        if c < 0:
            continue
        # Nearest objects seen by any quad, by horizontal distance (selection by min search).
        n_obj = obj_centre.shape[0]
        for o in range(n_obj):
            if obj_seen_by_quad[o]:
                ddx, ddy = obj_centre[o, 0] - pos[i, 0], obj_centre[o, 1] - pos[i, 1]
                dist_buf[o] = ddx * ddx + ddy * ddy
            else:
                dist_buf[o] = np.inf
        for s in range(n_slots):
            best, best_d = -1, np.inf
            for o in range(n_obj):
                if dist_buf[o] < best_d:
                    best, best_d = o, dist_buf[o]
            b = c + s * 5
            if best < 0:
                for q in range(5):
                    obs[i, b + q] = 0.0
                continue
            dist_buf[best] = np.inf
            obs[i, b] = (obj_centre[best, 0] - pos[i, 0]) / extent[0]
            obs[i, b + 1] = (obj_centre[best, 1] - pos[i, 1]) / extent[1]
            obs[i, b + 2] = obj_top[best] / extent[2]
            obs[i, b + 3] = obj_left[best] / obj_total[best]
            obs[i, b + 4] = 1.0
