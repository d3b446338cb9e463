"""Exact voxel raycasting (Amanatides-Woo DDA) compiled with numba.

``cast_ray`` walks the voxels a ray crosses in order and stops at the first occupied one,
at the arena boundary (floor, walls, ceiling) or at the sensor range, whichever is first.
It returns the distance, the flat voxel index (or a negative code) and the face the ray
entered through (0..5 = -x, +x, -y, +y, -z, +z). ``cast_rays`` is the batch form used by
tests and the benchmark; the world step inlines ``cast_ray``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

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
def cast_ray(occ, nx, ny, nz, cell, ox, oy, oz, dx, dy, dz, max_t):
    """First hit of the ray o + t d (|d| = 1) for 0 <= t <= max_t.

    Returns (t, code, face): code >= 0 is the flat index of the occupied voxel hit,
    BOUNDARY means the ray left the arena at distance t, MISS means nothing in range.
    The origin must be inside the arena.
    """
    ix = min(max(int(ox / cell), 0), nx - 1)
    iy = min(max(int(oy / cell), 0), ny - 1)
    iz = min(max(int(oz / cell), 0), nz - 1)
    flat = (ix * ny + iy) * nz + iz
    if occ[flat]:
        return 0.0, flat, -1
    sx, tx, ddx = _axis_init(ox, dx, ix, cell)
    sy, ty, ddy = _axis_init(oy, dy, iy, cell)
    sz, tz, ddz = _axis_init(oz, dz, iz, cell)
    while True:
        if tx <= ty and tx <= tz:
            t = tx
            if t > max_t:
                return max_t, MISS, -1
            ix += sx
            if ix < 0 or ix >= nx:
                return t, BOUNDARY, -1
            tx += ddx
            face = 0 if sx > 0 else 1
        elif ty <= tz:
            t = ty
            if t > max_t:
                return max_t, MISS, -1
            iy += sy
            if iy < 0 or iy >= ny:
                return t, BOUNDARY, -1
            ty += ddy
            face = 2 if sy > 0 else 3
        else:
            t = tz
            if t > max_t:
                return max_t, MISS, -1
            iz += sz
            if iz < 0 or iz >= nz:
                return t, BOUNDARY, -1
            tz += ddz
            face = 4 if sz > 0 else 5
        flat = (ix * ny + iy) * nz + iz
        if occ[flat]:
            return t, flat, face


@nb.njit(cache=True)
def cast_rays(occ, shape, cell, origins, dirs, max_t, out_t, out_code, out_face):
    """Cast many rays (origins/dirs are (n, 3); dirs unit length) into preallocated outputs."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for r in range(origins.shape[0]):
        t, code, face = cast_ray(occ, nx, ny, nz, cell, origins[r, 0], origins[r, 1],
                                 origins[r, 2], dirs[r, 0], dirs[r, 1], dirs[r, 2], max_t[r])
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
    best_t, best_code, best_face = max_t, MISS, -1
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
        return t_exit, BOUNDARY, -1
    return best_t, best_code, best_face
