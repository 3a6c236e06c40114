"""The renderer: files of the render contract, marker corners where the detector finds them,
true rotations in truth.csv, the hands-cover event, the default trajectory."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from annotator.cli import app
from annotator.render import LoopTrajectory, default_cameras, render_experiment
from annotator.render.camera import RIG_YAML, CameraModel, camera_pose
from annotator.render.frames import FrameRenderer
from annotator.render.scene import MarkerScene
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir

T0 = 1_700_000_000.0
FPS = 30.0
OFFSET = 0.41


def make_detector() -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50), params)


def detect(det: cv2.aruco.ArucoDetector, img: np.ndarray) -> dict[int, np.ndarray]:
    corners, ids, _ = det.detectMarkers(img)
    return (
        {}
        if ids is None
        else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}
    )


def read_truth(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    return lines[0].split(","), np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])


def read_calibration(path: Path) -> CameraModel:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    k = fs.getNode("camera_matrix").mat()
    d = fs.getNode("distortion_coefficients").mat().ravel()
    w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
    fs.release()
    return CameraModel(w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2], tuple(float(v) for v in d))


def video_frames(path: Path) -> list[tuple[float, np.ndarray]]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        out.append((cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0, img))
    cap.release()
    return out


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s render through the CLI, with the hands over both lenses from 1.6 s for 0.6 s."""
    out = tmp_path_factory.mktemp("sim") / "exp"
    res = CliRunner().invoke(
        app, ["simulate", "--out", str(out), "--duration", "3", "--cover", "1.6:0.6", "--seed", "3"]
    )
    assert res.exit_code == 0, res.output
    return out


def test_simulate_writes_the_contract_files(sim: Path) -> None:
    exp = yaml.safe_load((sim / "experiment.yaml").read_text())
    assert exp["markers"] == {
        "file": "marker_positions.dat",
        "dictionary": "DICT_6X6_50",
        "length": 0.298,
    }
    assert exp["rig"] == "rig.yaml"
    assert exp["videos"] == {"front": "front.mp4", "back": "back.mp4"}
    assert exp["rssi"] == "run"  # the simulated readings: a collector run
    assert (sim / "run" / "run.yaml").is_file()
    assert len(list((sim / "run" / "rssi" / "simulated").glob("*.mbd"))) == 12
    assert exp["sync"] == {"mode": "manual", "video_start": {"front": T0, "back": T0 + OFFSET}}
    assert (sim / "rig.yaml").read_text() == RIG_YAML
    rig = yaml.safe_load(RIG_YAML)["cameras"]
    assert rig["back"]["R_bundle_camera"] == [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]
    assert read_marker_map(sim / "marker_positions.dat") == read_marker_map(
        site_dir() / "marker_positions.dat"
    )
    for name, cam in default_cameras().items():
        got = read_calibration(sim / f"{name}.yaml")
        assert (got.width, got.height) == (960, 540)
        np.testing.assert_allclose(got.K, cam.K)
        np.testing.assert_allclose(got.dist, cam.dist)
    assert not (sim / "rssi").exists()  # only --no-rssi leaves an empty rssi/ folder


def test_the_tracker_loads_the_experiment(sim: Path) -> None:
    from annotator.io.experiment import load_experiment

    exp = load_experiment(sim / "experiment.yaml")
    assert exp.video_start == {"front": T0, "back": T0 + OFFSET}
    assert exp.videos == {"front": sim / "front.mp4", "back": sim / "back.mp4"}
    assert exp.markers.length == 0.298
    assert len(exp.markers.markers) == 30
    for name, cam in default_cameras().items():
        np.testing.assert_allclose(exp.rig.cameras[name].calibration.camera_matrix, cam.K)


def test_videos_have_the_promised_frame_times(sim: Path) -> None:
    for name, n in (("front", 90), ("back", int((3 - OFFSET) * FPS))):
        frames = video_frames(sim / f"{name}.mp4")
        assert len(frames) == n
        pts = np.array([t for t, _ in frames])
        np.testing.assert_allclose(pts, np.arange(n) / FPS, atol=1e-6)
        assert frames[0][1].shape == (540, 960, 3)


def test_truth_is_every_frame_time_with_true_rotations(sim: Path) -> None:
    header, rows = read_truth(sim / "truth.csv")
    assert header == "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33".split(",")
    expected_t = np.union1d(T0 + np.arange(90) / FPS, T0 + OFFSET + np.arange(77) / FPS)
    np.testing.assert_allclose(rows[:, 0], expected_t, atol=1e-6)
    r = rows[:, 4:13].reshape(-1, 3, 3)
    np.testing.assert_allclose(
        r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-9)
    # t is printed to the microsecond, so the poses agree to what moves in a microsecond.
    pos, rot = LoopTrajectory(t0=T0)(rows[:, 0])
    np.testing.assert_allclose(rows[:, 1:4], pos, atol=1e-6)
    np.testing.assert_allclose(r, rot.as_matrix(), atol=1e-6)


