"""Occupancy grids from a floor plan: a cell is occupied (1) when enough of the plan under it is
not bare floor (furniture, walls), or when it lies off the plan; free floor is 0, as in the
published `.occ` files.

The plan's pixels map to the world by the site's `.par` (``MapParams.world_to_pixel``). A pixel
is floor when it is near white (every channel at least ``floor_level``); a cell is occupied when
the share of non-floor pixels in it reaches ``threshold``. Walls are thin lines: a cell with a
wall through it has a small share, so any pixel darker than ``wall_level`` (the plan's black
lines) occupies its cell on its own.
"""

from __future__ import annotations

import numpy as np

from bgt_core.formats.devices import MapParams
from bgt_core.formats.occ import Occupancy, grid_corners

FLOOR_LEVEL = 200  # a pixel with every channel at least this bright is floor
THRESHOLD = 0.3  # share of non-floor pixels that occupies a cell
WALL_LEVEL = 60  # a pixel with every channel darker than this is a wall
WALL_PIXELS = 3  # this many wall pixels occupy a cell


def occupancy_from_plan(
    image: np.ndarray,
    params: MapParams,
    cell: float,
    *,
    floor_level: int = FLOOR_LEVEL,
    threshold: float = THRESHOLD,
    wall_level: int = WALL_LEVEL,
    wall_pixels: int = WALL_PIXELS,
) -> Occupancy:
    """The occupancy grid of the site's area (``params.limits``) at ``cell`` metres from the plan
    ``image`` (H x W x 3 or H x W, uint8). Cells are laid out as the published grids are (lower-
    left corners from the area's origin, `grid_corners`)."""
    if image.ndim == 3:
        low = image[..., :3].min(axis=2)
        high = image[..., :3].max(axis=2)
    else:
        low = high = image
    not_floor = low < floor_level
    wall = high < wall_level
    h, w = not_floor.shape
    x0, y0, x1, y1 = params.limits
    xs, ys = grid_corners(((x0, y0), (x1, y1)), cell)
    # Sample each cell on a grid of points about a pixel apart (the plan's resolution).
    n = max(2, int(np.ceil(cell / params.parity)))
    offsets = (np.arange(n) + 0.5) / n * cell
    cells: dict[tuple[float, float], int] = {}
    for gy in ys:
        for gx in xs:
            px, py = params.world_to_pixel(
                np.repeat(gx + offsets, n).astype(float), np.tile(gy + offsets, n).astype(float)
            )
            u, v = np.floor(px).astype(int), np.floor(py).astype(int)
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            if inside.mean() < 0.5:
                cells[(gx, gy)] = 1  # off the plan: nothing known is free
                continue
            u, v = u[inside], v[inside]
            occupied = not_floor[v, u].mean() >= threshold or int(wall[v, u].sum()) >= wall_pixels
            cells[(gx, gy)] = int(occupied)
    return Occupancy(((x0, y0), (x1, y1)), cell, cells)


def agreement(ours: Occupancy, theirs: Occupancy) -> tuple[float, int]:
    """Share of the cells both grids hold that have the same value, and how many they share."""
    common = [c for c in ours.cells if c in theirs.cells]
    if not common:
        return float("nan"), 0
    same = sum(ours.cells[c] == theirs.cells[c] for c in common)
    return same / len(common), len(common)
