"""Routes planned on an occupancy grid: through the door, never through the wall."""

from __future__ import annotations

import numpy as np
import pytest

from annotator.core.floor_paths import FloorGrid, PlanError, plan_route
from annotator.io.radio_data import site_occupancy
from bgt_core.formats.occ import Occupancy


def walled_room() -> Occupancy:
    """10 x 6 m in 0.5 m cells: outer walls, and an inner wall at x 5.0..5.5 with a 1.5 m door
    at y 4.0..5.5 (value 1 = occupied, as the published files)."""
    cells = {}
    for j in range(12):
        for i in range(20):
            x, y = i * 0.5, j * 0.5
            wall = i in (0, 19) or j in (0, 11) or (i == 10 and not 8 <= j <= 10)
            cells[(x, y)] = int(wall)
    return Occupancy(((0.0, 0.0), (9.99, 5.99)), 0.5, cells)


def densify(route: np.ndarray, closed: bool) -> np.ndarray:
    pts = np.vstack([route, route[:1]]) if closed else route
    return np.vstack(
        [a + (b - a) * np.linspace(0, 1, 50)[:, None] for a, b in zip(pts, pts[1:], strict=False)]
    )


def test_route_goes_through_the_door_and_keeps_its_margin() -> None:
    g = FloorGrid.from_occupancy(walled_room())
    route = plan_route(g, [(2.0, 1.5), (8.0, 1.5)], closed=False, margin=0.3)
    np.testing.assert_allclose(route[0], [2.0, 1.5])
    np.testing.assert_allclose(route[-1], [8.0, 1.5])
    crossing = densify(route, closed=False)
    at_wall = np.abs(crossing[:, 0] - 5.25) < 0.25
    assert at_wall.any()
    assert (crossing[at_wall, 1] > 4.0).all()  # through the door (y 4.0 .. 5.5), nowhere else
    assert (crossing[at_wall, 1] < 5.5).all()
    assert g.clearance(crossing).min() >= 0.3 - 1e-9
    # the straight line would cross the wall
    assert not g.segment_clear(np.array([2.0, 1.5]), np.array([8.0, 1.5]), 1e-6)


def test_clearance_is_to_the_occupied_squares() -> None:
    g = FloorGrid.from_occupancy(walled_room())
    # the inner wall's cells span x 5.0 .. 5.5; the outer wall's first column x 0 .. 0.5
    np.testing.assert_allclose(
        g.clearance(np.array([[4.0, 2.0], [5.25, 2.0], [1.0, 3.0]])), [1.0, 0.0, 0.5]
    )


def test_no_route_is_a_plan_error() -> None:
    g = FloorGrid.from_occupancy(walled_room())
    with pytest.raises(PlanError, match="not on free floor"):
        plan_route(g, [(5.25, 1.0), (8.0, 1.5)], closed=False)
    # a door 1.5 m wide does not pass a walker who needs 0.8 m on each side
    with pytest.raises(PlanError, match="no free route"):
        plan_route(g, [(2.0, 1.5), (8.0, 1.5)], closed=False, margin=0.8)


def test_site_occupancy_is_the_published_grid() -> None:
    occ = site_occupancy("tetam")
    assert occ.cell == 0.5
    assert len(occ.cells) == 37 * 43
    assert 0.2 < np.mean(list(occ.cells.values())) < 0.6  # desks and walls are a good share
