"""Robot kinematics and the safety set, compiled with numba.

Each step a robot turns (yaw, and pitch for quads, clipped to its limits), then moves with
its commanded body-frame velocity for ``dt``. The straight-line motion is checked at
sub-steps no longer than ``SUBSTEP_RADII`` body radii; if any sub-step would touch an
object voxel, another robot or the arena bounds, the whole translation is blocked (the
robot stays where it was, its velocity becomes 0) and the collision is counted.
Rotations never collide (the body is a sphere).
"""

from __future__ import annotations

import math

import numba as nb

from rl_scan.envs.sim.robots import FORWARD, LEFT, PITCH, UP, YAW

COLLIDE_NONE, COLLIDE_OBJECT, COLLIDE_ROBOT, COLLIDE_BOUNDS = 0, 1, 2, 3
SUBSTEP_RADII = 0.25  # longest collision-check sub-step, in body radii: no voxel is skipped


@nb.njit(cache=True)
def sphere_hits_voxels(occ, nx, ny, nz, cell, x, y, z, r):
    """True if the sphere (x, y, z, r) overlaps any occupied voxel."""
    i0, i1 = max(int((x - r) / cell), 0), min(int((x + r) / cell), nx - 1)
    j0, j1 = max(int((y - r) / cell), 0), min(int((y + r) / cell), ny - 1)
    k0, k1 = max(int((z - r) / cell), 0), min(int((z + r) / cell), nz - 1)
    r2 = r * r
    for i in range(i0, i1 + 1):
        dx = max(i * cell - x, 0.0, x - (i + 1) * cell)
        for j in range(j0, j1 + 1):
            dy = max(j * cell - y, 0.0, y - (j + 1) * cell)
            for k in range(k0, k1 + 1):
                if occ[(i * ny + j) * nz + k]:
                    dz = max(k * cell - z, 0.0, z - (k + 1) * cell)
                    if dx * dx + dy * dy + dz * dz < r2:
                        return True
    return False


@nb.njit(cache=True)
def collision_at(occ, nx, ny, nz, cell, pos, radius, me, x, y, z):
    """Why robot ``me`` at (x, y, z) would collide (COLLIDE_*), or COLLIDE_NONE."""
    r = radius[me]
    if (x < r or y < r or z < r or x > nx * cell - r or y > ny * cell - r
            or z > nz * cell - r):
        return COLLIDE_BOUNDS
    if sphere_hits_voxels(occ, nx, ny, nz, cell, x, y, z, r):
        return COLLIDE_OBJECT
    for o in range(pos.shape[0]):
        if o != me:
            dx, dy, dz = x - pos[o, 0], y - pos[o, 1], z - pos[o, 2]
            rr = r + radius[o]
            if dx * dx + dy * dy + dz * dz < rr * rr:
                return COLLIDE_ROBOT
    return COLLIDE_NONE


@nb.njit(cache=True)
def move_robots(grid, team, state, actions, dt, collided):
    """Apply actions (n, ACTION_WIDTH) = (forward, left, yaw, up, pitch) in robot order.

    Robots move one after another, so a robot sees its teammates' new positions.
    Collision codes (COLLIDE_*) go to ``collided``.
    """
    occ, cell = grid.occ, grid.cell
    nx, ny, nz = grid.shape[0], grid.shape[1], grid.shape[2]
    pos, vel, yaw, pitch = state.pos, state.vel, state.yaw, state.pitch
    radius = team.radius
    for i in range(pos.shape[0]):
        k = team.kind[i]
        a = actions[i]
        y = yaw[i] + a[YAW] * team.max_yaw_rate[k] * dt
        yaw[i] = math.atan2(math.sin(y), math.cos(y))
        pitch[i] = min(max(pitch[i] + a[PITCH] * team.max_pitch_rate[k] * dt, team.pitch_lo[k]),
                       team.pitch_hi[k])
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        fwd, left = a[FORWARD] * team.max_speed[k], a[LEFT] * team.max_speed[k]
        vx, vy, vz = c * fwd - s * left, s * fwd + c * left, a[UP] * team.max_vertical_speed[k]
        dx, dy, dz = vx * dt, vy * dt, vz * dt
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        n_sub = max(1, int(math.ceil(length / (SUBSTEP_RADII * radius[i]))))
        code = COLLIDE_NONE
        for sub in range(1, n_sub + 1):
            f = sub / n_sub
            code = collision_at(occ, nx, ny, nz, cell, pos, radius, i, pos[i, 0] + f * dx,
                                pos[i, 1] + f * dy, pos[i, 2] + f * dz)
            if code != COLLIDE_NONE:
                break
        collided[i] = code
        if code == COLLIDE_NONE:
            pos[i, 0] += dx
            pos[i, 1] += dy
            pos[i, 2] += dz
            vel[i, 0], vel[i, 1], vel[i, 2] = vx, vy, vz
        else:
            vel[i, 0], vel[i, 1], vel[i, 2] = 0.0, 0.0, 0.0
