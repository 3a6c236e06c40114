"""Walks planned on an occupancy grid, so simulated beacons go round desks and walls instead of
through them.

A planned route visits given via points in order along the cheapest path over free cells
(8-connected; cost = length x (1 + ``keep_off`` / clearance), which keeps it in the middle of
corridors), then drops every intermediate cell that a straight line can skip while staying
``margin`` metres off all occupied cells. Clearance is measured to the occupied cells as squares,
not to their centres. In the published .occ files 0 marks free floor (see
bgt_core.formats.occ).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from bgt_core.formats.occ import Occupancy


@dataclass(frozen=True)
class FloorGrid:
    centres: np.ndarray  # (C, 2) centres of all cells, row-major (y outer)
    free: np.ndarray  # (C,) bool
    cell: float
    shape: tuple[int, int]  # (ny, nx)
    _occupied: cKDTree | None

    @classmethod
    def from_occupancy(cls, occ: Occupancy, free_value: int = 0) -> FloorGrid:
        from bgt_core.formats.tables import occ_to_mask

        xs, ys, mask = occ_to_mask(occ, free_value)
        gx, gy = np.meshgrid(np.asarray(xs) + occ.cell / 2, np.asarray(ys) + occ.cell / 2)
        centres = np.column_stack([gx.ravel(), gy.ravel()])
        free = mask.ravel()
        occupied = centres[~free]
        return cls(
            centres, free, float(occ.cell), mask.shape, cKDTree(occupied) if len(occupied) else None
        )

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from each point to the nearest occupied cell square (0 inside one)."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        if self._occupied is None:
            return np.full(len(p), np.inf)
        k = min(9, self._occupied.n)
        _, idx = self._occupied.query(p, k=k)
        idx = np.asarray(idx).reshape(len(p), k)
        c = self._occupied.data[idx]  # (N, k, 2)
        d = np.maximum(np.abs(p[:, None, :] - c) - self.cell / 2, 0.0)
        return np.linalg.norm(d, axis=2).min(axis=1)

    def segment_clear(self, a: np.ndarray, b: np.ndarray, margin: float) -> bool:
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / (self.cell / 10))) + 1)
        pts = a + (b - a) * np.linspace(0.0, 1.0, n)[:, None]
        return bool((self.clearance(pts) >= margin).all())


class PlanError(ValueError):
    """No route: a via point is not on free floor, or free floor does not connect them."""


@dataclass(frozen=True)
class Lattice:
    """Planning nodes every ``step`` metres over the grid's area."""

    points: np.ndarray  # (ny * nx, 2), row-major
    shape: tuple[int, int]
    step: float

    @classmethod
    def over(cls, g: FloorGrid, step: float) -> Lattice:
        lo = g.centres.min(axis=0) - g.cell / 2
        hi = g.centres.max(axis=0) + g.cell / 2
        xs = np.arange(lo[0] + step, hi[0], step)  # multiples of step from the origin
        ys = np.arange(lo[1] + step, hi[1], step)
        gx, gy = np.meshgrid(xs, ys)
        return cls(np.column_stack([gx.ravel(), gy.ravel()]), (len(ys), len(xs)), step)

    def nearest(self, p: np.ndarray) -> int:
        return int(np.argmin(np.linalg.norm(self.points - np.asarray(p, dtype=float)[:2], axis=1)))


def _graph(lat: Lattice, clear: np.ndarray, usable: np.ndarray, keep_off: float) -> csr_matrix:
    ny, nx = lat.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    clear = np.maximum(clear, 1e-3)
    rows, cols, w = [], [], []
    yy, xx = np.mgrid[0:ny, 0:nx]
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        y2, x2 = yy + dy, xx + dx
        valid = (y2 < ny) & (x2 >= 0) & (x2 < nx)
        a, b = idx[yy[valid], xx[valid]], idx[y2[valid], x2[valid]]
        ok = usable[a] & usable[b]
        length = lat.step * np.hypot(dx, dy)
        cost = length * (1.0 + keep_off / np.minimum(clear[a[ok]], clear[b[ok]]))
        rows += [a[ok], b[ok]]
        cols += [b[ok], a[ok]]
        w += [cost, cost]
    n = ny * nx
    return coo_matrix(
        (np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()


def plan_route(
    g: FloorGrid,
    via: list[tuple[float, float]],
    *,
    closed: bool = True,
    margin: float = 0.3,
    keep_off: float = 1.0,
    step: float = 0.1,
) -> np.ndarray:
    """Waypoints (N, 2) of a route through ``via`` in order (back to the first if ``closed``),
    planned on nodes every ``step`` m that are at least ``margin`` m from occupied cells, then
    shortened by straight lines that keep that margin. Raises PlanError if there is none."""
    lat = Lattice.over(g, step)
    clear = g.clearance(lat.points)
    usable = clear >= margin
    graph = _graph(lat, clear, usable, keep_off)
    stops = [lat.nearest(np.asarray(p)) for p in via]
    for p, s in zip(via, stops, strict=True):
        if not usable[s]:
            raise PlanError(f"via point {tuple(p)} is not on free floor {margin} m from furniture")
    if closed:
        stops.append(stops[0])
    nodes: list[int] = [stops[0]]
    kept = {0}
    for a, b in zip(stops, stops[1:], strict=False):
        _, pred = dijkstra(graph, indices=a, return_predecessors=True)
        if b != a and pred[b] < 0:
            raise PlanError(
                f"no free route from {lat.points[a].round(2)} to {lat.points[b].round(2)}"
            )
        leg = [b]
        while leg[-1] != a:
            leg.append(int(pred[leg[-1]]))
        nodes += leg[::-1][1:]
        kept.add(len(nodes) - 1)  # the via points stay waypoints
    pts = lat.points[nodes]
    out = [0]
    i = 0
    while i < len(pts) - 1:
        j = i + 1
        while j not in kept and j + 1 < len(pts) and g.segment_clear(pts[i], pts[j + 1], margin):
            j += 1
        out.append(j)
        i = j
    route = pts[out]
    # drop waypoints in the middle of a straight run (via points included)
    keep = [0]
    for k in range(1, len(route) - 1):
        a, b, c = route[keep[-1]], route[k], route[k + 1]
        cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(cross) > 1e-9:
            keep.append(k)
    keep.append(len(route) - 1)
    route = route[keep]
    if closed and len(route) > 1 and np.allclose(route[0], route[-1]):
        route = route[:-1]
    return route


def path_clearance(positions: np.ndarray, g: FloorGrid) -> np.ndarray:
    """Clearance (m) of sampled path positions (N, 2 or 3) from the occupied cells."""
    return g.clearance(np.asarray(positions, dtype=float)[:, :2])
