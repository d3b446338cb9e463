"""The voxel grid of the arena and the scan cells (exposed, non-downward voxel faces).

Voxel (i, j, k) spans [i, i+1) x [j, j+1) x [k, k+1) cells, i.e. cell_size metres per
axis, with the floor at z = 0. Flat voxel index = (i * ny + j) * nz + k (C order).
Faces are numbered 0..5 = -x, +x, -y, +y, -z, +z. A cell is an object-voxel face whose
neighbour is free (or outside the grid), except -z faces (the paper tiles five faces of
an object, never its underside): a 6x6x6 cube has 4*36 + 36 = 180 cells.
``VoxelGrid`` and ``Objects`` are these facts as the numba kernels read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

NEG_X, POS_X, NEG_Y, POS_Y, NEG_Z, POS_Z = range(6)  # face ids: 2 * axis + (normal > 0)
N_FACES = 6
DOWN_FACE = NEG_Z
NO_FACE = -1  # a ray that hit nothing, or started inside an object voxel
NO_CELL = -1  # an object-voxel face that is not a cell (hidden, or downward)
FREE = -1  # the slot (and object id) of a free voxel
FACE_NORMALS = np.array(
    [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)


@dataclass(frozen=True)
class GridShape:
    """Voxel counts of the arena grid and the voxel edge length in metres."""

    nx: int
    ny: int
    nz: int
    cell_size: float

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.nx, self.ny, self.nz)

    @property
    def extent(self) -> np.ndarray:
        """Arena size in metres (x, y, z)."""
        return np.array(self.shape, dtype=np.float64) * self.cell_size

    def voxel_centres(self, idx: np.ndarray) -> np.ndarray:
        """Centres (metres) of voxels given as an (n, 3) integer index array."""
        return (np.asarray(idx, dtype=np.float64) + 0.5) * self.cell_size


@dataclass(frozen=True)
class Cells:
    """The scan cells of an occupancy grid, in a fixed order (by voxel, then face)."""

    voxel: np.ndarray  # (n,) flat voxel index
    face: np.ndarray  # (n,) face index 0..5 (never 4)
    centre: np.ndarray  # (n, 3) face centre in metres
    obj: np.ndarray  # (n,) object id of the voxel

    def __len__(self) -> int:
        return len(self.voxel)


def exposed_cells(object_id: np.ndarray, cell_size: float) -> Cells:
    """Enumerate the cells of an object-id grid (-1 = free) as described in the module doc."""
    occ = object_id >= 0
    padded = np.pad(occ, 1, constant_values=False)
    nx, ny, nz = occ.shape
    voxels, faces = [], []
    centre_idx = np.argwhere(occ)
    flat = np.ravel_multi_index(centre_idx.T, occ.shape) if len(centre_idx) else np.zeros(0, int)
    for face, normal in enumerate(FACE_NORMALS):
        if face == DOWN_FACE:
            continue
        i, j, k = (centre_idx + 1 + normal).T
        free = ~padded[i, j, k]
        voxels.append(flat[free])
        faces.append(np.full(int(free.sum()), face, dtype=np.int64))
    voxel = np.concatenate(voxels) if voxels else np.zeros(0, np.int64)
    face = np.concatenate(faces) if faces else np.zeros(0, np.int64)
    order = np.lexsort((face, voxel))
    voxel, face = voxel[order], face[order]
    ijk = np.stack(np.unravel_index(voxel, occ.shape), axis=1).astype(np.float64)
    centre = (ijk + 0.5 + 0.5 * FACE_NORMALS[face]) * cell_size
    obj = object_id.reshape(-1)[voxel]
    return Cells(voxel=voxel.astype(np.int64), face=face.astype(np.int64),
                 centre=centre, obj=obj.astype(np.int64))


class VoxelGrid(NamedTuple):
    """The arena's occupancy for raycasting and collisions."""

    occ: np.ndarray
    """(nx * ny * nz,) uint8, 1 = object voxel, flat index as in the module doc."""
    shape: np.ndarray
    """(3,) int64 voxel counts (nx, ny, nz)."""
    cell: float
    """Voxel edge, metres."""
    box: np.ndarray
    """(6,) int64 bounds (i0, j0, k0, i1, j1, k1) of all object voxels, see occupied_box."""
    extent: np.ndarray
    """(3,) arena size in metres; observations are positions divided by it."""


class Objects(NamedTuple):
    """What a ray hit counts for, and what the object channel reports about each object.

    Occupied voxels are numbered by "slot" so that per-face tables stay small.
    """

    voxel_slot: np.ndarray
    """(nx * ny * nz,) int64 slot of each voxel, FREE where there is no object."""
    slot_object: np.ndarray
    """(slots,) int64 object id of each occupied voxel."""
    slot_cells: np.ndarray
    """(slots, N_FACES) int64 cell id of each face of each occupied voxel, or NO_CELL."""
    n_cells: np.ndarray
    """(objects,) int64 cells per object."""
    centre: np.ndarray
    """(objects, 3) centre of the object's voxels, metres."""
    top: np.ndarray
    """(objects,) height of the object's top, metres."""
