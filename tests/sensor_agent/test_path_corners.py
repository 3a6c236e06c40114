"""PathModel's optional rounded corners: exact geometry, constant speed, no instant turns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bgt_core.motion import MotionError, PathModel
from sensor_agent.config import load_config

SQUARE = ((0.0, 0.0, 1.0), (4.0, 0.0, 1.0), (4.0, 4.0, 1.0), (0.0, 4.0, 1.0))


def sample(
    p: PathModel, dt: float = 1e-3, laps: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(0.0, laps * p.period_s, dt)
    return (
        t,
        np.array([p.position_at(float(s)) for s in t]),
        np.array([p.direction_at(float(s)) for s in t]),
    )


def test_zero_radius_is_the_sharp_polyline_and_is_not_written() -> None:
    sharp = PathModel(SQUARE, speed_mps=1.0)
    assert sharp.corner_radius == 0.0
    assert "corner_radius" not in sharp.to_dict()  # older readers see the same dict as before
    assert sharp.period_s == pytest.approx(16.0)
    assert sharp.position_at(4.0) == pytest.approx((4.0, 0.0, 1.0))  # passes through the corner
    assert sharp.direction_at(3.999) == pytest.approx((1.0, 0.0, 0.0))
    assert sharp.direction_at(4.001) == pytest.approx((0.0, 1.0, 0.0))  # turns in an instant


def test_rounded_square_geometry_is_exact() -> None:
    r, v = 1.0, 0.5
    p = PathModel(SQUARE, speed_mps=v, corner_radius=r)
    # Each corner swaps 2 r of straight for a quarter circle.
    assert p.period_s == pytest.approx((16.0 - 8 * r + 2 * math.pi * r) / v)
    # Time 0 is where the first corner's arc begins: r before waypoint 0 on the closing side.
    assert p.position_at(0.0) == pytest.approx((0.0, r, 1.0))
    assert p.direction_at(0.0) == pytest.approx((0.0, -1.0, 0.0))
    # Halfway round that arc: centre (r, r), 45 degrees from each side.
    quarter = 0.5 * math.pi * r / v
    c = r - r / math.sqrt(2)
    assert p.position_at(quarter / 2) == pytest.approx((c, c, 1.0))
    assert p.direction_at(quarter / 2) == pytest.approx((1 / math.sqrt(2), -1 / math.sqrt(2), 0.0))
    # End of the arc, then the straight bottom side at full speed.
    assert p.position_at(quarter) == pytest.approx((r, 0.0, 1.0))
    assert p.position_at(quarter + 2.0) == pytest.approx((r + 2.0 * v, 0.0, 1.0))
    # The path passes r (sqrt 2 - 1) inside each corner's waypoint.
    _, pos, _ = sample(p)
    assert np.min(np.linalg.norm(pos - SQUARE[1], axis=1)) == pytest.approx(
        r * (math.sqrt(2) - 1), abs=1e-4
    )


def test_rounded_path_has_constant_speed_and_no_instant_turn_in_3d() -> None:
    # Sloping sides: the arcs lie in tilted planes; speed is along the 3-d path.
    wps = ((0.0, 0.0, 1.2), (5.0, 0.0, 1.6), (5.0, 3.0, 1.4), (1.0, 4.0, 1.9))
    dt, v, r = 1e-3, 0.4, 0.8
    p = PathModel(wps, speed_mps=v, corner_radius=r)
    _, pos, d = sample(p, dt, laps=1.5)
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) / dt
    np.testing.assert_allclose(speed, v, rtol=1e-5)
    # The direction of travel turns at most at v / r rad/s: no step anywhere, across the lap too.
    turn = np.arccos(np.clip(np.sum(d[1:] * d[:-1], axis=1), -1.0, 1.0))
    assert turn.max() <= v / r * dt * 1.001
    assert turn.max() > 0.9 * v / r * dt  # and the arcs do turn at that rate
    # The reported direction is the derivative of the position.
    np.testing.assert_allclose(np.diff(pos, axis=0) / (v * dt), 0.5 * (d[1:] + d[:-1]), atol=1e-4)
    # The sharp path with the same waypoints turns by up to 90+ degrees between two samples.
    _, _, d0 = sample(PathModel(wps, speed_mps=v), dt)
    assert np.arccos(np.clip(np.sum(d0[1:] * d0[:-1], axis=1), -1, 1)).max() > 1.0


def test_dwell_is_at_the_start_of_each_arc() -> None:
    p = PathModel(SQUARE, speed_mps=1.0, dwell_s=2.0, corner_radius=1.0)
    assert p.period_s == pytest.approx(4 * 2.0 + 8.0 + 2 * math.pi)
    assert not p.is_moving(1.0)
    assert p.position_at(1.0) == pytest.approx((0.0, 1.0, 1.0))
    assert p.direction_at(1.0) == pytest.approx((0.0, -1.0, 0.0))
    assert p.is_moving(2.1)


def test_collinear_waypoint_needs_no_arc() -> None:
    p = PathModel(
        ((0, 0, 1), (2, 0, 1), (4, 0, 1), (4, 4, 1), (0, 4, 1)), speed_mps=1.0, corner_radius=1.0
    )
    assert p.position_at(0.0) == pytest.approx((0.0, 1.0, 1.0))  # corner 0 rounded, as before
    # Straight through (2, 0): it lies on the bottom side, 1 s after that arc ends.
    t_mid = 0.5 * math.pi + 1.0
    assert p.position_at(t_mid) == pytest.approx((2.0, 0.0, 1.0))


def test_bad_corner_radius_is_a_clear_error() -> None:
    with pytest.raises(MotionError, match="corner_radius must be a number >= 0"):
        PathModel(SQUARE, corner_radius=-1.0)
    with pytest.raises(
        MotionError, match="too large: the arcs at waypoints 0 and 1 need 5.000 m of the 4.000 m"
    ):
        PathModel(SQUARE, corner_radius=2.5)
    with pytest.raises(MotionError, match="waypoint 0 turns straight back"):
        PathModel(((0, 0, 0), (3, 0, 0)), corner_radius=0.5)
    with pytest.raises(MotionError, match="unknown key 'corner'"):
        PathModel.from_dict({"corner": 1})


def test_corner_radius_round_trips_through_dict_and_agent_yaml(tmp_path) -> None:
    p = PathModel(SQUARE, speed_mps=0.4, corner_radius=0.75)
    assert PathModel.from_dict(p.to_dict()) == p
    (tmp_path / "agent.yaml").write_text(
        "backend: simulated\nsimulated:\n  path: {waypoints: [[0, 0, 1], [4, 0, 1], [4, 4, 1], [0, 4, 1]], "
        "speed_mps: 0.4, corner_radius: 0.75}\n",
        encoding="utf-8",
    )
    cfg = load_config(tmp_path / "agent.yaml")
    assert cfg.simulated.path == p
    assert cfg.simulated.path.position_at(0.0) == pytest.approx((0.0, 0.75, 1.0))
