"""`annotator calibrate` on rendered ChArUco views of a known camera (with lens distortion)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.render.camera import default_cameras
from annotator.render.charuco import charuco_board, random_board_poses, render_charuco_views

BOARD = [
    "--squares",
    "5x7",
    "--square-length",
    "0.0598",
    "--marker-length",
    "0.0299",
    "--dictionary",
    "DICT_6X6_50",
]
CAMERA = default_cameras()["back"]


@pytest.fixture(scope="module")
def views() -> list[np.ndarray]:
    board = charuco_board((5, 7), 0.0598, 0.0299, "DICT_6X6_50")
    return render_charuco_views(
        CAMERA, board, random_board_poses(14, board, CAMERA, np.random.default_rng(7))
    )


def read_back(path: Path) -> tuple[np.ndarray, np.ndarray, int, int]:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    k = fs.getNode("camera_matrix").mat()
    d = fs.getNode("distortion_coefficients").mat()
    w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
    fs.release()
    return k, d, w, h


def test_calibrate_png_views_recovers_the_focal_lengths(
    views: list[np.ndarray], tmp_path: Path
) -> None:
    paths = []
    for i, img in enumerate(views):
        paths.append(tmp_path / f"view{i:02d}.png")
        cv2.imwrite(str(paths[-1]), img)
    out = tmp_path / "cal" / "camera.yaml"
    res = CliRunner().invoke(app, ["calibrate", *map(str, paths), *BOARD, "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "RMS reprojection error" in res.output
    rms = float(res.output.split("RMS reprojection error")[1].split("px")[0])
    assert 0 < rms < 0.5
    k, d, w, h = read_back(out)
    assert (w, h) == (CAMERA.width, CAMERA.height)
    assert k[0, 0] == pytest.approx(CAMERA.fx, rel=0.01)
    assert k[1, 1] == pytest.approx(CAMERA.fy, rel=0.01)
    assert k[0, 2] == pytest.approx(CAMERA.cx, abs=5)
    assert k[1, 2] == pytest.approx(CAMERA.cy, abs=5)
    assert d.ravel()[0] == pytest.approx(CAMERA.dist[0], abs=0.03)


def test_calibrate_from_a_video(views: list[np.ndarray], tmp_path: Path) -> None:
    video = tmp_path / "board.mp4"
    writer = cv2.VideoWriter(
        str(video), cv2.VideoWriter.fourcc(*"mp4v"), 5, (CAMERA.width, CAMERA.height)
    )
    for img in views:
        for _ in range(2):  # each view held for two frames; --every 2 takes one of each
            writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    out = tmp_path / "camera.yaml"
    res = CliRunner().invoke(
        app, ["calibrate", str(video), *BOARD, "--every", "2", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert "over 14 of 14 views" in res.output
    k, _, _, _ = read_back(out)
    assert k[0, 0] == pytest.approx(CAMERA.fx, rel=0.01)
    assert k[1, 1] == pytest.approx(CAMERA.fy, rel=0.01)


def test_wrong_dictionary_finds_no_board(views: list[np.ndarray], tmp_path: Path) -> None:
    paths = []
    for i, img in enumerate(views[:4]):
        paths.append(tmp_path / f"v{i}.png")
        cv2.imwrite(str(paths[-1]), img)
    out = tmp_path / "camera.yaml"
    args = ["calibrate", *map(str, paths), *BOARD[:-1], "DICT_4X4_50", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1
    assert "found in 0 of 4 views" in res.output
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--squares", "5by7"], "--squares '5by7'"),
        (["--dictionary", "DICT_NOPE"], "unknown ArUco dictionary"),
        (["--marker-length", "0.07"], "smaller than the square length"),
    ],
)
def test_bad_board_settings_are_one_line_errors(
    tmp_path: Path, args: list[str], message: str
) -> None:
    img = tmp_path / "x.png"
    cv2.imwrite(str(img), np.zeros((10, 10), np.uint8))
    res = CliRunner().invoke(
        app, ["calibrate", str(img), *BOARD, *args, "--out", str(tmp_path / "c.yaml")]
    )
    assert res.exit_code == 1
    assert message in res.output
    assert "Traceback" not in res.output


def test_unreadable_input_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "notes.txt"
    bad.write_text("not a picture")
    res = CliRunner().invoke(
        app, ["calibrate", str(bad), *BOARD, "--out", str(tmp_path / "c.yaml")]
    )
    assert res.exit_code == 1
    assert "notes.txt" in res.output


@pytest.fixture(scope="module")
def waved_board_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 s at 30 fps of the board waved in front of a camera with a 15 ms rolling shutter."""
    from annotator.render.charuco import render_charuco_video, waving_board

    board = charuco_board((5, 7), 0.0598, 0.0299, "DICT_6X6_50")
    path = tmp_path_factory.mktemp("readout") / "board.mp4"
    render_charuco_video(
        str(path), CAMERA, board, waving_board(board, seed=3), np.arange(90) / 30.0, 0.015, seed=3
    )
    return path


def test_calibrate_measures_the_readout_from_a_waved_board(
    views: list[np.ndarray], waved_board_video: Path, tmp_path: Path
) -> None:
    """The field procedure: the lens from still views, then the readout from a waved board."""
    from annotator.io.experiment import load_calibration

    paths = []
    for i, img in enumerate(views):
        paths.append(tmp_path / f"view{i:02d}.png")
        cv2.imwrite(str(paths[-1]), img)
    lens = tmp_path / "lens.yaml"
    res = CliRunner().invoke(app, ["calibrate", *map(str, paths), *BOARD, "--out", str(lens)])
    assert res.exit_code == 0, res.output
    out = tmp_path / "camera.yaml"
    res = CliRunner().invoke(
        app,
        ["calibrate", str(waved_board_video), *BOARD, "--readout", "--intrinsics", str(lens),
         "--out", str(out)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "rolling-shutter readout" in res.output
    cal = load_calibration(out)
    assert np.allclose(cal.camera_matrix, load_calibration(lens).camera_matrix)
    # the readout comes back within 1 ms of the truth, and its stated sigma is honest
    assert abs(cal.readout_s - 0.015) < 0.001
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    sigma = fs.getNode("rolling_shutter_readout_sigma_s").real()
    fs.release()
    assert 0 < sigma < 0.002
    assert abs(cal.readout_s - 0.015) < 3 * sigma
    assert "the lens" in res.output  # the lens calibration's uncertainty is part of the sigma


def test_readout_needs_a_video_and_enough_consecutive_frames(
    views: list[np.ndarray], tmp_path: Path
) -> None:
    from annotator.core.readout import BoardView, estimate_readout
    from annotator.errors import NoDataError

    png = tmp_path / "one.png"
    cv2.imwrite(str(png), views[0])
    res = CliRunner().invoke(app, ["calibrate", str(png), *BOARD, "--readout", "--out", "x.yaml"])
    assert res.exit_code != 0
    assert "--readout needs a video" in res.output
    # views scattered in time share no velocity: one line, not a readout of noise
    scattered = [BoardView(10.0 * i, np.zeros((6, 3)), np.zeros((6, 2))) for i in range(12)]
    with pytest.raises(NoDataError, match="consecutive frames"):
        estimate_readout(scattered, CAMERA.K, CAMERA.dist, CAMERA.height, frame_interval=1 / 30)
