"""Experiment / rig / calibration loading, trajectory.csv round trips, frame times from PTS."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.trajectory import Trajectory
from annotator.errors import AnnotatorError, ConfigError
from annotator.io.experiment import load_calibration, load_experiment
from annotator.io.trajectory import read_trajectory, write_trajectory
from annotator.io.video import iter_frames
from bgt_core.sites import site_dir

K = np.array([[620.0, 0, 480.5], [0, 621.5, 268.25], [0, 0, 1]])
DIST = np.array([[-0.08, 0.02, 0.0004, -0.0003, 0.0]])

RIG = """\
cameras:
  front:
    calibration: cal/front.yaml
    R_bundle_camera: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    t_bundle_camera: [0.04, 0.0, 0.0]
  back:
    calibration: cal/back.yaml
    R_bundle_camera: [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]
    t_bundle_camera: [-0.04, 0.0, 0.0]
"""

ROS = """\
image_width: 960
image_height: 540
camera_name: back
camera_matrix: {rows: 3, cols: 3, data: [620.0, 0.0, 480.5, 0.0, 621.5, 268.25, 0.0, 0.0, 1.0]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [-0.08, 0.02, 0.0004, -0.0003, 0.0]}
rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
projection_matrix: {rows: 3, cols: 4, data: [620, 0, 480.5, 0, 0, 621.5, 268.25, 0, 0, 0, 1, 0]}
"""


def write_filestorage(path: Path) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 960)
    fs.write("image_height", 540)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", DIST)
    fs.release()


def make_video(path: Path, n: int = 6, fps: float = 25.0) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (64, 48))
    for i in range(n):
        w.write(np.full((48, 64, 3), 30 * i, np.uint8))
    w.release()


def make_experiment(tmp_path: Path, **override: str) -> Path:
    """An experiment folder with a nested calibration folder (paths are relative to each file)."""
    (tmp_path / "cal").mkdir()
    write_filestorage(tmp_path / "cal" / "front.yaml")
    (tmp_path / "cal" / "back.yaml").write_text(ROS)
    (tmp_path / "rig.yaml").write_text(override.get("rig", RIG))
    shutil.copy(site_dir("tetam") / "marker_positions.dat", tmp_path / "marker_positions.dat")
    (tmp_path / "vid").mkdir()
    make_video(tmp_path / "vid" / "front.mp4")
    make_video(tmp_path / "vid" / "back.mp4")
    text = override.get(
        "experiment",
        """\
markers: {file: marker_positions.dat, dictionary: DICT_6X6_50, length: 0.298}
rig: rig.yaml
videos: {front: vid/front.mp4, back: vid/back.mp4}
rssi: rssi
sync:
  mode: manual
  video_start: {front: 1700000000.00, back: 1700000000.41}
