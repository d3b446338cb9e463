"""Scannable objects: trimesh meshes (primitives or user files) voxelized into the grid.

Every shape is built inside a unit bounding box, scaled to ``size`` (metres, x y z),
rotated by ``yaw`` about z and placed with its footprint centre at ``position``
(x, y) and its bottom at ``z`` (0 = on the floor). A voxel belongs to the object iff its
centre is inside the mesh, decided by the generalized winding number (exact for
watertight meshes, graceful for slightly open user meshes, and needs no ray library).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from rl_scan.config import ConfigError, check_range, fail

SHAPES = ("box", "cylinder", "sphere", "lshape", "hull", "mesh")
MESH_SUFFIXES = (".obj", ".stl", ".glb", ".gltf", ".ply")


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a scenario."""

    shape: str = "box"
    """One of box, cylinder, sphere, lshape, hull, mesh."""
    size: tuple[float, float, float] = (3.0, 3.0, 3.0)
    """Bounding-box extents in metres (x, y, z) before yaw."""
    position: tuple[float, float] = (10.0, 10.0)
    """Footprint centre (x, y) in metres."""
    z: float = 0.0
    """Height of the object's bottom above the floor, metres."""
    yaw: float = 0.0
    """Rotation about the vertical axis, degrees."""
    points: tuple[tuple[float, float, float], ...] = ()
    """hull only: points in the unit cube [0, 1]^3 whose convex hull is the shape."""
    path: str = ""
    """mesh only: an OBJ/STL/GLB/PLY file, scaled to ``size``."""
    proportions: tuple[float, float] = (0.5, 0.5)
    """lshape only: fraction of x and y kept by the short arms."""

    def validate(self, prefix: str = "") -> None:
        if self.shape not in SHAPES:
            fail(prefix + "shape", self.shape, f"one of {list(SHAPES)}")
        for axis, s in zip("xyz", self.size):
            check_range(f"{prefix}size.{axis}", s, 0.0, None, lo_open=True)
        check_range(prefix + "z", self.z, 0.0)
        for i, p in enumerate(self.proportions):
            check_range(f"{prefix}proportions[{i}]", p, 0.05, 0.95)
        if self.shape == "hull" and len(self.points) < 4:
            fail(prefix + "points", self.points, "at least 4 points for a hull")
        if self.shape == "mesh":
            if not self.path:
                fail(prefix + "path", self.path, "a mesh file path for shape 'mesh'")
            if Path(self.path).suffix.lower() not in MESH_SUFFIXES:
                fail(prefix + "path", self.path, f"a file ending in {list(MESH_SUFFIXES)}")


def load_mesh_file(path: str | Path) -> trimesh.Trimesh:
    """Load a user mesh; missing, unreadable or empty files raise ConfigError naming the path."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"mesh file {str(path)!r} does not exist")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for broken files
        raise ConfigError(f"mesh file {str(path)!r} could not be read: {e}") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(f"mesh file {str(path)!r} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)) or np.any(mesh.extents <= 0):
        raise ConfigError(f"mesh file {str(path)!r} has degenerate or non-finite geometry")
    return mesh


def _unit_box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    lo_, hi_ = np.array(lo), np.array(hi)
    m = trimesh.creation.box(extents=hi_ - lo_)
    m.apply_translation((lo_ + hi_) / 2)
    return m


def unit_parts(spec: ObjectSpec) -> list[trimesh.Trimesh]:
    """Meshes of the shape inside the unit box [0, 1]^3 (an L-shape is two boxes)."""
    if spec.shape == "box":
        return [_unit_box((0, 0, 0), (1, 1, 1))]
    if spec.shape == "cylinder":
        m = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=48)
        m.apply_translation((0.5, 0.5, 0.5))
        return [m]
    if spec.shape == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
        m.apply_translation((0.5, 0.5, 0.5))
        return [m]
    if spec.shape == "lshape":
        px, py = spec.proportions
        return [_unit_box((0, 0, 0), (1, py, 1)), _unit_box((0, 0, 0), (px, 1, 1))]
    if spec.shape == "hull":
        m = trimesh.convex.convex_hull(np.asarray(spec.points, dtype=np.float64))
        m.apply_translation(-m.bounds[0])
        m.apply_scale(1.0 / m.extents)
        return [m]
    mesh = load_mesh_file(spec.path).copy()
    mesh.apply_translation(-mesh.bounds[0])
    mesh.apply_scale(1.0 / mesh.extents)
    return [mesh]


def placed_parts(spec: ObjectSpec) -> list[trimesh.Trimesh]:
    """The object's meshes in world coordinates (metres)."""
    size = np.asarray(spec.size, dtype=np.float64)
    c, s = np.cos(np.radians(spec.yaw)), np.sin(np.radians(spec.yaw))
    transform = np.array([[c, -s, 0, spec.position[0]], [s, c, 0, spec.position[1]],
                          [0, 0, 1, spec.z], [0, 0, 0, 1]], dtype=np.float64)
    out = []
    for part in unit_parts(spec):
        m = part.copy()
        m.apply_translation((-0.5, -0.5, 0.0))  # footprint centre at the origin, bottom at 0
        m.vertices = m.vertices * size
        m.apply_transform(transform)
        out.append(m)
    return out


def winding_number(mesh: trimesh.Trimesh, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Generalized winding number of ``points`` w.r.t. ``mesh`` (1 inside, 0 outside)."""
    tri = mesh.triangles  # (F, 3, 3)
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk, None, None, :]
        v = tri[None] - p  # (n, F, 3, 3)
        a, b, c = v[:, :, 0], v[:, :, 1], v[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("nfi,nfi->nf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("nfi,nfi->nf", a, b) * lc
               + np.einsum("nfi,nfi->nf", a, c) * lb + np.einsum("nfi,nfi->nf", b, c) * la)
        out[start:start + chunk] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


def voxelize(spec: ObjectSpec, shape: tuple[int, int, int], cell_size: float) -> np.ndarray:
    """Flat indices of the grid voxels whose centres lie inside the object."""
    parts = placed_parts(spec)
    lo = np.min([p.bounds[0] for p in parts], axis=0)
    hi = np.max([p.bounds[1] for p in parts], axis=0)
    i0 = np.maximum(np.floor(lo / cell_size - 0.5).astype(int), 0)
    i1 = np.minimum(np.ceil(hi / cell_size + 0.5).astype(int), shape)
    if np.any(i1 <= i0):
        return np.zeros(0, dtype=np.int64)
    axes = [np.arange(a, b) for a, b in zip(i0, i1)]
    idx = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = (idx + 0.5) * cell_size
    inside = np.zeros(len(idx), dtype=bool)
    for part in parts:
        in_box = np.all((centres >= part.bounds[0]) & (centres <= part.bounds[1]), axis=1)
        if in_box.any():
            sel = np.flatnonzero(in_box & ~inside)
            inside[sel] |= np.abs(winding_number(part, centres[sel])) > 0.5
    return np.ravel_multi_index(idx[inside].T, shape).astype(np.int64)