def corner_errors(
    sim: Path, name: str, start: float, t_max: float
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Per detected marker: median corner error (px) and side length; expected and found counts."""
    header, rows = read_truth(sim / "truth.csv")
    cam = read_calibration(sim / f"{name}.yaml")
    scene = MarkerScene(read_marker_map(sim / "marker_positions.dat"), 0.298)
    det = make_detector()
    errs, sides, n_exp, n_found = [], [], 0, 0
    for pts, img in video_frames(sim / f"{name}.mp4"):
        t = start + pts
        if t > t_max:
            break
        row = rows[np.argmin(np.abs(rows[:, 0] - t))]
        r_wc, c_w = camera_pose(Rotation.from_matrix(row[4:13].reshape(3, 3)), row[1:4], name)
        expected = scene.expected_corners(cam, r_wc.as_matrix(), c_w)
        found = detect(det, img)
        assert set(found) <= {m.id for m in scene.visible(r_wc.as_matrix(), c_w)}, (
            "a marker out of view"
        )
        if len(expected) < 2:
            continue
        for mid, uv in expected.items():
            n_exp += 1
            if mid in found:
                n_found += 1
                errs.append(np.median(np.linalg.norm(found[mid] - uv, axis=1)))
                sides.append(np.linalg.norm(uv[1] - uv[0]))
    return np.array(errs), np.array(sides), n_exp, n_found


@pytest.mark.parametrize(("name", "start"), [("front", T0), ("back", T0 + OFFSET)])
def test_detected_corners_agree_with_projection(sim: Path, name: str, start: float) -> None:
    # Frames before the hands come; read back from the encoded mp4 as the tracker will.
    errs, sides, n_exp, n_found = corner_errors(sim, name, start, T0 + 1.55)
    assert n_exp >= 60
    assert n_found / n_exp > 0.85
    # ArUco's sub-pixel corners sit ~0.25 px inside the true corner on their own, and the
    # mp4v codec smears markers under ~25 px; both are part of what the tracker will see.
    assert np.median(errs) < 0.6
    big = sides >= 25
    assert big.sum() >= 10
    assert np.median(errs[big]) < 0.5


def test_raw_frames_put_corners_where_projected() -> None:
    """Before blur, noise and encoding: the geometry alone, over several markers."""
    markers = read_marker_map(site_dir() / "marker_positions.dat")
    cam = default_cameras()["front"]
    fr = FrameRenderer(cam, markers, 0.298, "DICT_6X6_50", noise_sigma=0.0, seed=1)
    traj = LoopTrajectory(t0=T0)
    det = make_detector()
    errs = []
    for t in T0 + np.arange(0.0, 40.0, 2.0):
        pos, rot = traj(np.array([t]))
        r_wc, c_w = camera_pose(rot[0], pos[0], "front")
        expected = fr.scene.expected_corners(cam, r_wc.as_matrix(), c_w)
        found = detect(det, fr.render(r_wc.as_matrix(), c_w))
        errs += [np.linalg.norm(found[m] - uv, axis=1) for m, uv in expected.items() if m in found]
    errs = np.concatenate(errs)
    assert len(errs) >= 4 * 40
    assert np.median(errs) < 0.5


def test_hands_cover_darkens_and_hides_markers(sim: Path) -> None:
    frames = video_frames(sim / "front.mp4")
    bright = np.array([img.mean() for _, img in frames])
    det = make_detector()
    t = np.array([p for p, _ in frames])
    before, held = bright[t < 1.55], bright[(t > 1.6 + 0.16) & (t < 2.2)]
    assert held.max() < 0.6 * before.min()
    # The ramp starts at the cover start: the first darkened frame is within one frame of 1.6 s.
    first_dark = t[np.argmax(bright < before.min() - 3)]
    assert abs(first_dark - 1.6) <= 1 / FPS + 1e-6
    for p, img in frames:
        if 1.6 + 0.16 < p < 2.2:
            assert detect(det, img) == {}
    assert detect(det, frames[0][1]), "markers are visible before the cover"
    assert bright[-1] > 0.9 * before.mean(), "uncovered again after the event"


def test_loop_trajectory_walks_at_the_asked_speed() -> None:
    traj = LoopTrajectory(t0=T0, speed=0.4)
    t = T0 + np.arange(0.0, 120.0, 0.05)
    pos, rot = traj(t)
    v = np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1) / 0.05
    np.testing.assert_allclose(np.median(v), 0.4, rtol=1e-3)
    assert 1.2 <= pos[:, 2].min()
    assert pos[:, 2].max() <= 1.9
    # Heading follows the path: the bundle's x axis is along the horizontal velocity (+-5 deg wobble).
    fwd = rot.apply([1.0, 0.0, 0.0])[:-1, :2]
    vel = np.diff(pos[:, :2], axis=0)
    cosang = np.sum(fwd * vel, axis=1) / np.linalg.norm(fwd, axis=1) / np.linalg.norm(vel, axis=1)
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 6.0


def test_two_processes_render_the_same_videos(tmp_path: Path) -> None:
    traj = LoopTrajectory(t0=T0)
    one = render_experiment(
        tmp_path / "one", traj, (T0, T0 + 1.0), width=320, height=180, start_offset=0.1
    )
    two = render_experiment(
        tmp_path / "two", traj, (T0, T0 + 1.0), width=320, height=180, start_offset=0.1, jobs=2
    )
    assert one.frames == two.frames == {"front": 30, "back": 27}
    for name in ("front", "back"):
        a, b = video_frames(one.videos[name]), video_frames(two.videos[name])
        assert all(np.array_equal(x[1], y[1]) for x, y in zip(a, b, strict=True))


def test_bad_cover_is_a_one_line_error(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--cover", "soon"])
    assert res.exit_code == 1
    assert "--cover 'soon'" in res.output
    assert "Traceback" not in res.output


def test_simulate_no_rssi_leaves_an_empty_rssi_folder(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    res = CliRunner().invoke(
        app,
        [
            "simulate",
            "--out",
            str(out),
            "--duration",
            "1",
            "--width",
            "160",
            "--height",
            "90",
            "--no-rssi",
        ],
    )
    assert res.exit_code == 0, res.output
    assert yaml.safe_load((out / "experiment.yaml").read_text())["rssi"] == "rssi"
    assert (out / "rssi").is_dir()
    assert not any((out / "rssi").iterdir())
    assert not (out / "run").exists()
