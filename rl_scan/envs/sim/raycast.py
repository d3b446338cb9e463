"""Exact voxel raycasting (Amanatides-Woo DDA) compiled with numba.

``cast_ray`` walks the voxels a ray crosses in order and stops at the first occupied one,
at the arena boundary (floor, walls, ceiling) or at the sensor range, whichever is first.
Only the part of the ray inside the bounding box of all occupied voxels is walked.
It returns the distance, the flat voxel index (or a negative code) and the face the ray
entered through (grid.py's face ids). ``cast_rays`` is the batch form used by tests and
the benchmark; the world step inlines ``cast_ray``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from rl_scan.envs.sim.grid import NEG_X, NEG_Y, NEG_Z, NO_FACE, POS_X, POS_Y, POS_Z, VoxelGrid

MISS = -1  # nothing within range
BOUNDARY = -2  # the arena boundary (floor, wall or ceiling) within range
INF = np.inf


@nb.njit(cache=True, inline="always")
def _axis_init(o: float, d: float, i: int, cell: float):
    if d > 0.0:
        return 1, ((i + 1) * cell - o) / d, cell / d
    if d < 0.0:
        return -1, (i * cell - o) / d, -cell / d
    return 0, INF, INF


@nb.njit(cache=True)
def occupied_box(occ, nx, ny, nz):
    """Voxel bounds (i0, j0, k0, i1, j1, k1), hi exclusive, of all occupied voxels.

    An empty grid gives an empty box (i0 = i1 = 0), which no ray enters.
    """
    box = np.zeros(6, dtype=np.int64)
    box[0], box[1], box[2] = nx, ny, nz
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if occ[(i * ny + j) * nz + k]:
                    box[0], box[3] = min(box[0], i), max(box[3], i + 1)
                    box[1], box[4] = min(box[1], j), max(box[4], j + 1)
                    box[2], box[5] = min(box[2], k), max(box[5], k + 1)
    if box[3] == 0:
        box[:] = 0
    return box


# Inlined by numba, not just by LLVM's choice: the world step casts ~900 rays a step, and a
# call per ray (its arguments, the reference counts of the grid's arrays) cost ~15 % of it.
@nb.njit(cache=True, inline="always")
def cast_ray(grid, origin, direction, max_t):
    """First hit of the ray o + t d (|d| = 1; both (x, y, z) tuples) for 0 <= t <= max_t.

    Returns (t, code, face): code >= 0 is the flat index of the occupied voxel hit,
    BOUNDARY means the ray left the arena at distance t, MISS means nothing in range.
    The origin must be inside the arena. ``grid.box`` (see ``occupied_box``) bounds every
    occupied voxel: the ray is clipped to it by a slab test, so the DDA only walks
    voxels that can be occupied (exact; it just skips empty space).
    """
    occ, box, cell = grid.occ, grid.box, grid.cell
    nx, ny, nz = grid.shape[0], grid.shape[1], grid.shape[2]
    o0, o1, o2 = origin
    d0, d1, d2 = direction
    # Arena exit (the origin is inside the arena, so this is the first boundary crossing).
    t_exit = INF
    if d0 > 0.0:
        t_exit = min(t_exit, (nx * cell - o0) / d0)
    elif d0 < 0.0:
        t_exit = min(t_exit, -o0 / d0)
    if d1 > 0.0:
        t_exit = min(t_exit, (ny * cell - o1) / d1)
    elif d1 < 0.0:
        t_exit = min(t_exit, -o1 / d1)
    if d2 > 0.0:
        t_exit = min(t_exit, (nz * cell - o2) / d2)
    elif d2 < 0.0:
        t_exit = min(t_exit, -o2 / d2)
    no_hit_t, no_hit_code = (t_exit, BOUNDARY) if t_exit <= max_t else (max_t, MISS)
    # Slab test against the occupied box.
    t0, t1, enter = 0.0, min(max_t, t_exit), -1
    for a in range(3):
        o = o0 if a == 0 else (o1 if a == 1 else o2)
        d = d0 if a == 0 else (d1 if a == 1 else d2)
        lo, hi = box[a] * cell, box[a + 3] * cell
        if d == 0.0:
            if o < lo or o >= hi:
                return no_hit_t, no_hit_code, NO_FACE
        else:
            ta, tb = (lo - o) / d, (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0, enter = ta, a
            if tb < t1:
                t1 = tb
    if t0 > t1:
        return no_hit_t, no_hit_code, NO_FACE
    # Start voxel: the origin's, or the voxel where the ray enters the box.
    px, py, pz = o0 + d0 * t0, o1 + d1 * t0, o2 + d2 * t0
    ix = min(max(int(px / cell), box[0]), box[3] - 1)
    iy = min(max(int(py / cell), box[1]), box[4] - 1)
    iz = min(max(int(pz / cell), box[2]), box[5] - 1)
    face = NO_FACE
    if enter == 0:
        ix, face = (box[0], NEG_X) if d0 > 0 else (box[3] - 1, POS_X)
    elif enter == 1:
        iy, face = (box[1], NEG_Y) if d1 > 0 else (box[4] - 1, POS_Y)
    elif enter == 2:
        iz, face = (box[2], NEG_Z) if d2 > 0 else (box[5] - 1, POS_Z)
    flat = (ix * ny + iy) * nz + iz
    if occ[flat]:
        return t0, flat, face
    sx, tx, ddx = _axis_init(o0, d0, ix, cell)
    sy, ty, ddy = _axis_init(o1, d1, iy, cell)
    sz, tz, ddz = _axis_init(o2, d2, iz, cell)
    while True:
        if tx <= ty and tx <= tz:
            t = tx
            ix += sx
            if t > t1 or ix < box[0] or ix >= box[3]:
                return no_hit_t, no_hit_code, NO_FACE
            tx += ddx
            face = NEG_X if sx > 0 else POS_X
        elif ty <= tz:
            t = ty
            iy += sy
            if t > t1 or iy < box[1] or iy >= box[4]:
                return no_hit_t, no_hit_code, NO_FACE
            ty += ddy
            face = NEG_Y if sy > 0 else POS_Y
        else:
            t = tz
            iz += sz
            if t > t1 or iz < box[2] or iz >= box[5]:
                return no_hit_t, no_hit_code, NO_FACE
            tz += ddz
            face = NEG_Z if sz > 0 else POS_Z
        flat = (ix * ny + iy) * nz + iz
        if occ[flat]:
            return t, flat, face


@nb.njit(cache=True)
def cast_rays(occ, shape, cell, origins, dirs, max_t, out_t, out_code, out_face):
    """Cast many rays (origins/dirs are (n, 3); dirs unit length) into preallocated outputs."""
    box = occupied_box(occ, shape[0], shape[1], shape[2])
    grid = VoxelGrid(occ, shape, cell, box, shape * cell)
    for r in range(origins.shape[0]):
        t, code, face = cast_ray(grid, (origins[r, 0], origins[r, 1], origins[r, 2]),
                                 (dirs[r, 0], dirs[r, 1], dirs[r, 2]), max_t[r])
        out_t[r] = t
        out_code[r] = code
        out_face[r] = face


def cast_rays_brute_force(occ_grid: np.ndarray, cell: float, origin: np.ndarray,
                          direction: np.ndarray, max_t: float) -> tuple[float, int, int]:
    """Reference: slab-test the ray against every occupied voxel and the arena box.

    Slow and obviously correct; the tests compare ``cast_ray`` against it.
    """
    shape = np.array(occ_grid.shape)
    idx = np.argwhere(occ_grid)
    lo, hi = idx * cell, (idx + 1) * cell
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t1, t2 = (lo - origin) * inv, (hi - origin) * inv
    tnear_axis = np.minimum(t1, t2)
    tfar = np.maximum(t1, t2).min(axis=1)
    tnear = tnear_axis.max(axis=1)
    hit = (tnear <= tfar) & (tnear >= 0) & (tnear <= max_t)
    best_t, best_code, best_face = max_t, MISS, NO_FACE
    if hit.any():
        k = np.flatnonzero(hit)[np.argmin(tnear[hit])]
        axis = int(np.argmax(tnear_axis[k]))
        best_t = float(tnear[k])
        best_code = int(np.ravel_multi_index(idx[k], occ_grid.shape))
        best_face = 2 * axis + (0 if direction[axis] > 0 else 1)
    # Arena exit: the smallest positive crossing of the grid box.
    with np.errstate(divide="ignore", invalid="ignore"):
        exits = np.where(direction > 0, (shape * cell - origin) / direction,
                         np.where(direction < 0, -origin / direction, np.inf))
    t_exit = float(exits.min())
    if t_exit <= max_t and t_exit < best_t:
        return t_exit, BOUNDARY, NO_FACE
    return best_t, best_code, best_face
