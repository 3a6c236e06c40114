"""Trajectory metrics with known numbers, and `annotator evaluate` end to end on files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from annotator.cli import app
from annotator.core.evaluate import (
    compare_to_path,
    compare_to_truth,
    error_stats,
)
from annotator.core.trajectory import Trajectory
from annotator.io.trajectory import write_trajectory


def make_truth(
    n: int = 101, dt: float = 0.1, t0: float = 1000.0
) -> tuple[np.ndarray, np.ndarray, Rotation]:
    """Straight line along x at 1 m/s, 1.5 m high, turning about z at 10 deg/s."""
    t = t0 + np.arange(n) * dt
    pos = np.column_stack([t - t0, np.zeros(n), np.full(n, 1.5)])
    return t, pos, Rotation.from_euler("z", 10.0 * (t - t0)[:, None], degrees=True)


def test_error_stats_known_numbers() -> None:
    s = error_stats(np.array([1.0, 2.0, 3.0, 4.0, 100.0, np.nan]))
    assert s.n == 5
    assert (s.median, s.mean, s.p75, s.max) == (3.0, 22.0, 4.0, 100.0)
    assert s.p95 == pytest.approx(80.8)  # linear interpolation between 4 and 100
    assert error_stats(np.array([np.nan])).n == 0


def test_interpolation_between_samples() -> None:
    t, pos, rot = make_truth()
    traj = Trajectory(t, pos, rot.as_matrix())
    p, r, ok = traj.interpolate(np.array([1000.05, 1000.0, 1010.0, 1010.01, 999.9]))
    assert ok.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(p[0], [0.05, 0.0, 1.5], atol=1e-12)
    yaw = Rotation.from_matrix(r[:3]).as_euler("zyx", degrees=True)[:, 0]
    np.testing.assert_allclose(yaw, [0.5, 0.0, 100.0], atol=1e-9)  # slerp halfway: 0.5 deg
    assert np.isnan(p[3]).all()


def test_constant_offset_and_tilt_are_measured_exactly() -> None:
    t, pos, rot = make_truth()
    est_t = t[:-1] + 0.05  # between the reference samples: interpolation is exercised
    est_pos = np.column_stack([est_t - 1000.0, np.zeros(len(est_t)), np.full(len(est_t), 1.5)])
    est_pos = est_pos + [0.03, 0.04, 0.0]  # 5 cm off
    tilt = Rotation.from_euler("x", 2.0, degrees=True)
    est_rot = (
        Rotation.from_euler("z", 10.0 * (est_t - 1000.0)[:, None], degrees=True) * tilt
    ).as_matrix()
    cmp = compare_to_truth(est_t, est_pos, est_rot, t, pos, rot.as_matrix())
    np.testing.assert_allclose(cmp.position_error, 0.05, atol=1e-9)
    np.testing.assert_allclose(cmp.rotation_error_deg, 2.0, atol=1e-9)
    rep = cmp.report()
    assert rep["compared"] == 100
    assert rep["position_error_m"]["p95"] == pytest.approx(0.05)


def test_gaps_and_out_of_range_rows_are_counted_not_compared() -> None:
    t, pos, rot = make_truth()
    est_t = np.array([999.0, 1000.0, 1000.5, 1000.95])
    est_pos = np.array([[0, 0, 1.5], [0.1, 0, 1.5], [np.nan] * 3, [0.95, 0, 1.5]])
    est_rot = rot.as_matrix()[[0, 0, 5, 10]]
    est_rot[2] = np.nan
    ref_pos = pos.copy()
    ref_pos[9] = np.nan  # a gap in the reference: t = 1000.95 lies between rows 9 and 10
    cmp = compare_to_truth(est_t, est_pos, est_rot, t, ref_pos, rot.as_matrix())
    assert cmp.missing == 1
    assert cmp.outside == 2  # before the reference starts, and beside its gap
    assert np.isnan(cmp.position_error[[0, 2, 3]]).all()
    assert cmp.position_error[1] == pytest.approx(0.1)


def l_path_trajectory() -> tuple[np.ndarray, np.ndarray]:
    """Planned L: (0,0) -> (4,0) -> (4,3). Walked 10 cm left of leg 1, turning at x = 3.8, then
    15 cm inside leg 2, stopping at y = 2.5."""
    waypoints = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]])
    leg1 = np.column_stack([np.arange(0, 39) * 0.1, np.full(39, 0.1)])  # x 0 .. 3.8
    leg2 = np.column_stack([np.full(24, 3.85), 0.2 + np.arange(24) * 0.1])  # y 0.2 .. 2.5
    xy = np.vstack([leg1, leg2])
    return np.column_stack([xy, np.full(len(xy), 1.5)]), waypoints


def test_path_deviation_and_drag_known_numbers() -> None:
    pos, wp = l_path_trajectory()
    cmp = compare_to_path(pos, wp)
    np.testing.assert_allclose(cmp.deviation[:39], 0.10, atol=1e-12)
    np.testing.assert_allclose(cmp.deviation[39:], 0.15, atol=1e-12)
    assert cmp.segment.tolist() == [0] * 39 + [1] * 24
    np.testing.assert_allclose(cmp.drag, [0.2, 0.5], atol=1e-12)
    rep = cmp.report()
    assert rep["deviation_m"]["median"] == pytest.approx(0.10)
    assert rep["deviation_m"]["mean"] == pytest.approx((39 * 0.10 + 24 * 0.15) / 63)
    assert rep["drag_mean_abs_m"] == pytest.approx(0.35)


def test_overshoot_is_negative_drag() -> None:
    wp = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]])
    leg1 = np.column_stack([np.linspace(0, 4.3, 44), np.zeros(44)])  # runs 30 cm past the corner
    leg2 = np.column_stack([np.full(10, 4.0), np.linspace(0.5, 3.0, 10)])
    cmp = compare_to_path(np.column_stack([np.vstack([leg1, leg2]), np.zeros(54)]), wp)
    assert cmp.drag[0] == pytest.approx(-0.3)
    assert cmp.drag[1] == pytest.approx(0.0)


def write_traj(path: Path, t: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> Path:
    write_trajectory(path, Trajectory(t, pos, rot))
    return path


def test_cli_truth_report_and_plot(tmp_path: Path) -> None:
    t, pos, rot = make_truth()
    truth = write_traj(tmp_path / "truth.csv", t, pos, rot.as_matrix())
    est = write_traj(tmp_path / "trajectory.csv", t, pos + [0.0, 0.02, 0.0], rot.as_matrix())
    res = CliRunner().invoke(app, ["evaluate", str(est), "--truth", str(truth)])
    assert res.exit_code == 0, res.output
    assert "median 2.00 cm" in res.output
    rep = json.loads((tmp_path / "evaluation.json").read_text())
    assert rep["compared"] == 101
    assert rep["position_error_m"]["median"] == pytest.approx(0.02, abs=1e-6)
    assert rep["rotation_error_deg"]["max"] == pytest.approx(0.0, abs=1e-6)
    assert (tmp_path / "evaluation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_path_report(tmp_path: Path) -> None:
    pos, wp = l_path_trajectory()
    n = len(pos)
    est = write_traj(
        tmp_path / "trajectory.csv",
        1000.0 + np.arange(n) * 0.1,
        pos,
        np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
    )
    path = tmp_path / "path.yaml"
    path.write_text("waypoints: [[0, 0], [4, 0], [4, 3]]\n")
    out, png = tmp_path / "r" / "rep.json", tmp_path / "p.png"
    (tmp_path / "r").mkdir()
    res = CliRunner().invoke(
        app, ["evaluate", str(est), "--path", str(path), "--report", str(out), "--plot", str(png)]
    )
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["drag_m"] == [pytest.approx(0.2), pytest.approx(0.5)]
    assert rep["deviation_m"]["max"] == pytest.approx(0.15)
    assert png.exists()


@pytest.mark.parametrize(
    ("path_text", "message"),
    [
        ("waypoints: [[0, 0]]\n", "at least two [x, y] pairs"),
        ("waypoints: [[0, 0], [1, 1, 1]]\n", "at least two [x, y] pairs"),
        ("points: []\n", "'waypoints'"),
        ("waypoints: [[0, 0], [0, 0]]\n", "the same point"),
        ("waypoints: [[0, 0], [1, 0]\n", "not valid YAML"),
    ],
)
def test_bad_path_files_are_one_line_errors(tmp_path: Path, path_text: str, message: str) -> None:
    t, pos, rot = make_truth(n=5)
    est = write_traj(tmp_path / "trajectory.csv", t, pos, rot.as_matrix())
    path = tmp_path / "path.yaml"
    path.write_text(path_text)
    res = CliRunner().invoke(app, ["evaluate", str(est), "--path", str(path)])
    assert res.exit_code == 1
    assert message in res.output
    assert "path.yaml" in res.output
    assert not (tmp_path / "evaluation.json").exists()


def test_needs_exactly_one_reference(tmp_path: Path) -> None:
    t, pos, rot = make_truth(n=5)
    est = write_traj(tmp_path / "trajectory.csv", t, pos, rot.as_matrix())
    res = CliRunner().invoke(app, ["evaluate", str(est)])
    assert res.exit_code == 1
    assert "exactly one of --truth" in res.output


def test_disjoint_times_are_an_error(tmp_path: Path) -> None:
    t, pos, rot = make_truth(n=5)
    est = write_traj(tmp_path / "trajectory.csv", t, pos, rot.as_matrix())
    truth = write_traj(tmp_path / "truth.csv", t + 100, pos, rot.as_matrix())
    res = CliRunner().invoke(app, ["evaluate", str(est), "--truth", str(truth)])
    assert res.exit_code == 1
    assert "no pose falls inside the time range" in res.output