""",
    )
    (tmp_path / "experiment.yaml").write_text(text)
    return tmp_path / "experiment.yaml"


def test_experiment_loads_with_relative_paths_and_both_calibration_flavours(tmp_path):
    exp = load_experiment(make_experiment(tmp_path))
    assert set(exp.videos) == {"front", "back"}
    assert exp.videos["front"] == tmp_path / "vid" / "front.mp4"
    assert exp.video_start == {"front": 1700000000.0, "back": 1700000000.41}
    assert exp.markers.dictionary == "DICT_6X6_50"
    assert exp.markers.length == 0.298
    assert len(exp.markers.markers) == 30
    for cam in exp.rig.cameras.values():  # FileStorage (front) and ROS camera_info (back) agree
        assert np.allclose(cam.calibration.camera_matrix, K)
        assert np.allclose(cam.calibration.dist_coeffs, DIST.ravel())
        assert (cam.calibration.width, cam.calibration.height) == (960, 540)
    back = exp.rig.cameras["back"]
    assert np.allclose(back.R_bundle_camera @ [0, 0, 1], [-1, 0, 0])  # looks backwards
    assert np.allclose(back.t_bundle_camera, [-0.04, 0, 0])


def test_old_opencv_yaml_header_is_accepted(tmp_path):
    p = tmp_path / "old.yaml"
    write_filestorage(p)
    p.write_text(p.read_text().replace("%YAML 1.2", "%YAML:1.0"))
    assert p.read_text().startswith("%YAML:1.0")
    cal = load_calibration(p)
    assert np.allclose(cal.camera_matrix, K)


@pytest.mark.parametrize(
    ("what", "old", "new", "message"),
    [
        (
            "experiment",
            "videos: {front: vid/front.mp4, back: vid/back.mp4}",
            "videos: {front: vid/front.mp4, side: x.mp4}",
            "videos: camera(s) side not in the rig",
        ),
        ("experiment", "vid/back.mp4}", "vid/gone.mp4}", "videos.back: no such file"),
        ("experiment", "DICT_6X6_50", "DICT_6X6_51", "unknown ArUco dictionary 'DICT_6X6_51'"),
        ("experiment", "length: 0.298", "length: -1", "markers.length must be positive"),
        (
            "experiment",
            "  video_start: {front: 1700000000.00, back: 1700000000.41}\n",
            "",
            "sync.video_start is missing",
        ),
        (
            "experiment",
            "  video_start: {front: 1700000000.00, back: 1700000000.41}",
            "  video_start: {front: 1700000000.00}",
            "no start time for back",
        ),
        ("experiment", "rig: rig.yaml", "rig: [oops", "not valid YAML"),
        ("rig", "[0, -1, 0]]", "[0, -2, 0]]", "cameras.front: R_bundle_camera: not a rotation"),
        (
            "rig",
            "t_bundle_camera: [0.04, 0.0, 0.0]",
            "t_bundle_camera: [0.04]",
            "t_bundle_camera: expected shape (3,)",
        ),
        (
            "rig",
            "calibration: cal/back.yaml",
            "calibration: cal/none.yaml",
            "cameras.back.calibration: no such file",
        ),
    ],
)
def test_bad_files_give_one_line_errors_naming_file_and_field(tmp_path, what, old, new, message):
    text = make_experiment(tmp_path).read_text() if what == "experiment" else RIG
    assert old in text
    kwargs = {what: text.replace(old, new)}
    shutil.rmtree(tmp_path)
    tmp_path.mkdir()
    path = make_experiment(tmp_path, **kwargs)
    with pytest.raises(ConfigError) as e:
        load_experiment(path)
    msg = str(e.value)
    assert message in msg
    assert "\n" not in msg
    assert ("rig.yaml" if what == "rig" else "experiment.yaml") in msg


def test_calibration_missing_key_is_named(tmp_path):
    p = tmp_path / "cam.yaml"
    p.write_text(ROS.replace("image_height: 540\n", ""))
    with pytest.raises(ConfigError, match=r"cam\.yaml: missing 'image_height'"):
        load_calibration(p)


def test_frames_come_with_container_timestamps(tmp_path):
    make_video(tmp_path / "v.mp4", n=8, fps=25.0)
    pts = [t for t, _ in iter_frames(tmp_path / "v.mp4")]
    assert np.allclose(pts, np.arange(8) / 25.0, atol=1e-6)
    gray = next(iter_frames(tmp_path / "v.mp4", gray=True))[1]
    assert gray.ndim == 2


def test_luma_frames_match_grey_frames_at_the_same_times(tmp_path):
    # An odd width and a textured image: a wrong plane stride or chroma mix-up would show.
    w = cv2.VideoWriter(str(tmp_path / "v.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (200, 120))
    rng = np.random.default_rng(1)
    base = cv2.resize(
        rng.integers(0, 256, (15, 25, 3), dtype=np.uint8),
        (200, 120),
        interpolation=cv2.INTER_NEAREST,
    )
    for i in range(5):
        w.write(np.roll(base, 8 * i, axis=1))
    w.release()
    grey = list(iter_frames(tmp_path / "v.mp4", gray=True))
    luma = list(iter_frames(tmp_path / "v.mp4", gray=True, threads=1, luma=True))
    assert [t for t, _ in luma] == [t for t, _ in grey]
    for (_, g), (_, y) in zip(grey, luma, strict=True):
        assert y.shape == g.shape == (120, 200)
        assert y.dtype == np.uint8
        # Video-range luma is grey scaled into 16..235: a straight line through the pixel pairs.
        fit = np.polyfit(g.ravel().astype(float), y.ravel().astype(float), 1)
        assert fit[0] == pytest.approx(219 / 255, abs=0.03)
        assert fit[1] == pytest.approx(16, abs=3)
        assert np.corrcoef(g.ravel(), y.ravel())[0, 1] > 0.99


def test_luma_of_a_missing_video_is_a_one_line_error(tmp_path):
    with pytest.raises(AnnotatorError, match="no such video"):
        list(iter_frames(tmp_path / "none.mp4", gray=True, luma=True))


def test_unreadable_video_is_a_one_line_error(tmp_path):
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    with pytest.raises(AnnotatorError, match="cannot open as video"):
        list(iter_frames(tmp_path / "bad.mp4"))


def test_trajectory_round_trip_keeps_gaps_and_true_rotations(tmp_path):
    n = 5
    t = 1_700_000_000.0 + np.arange(n) / 30
    R = Rotation.from_euler("zyx", np.linspace(0, 1, 3 * n).reshape(n, 3)).as_matrix()
    p = np.arange(3 * n, dtype=float).reshape(n, 3) / 7
    p[2], R[2] = np.nan, np.nan
    traj = Trajectory(
        t,
        p,
        R,
        {"markers": np.array([3, 2, 0, 5, 1.0]), "rms_px": np.array([0.5, 0.7, np.nan, 1, 2])},
    )
    write_trajectory(tmp_path / "trajectory.csv", traj)
    header = (tmp_path / "trajectory.csv").read_text().splitlines()[0]
    assert header == "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33,markers,rms_px"
    back = read_trajectory(tmp_path / "trajectory.csv")
    assert np.allclose(back.t, t, atol=1e-6, rtol=0)
    assert back.valid.tolist() == [True, True, False, True, True]
    ok = back.valid
    assert np.allclose(back.position[ok], p[ok], atol=1e-6)
    Rb = back.rotation[ok]
    assert np.abs(np.einsum("nji,njk->nik", Rb, Rb) - np.eye(3)).max() < 1e-9
    assert np.allclose(np.linalg.det(Rb), 1, atol=1e-9)
    assert back.quality["markers"].tolist()[:2] == [3, 2]
    assert math.isnan(back.quality["rms_px"][2])
    assert not (tmp_path / "trajectory.csv.part").exists()


def test_malformed_trajectory_names_the_line(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33\n1,2,3,4,1,0,0,0,1,0,0,0,1\n2,x,3\n")
    with pytest.raises(AnnotatorError, match=r"t\.csv:3: not 13 numbers"):
        read_trajectory(p)
    p.write_text("t,x,y\n")
    with pytest.raises(AnnotatorError, match="lacks column"):
        read_trajectory(p)


def test_video_size_not_matching_its_calibration_is_a_clear_error(tmp_path):
    from annotator.errors import NoDataError
    from annotator.pipeline import TrackSettings, track_experiment

    exp = load_experiment(make_experiment(tmp_path))  # 64x48 videos, 960x540 calibrations
    with pytest.raises(
        NoDataError,
        match=r"front\.mp4: frames are 64x48 but the calibration front\.yaml is for 960x540",
    ):
        track_experiment(exp, TrackSettings())


def test_videos_without_markers_are_no_data(tmp_path):
    from annotator.errors import NoDataError
    from annotator.pipeline import TrackSettings, track_experiment

    path = make_experiment(tmp_path)
    for cal in ("front.yaml", "back.yaml"):  # calibrations for the tiny blank test videos
        p = tmp_path / "cal" / cal
        p.write_text(p.read_text().replace("960", "64").replace("540", "48"))
    for method in ("rig", "paper"):
        with pytest.raises(NoDataError, match="no marker from the map was detected"):
            track_experiment(load_experiment(path), TrackSettings(method=method))
