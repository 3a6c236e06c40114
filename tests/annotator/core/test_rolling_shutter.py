"""The rolling shutter's one module (issue 32): row v of a frame stamped t is seen at
t + readout * v / height, and a point moved by moved_points looks from the pose at t exactly as
the original looks from the pose at its row's time."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.rolling_shutter import moved_points, row_delay


def test_row_delay() -> None:
    assert row_delay(540, 1080, 0.02) == pytest.approx(0.01)
    assert np.allclose(row_delay(np.array([0, 1079]), 1080, 0.0), 0.0)  # a global shutter
    # per camera arrays broadcast
    assert np.allclose(row_delay([100, 100], np.array([200, 400]), 0.03), [0.015, 0.0075])


def test_moved_points_match_the_pose_at_the_rows_time() -> None:
    rng = np.random.default_rng(0)
    R_wb = Rotation.from_rotvec([0.1, -0.2, 0.3])
    p_wb = np.array([1.0, 2.0, 1.5])
    omega = np.array([0.2, -0.5, 1.0])  # rad/s, world frame
    vel = np.array([0.4, -0.1, 0.05])
    world = rng.uniform(-3, 3, (20, 3)) + p_wb
    pixels = np.column_stack([rng.uniform(0, 960, 20), rng.uniform(0, 540, 20)])
    readout = 0.03
    moved = moved_points(world, pixels, 540, readout, R_wb.as_matrix(), p_wb, omega, vel)
    tau = readout * pixels[:, 1] / 540
    for k in range(20):
        R_tau = Rotation.from_rotvec(omega * tau[k]) * R_wb
        p_tau = p_wb + vel * tau[k]
        seen_late = R_tau.inv().apply(world[k] - p_tau)  # the bundle frame at the row's time
        seen_now = R_wb.inv().apply(moved[k] - p_wb)  # the bundle frame at the stamp
        assert np.allclose(seen_late, seen_now, atol=1e-12)
