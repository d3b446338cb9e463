"""RGB frames of a world: a top view and a side view, plus PNG/GIF writers.

Object columns are coloured from green (no cell scanned) to blue (all scanned); wheeled
robots are red discs, quadcopters orange discs with a heading tick, both in both views.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from rl_scan.envs.sim.robots import QUAD

PX = 12  # pixels per voxel
UNSCANNED, SCANNED = np.array([60, 170, 75]), np.array([65, 105, 225])
FLOOR, WHEELED_RGB, QUAD_RGB = (235, 235, 235), (220, 40, 40), (245, 150, 20)
HEADER = 22


def _fraction_image(keys: np.ndarray, scanned: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    total = np.bincount(keys, minlength=shape[0] * shape[1])
    done = np.bincount(keys, weights=scanned, minlength=shape[0] * shape[1])
    img = np.empty((shape[0] * shape[1], 3))
    img[:] = FLOOR
    has = total > 0
    frac = (done[has] / total[has])[:, None]
    img[has] = UNSCANNED * (1 - frac) + SCANNED * frac
    return img.reshape(shape[0], shape[1], 3)


def render_frame(world, step: int = 0) -> np.ndarray:
    """Top view (x right, y up) above a side view (x right, z up) as an RGB uint8 array."""
    g = world.grid
    ijk = np.stack(np.unravel_index(world.cells.voxel, g.shape), axis=1)
    state = world.cell_state.astype(np.float64)
    top = _fraction_image(ijk[:, 0] * g.ny + ijk[:, 1], state, (g.nx, g.ny))
    side = _fraction_image(ijk[:, 0] * g.nz + ijk[:, 2], state, (g.nx, g.nz))
    top_img = np.flipud(np.transpose(top, (1, 0, 2)))  # rows = y (up), cols = x
    side_img = np.flipud(np.transpose(side, (1, 0, 2)))
    body = np.concatenate([top_img, np.full((1, g.nx, 3), 120.0), side_img])
    body = np.repeat(np.repeat(body, PX, axis=0), PX, axis=1).astype(np.uint8)
    canvas = Image.new("RGB", (body.shape[1], body.shape[0] + HEADER), (255, 255, 255))
    canvas.paste(Image.fromarray(body), (0, HEADER))
    draw = ImageDraw.Draw(canvas)
    cov = world.n_scanned / max(world.n_cells, 1)
    draw.text((4, 4), f"step {step}  coverage {100 * cov:.1f}%  "
                      f"({world.n_scanned}/{world.n_cells} cells)", fill=(0, 0, 0))
    scale = PX / g.cell_size
    side_top = HEADER + (g.ny + 1) * PX
    for i in range(world.n_robots):
        x, y, z = world.pos[i]
        rgb = QUAD_RGB if world.kind[i] == QUAD else WHEELED_RGB
        r = max(3, world.radius[i] * scale)
        for cx, cy in ((x * scale, HEADER + (g.ny * g.cell_size - y) * scale),
                       (x * scale, side_top + (g.nz * g.cell_size - z) * scale)):
            draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=rgb, outline=(0, 0, 0))
        hx, hy = np.cos(world.yaw[i]) * 2 * r, -np.sin(world.yaw[i]) * 2 * r
        cx, cy = x * scale, HEADER + (g.ny * g.cell_size - y) * scale
        draw.line((cx, cy, cx + hx, cy + hy), fill=(0, 0, 0), width=2)
    return np.asarray(canvas)


def save_frames(frames: list[np.ndarray], path: str | Path, fps: int = 10) -> Path:
    """Write one PNG (a single frame or a .png path) or an animated GIF."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    if path.suffix.lower() == ".png":
        images[-1].save(path)
    elif path.suffix.lower() == ".gif":
        images[0].save(path, save_all=True, append_images=images[1:],
                       duration=int(1000 / fps), loop=0, optimize=True)
    else:
        raise ValueError(f"output={str(path)!r} is invalid: allowed a .png or .gif path")
    return path
