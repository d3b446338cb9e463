"""Voxelization and scan cells, checked against hand counts."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from rl_scan.config import ConfigError
from rl_scan.envs.sim.grid import exposed_cells
from rl_scan.envs.sim.objects import ObjectSpec, voxelize

SHAPE, CELL = (40, 40, 16), 0.5


def _grid(*specs: ObjectSpec) -> np.ndarray:
    grid = np.full(SHAPE, -1, dtype=np.int64)
    for i, spec in enumerate(specs):
        grid.reshape(-1)[voxelize(spec, SHAPE, CELL)] = i
    return grid


def test_cube_6x6x6_has_216_voxels_and_180_cells():
    grid = _grid(ObjectSpec(shape="box", size=(3.0, 3.0, 3.0), position=(10.0, 10.0)))
    assert (grid >= 0).sum() == 216
    cells = exposed_cells(grid, CELL)
    assert len(cells) == 180  # 4 sides * 36 + top 36; the bottom is never a cell
    assert np.bincount(cells.face, minlength=6).tolist() == [36, 36, 36, 36, 0, 36]


def test_box_2x3x4_cells_by_hand():
    # 2 x 3 x 4 cells: x faces 2 * (3*4) = 24, y faces 2 * (2*4) = 16, top 2*3 = 6 -> 46.
    # Extents 1.0 x 1.5 x 2.0 m; the y centre 10.25 puts both y faces on the 0.5 m grid.
    grid = _grid(ObjectSpec(shape="box", size=(1.0, 1.5, 2.0), position=(10.0, 10.25)))
    assert (grid >= 0).sum() == 24
    cells = exposed_cells(grid, CELL)
    assert len(cells) == 46
    assert np.bincount(cells.face, minlength=6).tolist() == [12, 12, 8, 8, 0, 6]


def test_lshape_cells_by_hand():
    # 4 x 4 footprint, height 2 cells, arms keep half of x and half of y: the L covers
    # 16 - 4 = 12 columns. Side faces: the outline of the L is 4+4+2+2+2+2 = 16 edges long,
    # times 2 cells of height = 32; top = 12 -> 44 cells; voxels = 12 * 2 = 24.
    spec = ObjectSpec(shape="lshape", size=(2.0, 2.0, 1.0), position=(10.0, 10.0),
                      proportions=(0.5, 0.5))
    grid = _grid(spec)
    assert (grid >= 0).sum() == 24
    assert len(exposed_cells(grid, CELL)) == 44


def test_touching_boxes_hide_their_shared_faces():
    a = ObjectSpec(shape="box", size=(1.0, 1.0, 1.0), position=(10.0, 10.0))
    b = ObjectSpec(shape="box", size=(1.0, 1.0, 1.0), position=(11.0, 10.0))
    alone = len(exposed_cells(_grid(a), CELL))
    assert alone == 4 * 4 + 4
    both = exposed_cells(_grid(a, b), CELL)
    assert len(both) == 2 * alone - 2 * 4  # the 2x2 faces where they touch, on both sides


def test_face_centres_lie_on_the_face():
    grid = _grid(ObjectSpec(shape="box", size=(3.0, 3.0, 3.0), position=(10.0, 10.0)))
    cells = exposed_cells(grid, CELL)
    top = cells.centre[cells.face == 5]
    assert np.allclose(top[:, 2], 3.0)
    minus_x = cells.centre[cells.face == 0]
    assert np.allclose(minus_x[:, 0], 8.5)
    assert top[:, :2].min() == pytest.approx(8.75) and top[:, :2].max() == pytest.approx(11.25)


@pytest.mark.parametrize("shape", ["cylinder", "sphere"])
def test_round_shapes_are_symmetric_under_quarter_turns(shape):
    grid = _grid(ObjectSpec(shape=shape, size=(3.0, 3.0, 3.0), position=(10.0, 10.0))) >= 0
    block = grid[14:26, 14:26, :]
    assert block.sum() > 0 and grid.sum() == block.sum()
    assert np.array_equal(block, np.rot90(block, 1, axes=(0, 1)))
    assert np.array_equal(block, block[::-1, :, :])


def test_hull_shapes_by_hand():
    """The hull of the unit cube's corners is the box; a corner tetrahedron is a sixth."""
    corners = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    kw = dict(size=(3.0, 3.0, 3.0), position=(10.0, 10.0))
    box = voxelize(ObjectSpec(shape="box", **kw), SHAPE, CELL)
    hull = voxelize(ObjectSpec(shape="hull", points=corners, **kw), SHAPE, CELL)
    assert np.array_equal(np.sort(hull), np.sort(box)) and len(box) == 6 * 6 * 6
    tetra = voxelize(ObjectSpec(shape="hull", points=[(0, 0, 0), (1, 0, 0), (0, 1, 0),
                                                      (0, 0, 1)], **kw), SHAPE, CELL)
    assert set(tetra) <= set(box)  # inside the same 3 m cube
    assert 216 / 6 * 0.5 < len(tetra) < 216 / 6 * 2  # volume 1/6 of the cube's, voxelized


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".glb"])
def test_mesh_files_voxelize_like_the_primitive(tmp_path, suffix):
    path = tmp_path / f"cube{suffix}"
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(path)
    from_file = voxelize(ObjectSpec(shape="mesh", path=str(path), size=(3.0, 3.0, 3.0),
                                    position=(10.0, 10.0)), SHAPE, CELL)
    primitive = voxelize(ObjectSpec(shape="box", size=(3.0, 3.0, 3.0), position=(10.0, 10.0)),
                         SHAPE, CELL)
    assert np.array_equal(np.sort(from_file), np.sort(primitive))


def test_missing_and_broken_mesh_files_name_the_path(tmp_path):
    missing = tmp_path / "nope.stl"
    with pytest.raises(ConfigError, match="nope.stl.*does not exist"):
        voxelize(ObjectSpec(shape="mesh", path=str(missing)), SHAPE, CELL)
    broken = tmp_path / "broken.obj"
    broken.write_bytes(b"\x00\x01garbage that is not a mesh\xff")
    with pytest.raises(ConfigError, match="broken.obj"):
        voxelize(ObjectSpec(shape="mesh", path=str(broken)), SHAPE, CELL)
