"""Planned-path renders: PolylineTrajectory on known numbers, `simulate --path` and its path.yaml."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.io.waypoints import load_waypoints
from annotator.render.trajectory import PRESET_PATHS, PolylineTrajectory

T0 = 1_700_000_000.0
SQUARE = ((0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0), (0.0, 0.0))


def still(waypoints: tuple[tuple[float, float], ...], **kw: object) -> PolylineTrajectory:
    """A polyline walk without wobble or height swing, so poses are exact numbers."""
    return PolylineTrajectory(waypoints, t0=T0, height_swing=0.0, wobble_deg=(0.0, 0.0, 0.0), **kw)


def heading_deg(rot) -> np.ndarray:  # noqa: ANN001 - scipy Rotation
    fwd = rot.apply([1.0, 0.0, 0.0])
    return np.degrees(np.arctan2(fwd[:, 1], fwd[:, 0]))


def test_closed_polyline_walks_turns_in_place_and_repeats() -> None:
    # 2 m sides at 0.5 m/s: 4 s per side, then 1 s turning at the corner; one lap is 20 s.
    traj = still(SQUARE, speed=0.5, dwell=1.0)
    t = T0 + np.array([2.0, 4.0, 4.5, 5.0, 7.0, 19.5, 21.0])
    pos, rot = traj(t)
    np.testing.assert_allclose(
        pos[:, :2], [[1, 0], [2, 0], [2, 0], [2, 0], [2, 1], [0, 0], [0.5, 0]], atol=1e-9
    )
    np.testing.assert_allclose(pos[:, 2], 1.55)
    # Along the first side 0 deg; half way through the corner turn 45; the second side 90;
    # the corner closing the lap turns from -90 back to 0 (half way: -45).
    np.testing.assert_allclose(heading_deg(rot), [0, 0, 45, 90, 90, -45, 0], atol=1e-6)


def test_open_polyline_goes_there_and_back() -> None:
    traj = still(((0.0, 0.0), (1.0, 0.0)), speed=1.0, dwell=1.0)
    pos, rot = traj(T0 + np.array([0.5, 1.5, 2.5, 3.5, 4.5]))
    np.testing.assert_allclose(
        pos[:, :2], [[0.5, 0], [1, 0], [0.5, 0], [0, 0], [0.5, 0]], atol=1e-9
    )
    h = heading_deg(rot)
    np.testing.assert_allclose(np.abs(h[[1, 3]]), 90, atol=1e-6)  # half way through a half turn
    np.testing.assert_allclose(np.abs(h[2]), 180, atol=1e-6)
    np.testing.assert_allclose(h[[0, 4]], 0, atol=1e-6)


def test_no_dwell_and_no_turn() -> None:
    traj = still(SQUARE, speed=0.5, dwell=0.0, turn=False)
    pos, rot = traj(T0 + np.array([4.0, 4.5, 8.0, 12.0]))
    np.testing.assert_allclose(pos[:, :2], [[2, 0], [2, 0.25], [2, 2], [0, 2]], atol=1e-9)
    np.testing.assert_allclose(heading_deg(rot), 0, atol=1e-6)  # the bundle never turns


@pytest.mark.parametrize("name", sorted(PRESET_PATHS))
def test_presets_walk_at_the_speed_inside_the_loop_region(name: str) -> None:
    traj = PolylineTrajectory(PRESET_PATHS[name], t0=T0, speed=0.4)
    t = T0 + np.arange(0.0, 120.0, 0.05)
    pos, rot = traj(t)
    v = np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1) / 0.05
    moving = v > 0.01
    np.testing.assert_allclose(np.median(v[moving]), 0.4, rtol=1e-6)
    assert 0.5 < moving.mean() < 0.95  # stops at the corners take the rest
    assert pos[:, 0].min() >= 7.7
    assert pos[:, 0].max() <= 11.8
    assert pos[:, 1].min() >= 7.0
    assert pos[:, 1].max() <= 10.9
    # While walking, the bundle's x axis is along the velocity (up to the few-degree wobble).
    fwd = rot.apply([1.0, 0.0, 0.0])[:-1, :2][moving]
    vel = np.diff(pos[:, :2], axis=0)[moving]
    cosang = np.sum(fwd * vel, axis=1) / np.linalg.norm(fwd, axis=1) / np.linalg.norm(vel, axis=1)
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 6.0


def test_bad_waypoints_are_refused() -> None:
    with pytest.raises(ValueError, match="same point"):
        PolylineTrajectory(((0.0, 0.0), (0.0, 0.0), (1.0, 0.0)))
    with pytest.raises(ValueError, match="at least two"):
        PolylineTrajectory(((0.0, 0.0),))


def simulate(out: Path, *args: str) -> None:
    res = CliRunner().invoke(
        app,
        [
            "simulate",
            "--out",
            str(out),
            "--duration",
            "1.5",
            "--width",
            "320",
            "--height",
            "180",
            "--start-offset",
            "0.11",
            *args,
        ],
    )
    assert res.exit_code == 0, res.output


def test_simulate_rectangle_writes_a_path_that_evaluate_accepts(tmp_path: Path) -> None:
    simulate(tmp_path, "--path", "rectangle")
    np.testing.assert_allclose(load_waypoints(tmp_path / "path.yaml"), PRESET_PATHS["rectangle"])
    res = CliRunner().invoke(
        app, ["evaluate", str(tmp_path / "truth.csv"), "--path", str(tmp_path / "path.yaml")]
    )
    assert res.exit_code == 0, res.output
    body = json.loads((tmp_path / "evaluation.json").read_text())
    assert body["compared"] == 45 + 41  # every frame of both cameras
    assert body["deviation_m"]["max"] < 1e-6  # the truth walks on the planned path
    # A later loop render into the same folder must not leave the old path behind.
    simulate(tmp_path, "--path", "loop")
    assert not (tmp_path / "path.yaml").exists()


def test_simulate_reads_a_waypoints_file(tmp_path: Path) -> None:
    wp = tmp_path / "mine.yaml"
    wp.write_text("waypoints: [[9.0, 8.0], [10.0, 8.0], [10.0, 9.5]]\n")
    simulate(tmp_path / "r", "--path", str(wp), "--speed", "0.5")
    np.testing.assert_allclose(
        load_waypoints(tmp_path / "r" / "path.yaml"), [[9, 8], [10, 8], [10, 9.5]]
    )
    truth = np.loadtxt(tmp_path / "r" / "truth.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(truth[-1, 1:3], [9.0 + 0.5 * 1.5 * 44 / 45, 8.0], atol=1e-6)


@pytest.mark.parametrize(
    ("value", "message"), [("circle", "--path 'circle'"), ("nope.yaml", "nope.yaml")]
)
def test_bad_path_is_a_one_line_error(tmp_path: Path, value: str, message: str) -> None:
    res = CliRunner().invoke(
        app,
        [
            "simulate",
            "--out",
            str(tmp_path / "x"),
            "--path",
            str(tmp_path / value) if value.endswith(".yaml") else value,
        ],
    )
    assert res.exit_code == 1
    assert message in res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("exposure", ["-0.001", "0.04"])  # 0.04 s is longer than a 30 fps frame
def test_impossible_exposure_is_a_one_line_error(tmp_path: Path, exposure: str) -> None:
    res = CliRunner().invoke(
        app, ["simulate", "--out", str(tmp_path / "x"), "--exposure", exposure]
    )
    assert res.exit_code == 1
    assert "exposure" in res.output
    assert not (tmp_path / "x").exists()
