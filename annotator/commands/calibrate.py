"""`annotator calibrate`: ChArUco camera calibration from images and/or videos -> FileStorage YAML."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import Progress

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

if TYPE_CHECKING:
    from annotator.core.calibration import Calibration, CharucoSpec
    from annotator.core.readout import BoardView, ReadoutEstimate

# 1-sigma of fx, fy, cx, cy, k1, k2, p1, p2, k3 as the calibration found them: `--readout
# --intrinsics` propagates them into the readout's sigma.
SIGMA_KEY = "intrinsics_sigma"
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


def iter_frames(paths: list[Path], every: int, progress: Progress | None = None) -> Iterator:
    """Images as they are; every `every`-th frame of each video. ConfigError names an unreadable file."""
    import cv2

    task = progress.add_task("views", total=len(paths)) if progress else None
    for path in paths:
        if not path.is_file():
            raise ConfigError(f"{path}: no such file")
        if path.suffix.lower() in IMAGE_SUFFIXES:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ConfigError(f"{path}: not a readable image")
            yield img
        else:
            cap = cv2.VideoCapture(str(path))
            if not cap.isOpened():
                raise ConfigError(f"{path}: not a readable image or video")
            i = 0
            try:
                while True:
                    ok, frame = cap.read()
                    if not ok:
                        break
                    if i % every == 0:
                        yield frame
                    i += 1
            finally:
                cap.release()
            if i == 0:
                raise ConfigError(f"{path}: no frames could be decoded")
        if progress is not None and task is not None:
            progress.advance(task)


def write_filestorage(path: Path, cal: Calibration, readout: ReadoutEstimate | None = None) -> None:
    """The YAML cv2.FileStorage writes: camera_matrix, distortion_coefficients, image size, RMS,
    and the rolling-shutter readout (with its sigma) when it was measured."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ConfigError(f"{path}: cannot write the calibration file")
    try:
        fs.write("image_width", int(cal.image_size[0]))
        fs.write("image_height", int(cal.image_size[1]))
        fs.write("camera_matrix", cal.camera_matrix)
        fs.write("distortion_coefficients", cal.dist_coeffs.reshape(1, -1))
        if cal.views_used:  # calibrated here, not read from --intrinsics
            fs.write("avg_reprojection_error", float(cal.rms))
            fs.write("views_used", int(cal.views_used))
        if cal.intrinsics_sigma is not None:
            import numpy as np

            fs.write(SIGMA_KEY, np.asarray(cal.intrinsics_sigma, dtype=float).reshape(1, -1))
        if readout is not None:
            from annotator.io.experiment import READOUT_KEY

            fs.write(READOUT_KEY, float(readout.readout_s))
            fs.write("rolling_shutter_readout_sigma_s", float(readout.sigma_s))
    finally:
        fs.release()


def calibrate(
    inputs: Annotated[
        list[Path], typer.Argument(help="Images (.png, .jpg, ...) and/or videos of the board.")
    ],
    out: Annotated[
        Path, typer.Option("--out", help="Calibration YAML to write (OpenCV FileStorage).")
    ],
    squares: Annotated[str, typer.Option(help="Board size in squares, COLUMNSxROWS.")] = "5x7",
    square_length: Annotated[float, typer.Option(help="Chessboard square side, metres.")] = 0.0598,
    marker_length: Annotated[
        float, typer.Option(help="ArUco marker side inside a square, metres.")
    ] = 0.0299,
    dictionary: Annotated[
        str, typer.Option(help="ArUco dictionary of the board's markers.")
    ] = "DICT_6X6_50",
    every: Annotated[int, typer.Option(help="Use every N-th frame of a video.")] = 10,
    readout: Annotated[
        bool,
        typer.Option(
            "--readout/--no-readout",
            help="Also measure the rolling-shutter readout from every frame of the video(s): "
            "wave the board (turns of 50-150 deg/s, the whole board in view, a short exposure). "
            "Written as rolling_shutter_readout_s, which the tracking and the slate sync use.",
        ),
    ] = False,
    intrinsics: Annotated[
        Path | None,
        typer.Option(
            "--intrinsics",
            help="With --readout: take the lens from this calibration (made from still views of "
            "the board) and only measure the readout. Intrinsics fitted to a waved board are "
            "bent by the very rolling shutter being measured.",
        ),
    ] = None,
) -> None:
    """Calibrate a camera from views of a ChArUco board; prints the RMS reprojection error and
    writes camera_matrix, distortion_coefficients, image_width and image_height (and, with
    --readout, the rolling-shutter readout measured from a video of the board waved)."""
    with one_line_errors():
        from annotator.core.calibration import CharucoSpec, calibrate_charuco, parse_squares

        if every < 1:
            raise ConfigError("--every must be at least 1")
        spec = CharucoSpec(parse_squares(squares), square_length, marker_length, dictionary)
        spec.board()  # bad board settings fail before any decoding
        videos = [p for p in inputs if p.suffix.lower() not in IMAGE_SUFFIXES]
        if readout and not videos:
            raise ConfigError("--readout needs a video of the board being waved, not images")
        if intrinsics is not None:
            if not readout:
                raise ConfigError("--intrinsics goes with --readout (it only adds the readout)")
            cal = _known_intrinsics(intrinsics)
        else:
            with Progress(console=console, transient=True) as bar:
                cal = calibrate_charuco(iter_frames(inputs, every, bar), spec)
        measured = None
        if readout:
            from annotator.core.readout import estimate_readout

            with Progress(console=console, transient=True) as bar:
                views = board_views(videos, spec, bar)
            measured = estimate_readout(
                views,
                cal.camera_matrix,
                cal.dist_coeffs,
                int(cal.image_size[1]),
                intrinsics_sigma=cal.intrinsics_sigma,
            )
        write_filestorage(out, cal, measured)
        k = cal.camera_matrix
        fitted = (
            f"RMS reprojection error {cal.rms:.3f} px over {cal.views_used} of "
            f"{cal.views_total} views"
            if cal.views_used
            else f"lens from {intrinsics}"
        )
        console.print(
            f"{fitted}; fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}; "
            f"wrote {out}",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )
        if measured is not None:
            console.print(
                f"rolling-shutter readout {1e3 * measured.readout_s:.2f} ms "
                f"+- {1e3 * measured.sigma_s:.2f} ms (the fit {1e3 * measured.fit_sigma_s:.2f}, "
                f"the lens {1e3 * measured.lens_sigma_s:.2f}) from {measured.views_used} frames (board "
                f"turning at {measured.rotation_deg_s:.0f} deg/s; RMS {measured.rms_px_global:.3f} "
                f"px with a global shutter, {measured.rms_px:.3f} px with this readout)",
                highlight=False,
                soft_wrap=True,
                markup=False,
            )
            if intrinsics is None:
                console.print(
                    "the lens was fitted to the waved board too: for the best readout calibrate "
                    "it from still views first and pass --intrinsics",
                    style="yellow",
                )
            if measured.rotation_deg_s < 20:
                console.print(
                    "the board hardly turned: wave it faster for a readout worth having",
                    style="yellow",
                )


def _known_intrinsics(path: Path) -> Calibration:
    """A calibration file's lens as a Calibration (no views: nothing was fitted here)."""
    import math

    import numpy as np

    from annotator.core.calibration import Calibration
    from annotator.io.experiment import load_calibration

    if not path.is_file():
        raise ConfigError(f"--intrinsics: no such file {path}")
    known = load_calibration(path)
    if known.model != "radtan":
        raise ConfigError(f"--intrinsics {path}: only the radtan lens model is supported here")
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    node = fs.getNode(SIGMA_KEY) if fs.isOpened() else None
    stated = node.mat() if node is not None and not node.empty() else None
    fs.release()
    sigma = None if stated is None else tuple(float(v) for v in np.asarray(stated).ravel())
    if sigma is None:
        console.print(
            f"{path} does not state its lens's uncertainty ({SIGMA_KEY}): the readout's sigma "
            "leaves it out",
            style="yellow",
        )
    return Calibration(
        known.camera_matrix,
        np.asarray(known.dist_coeffs, dtype=float),
        math.nan,
        (known.width, known.height),
        0,
        0,
        sigma,
    )


def board_views(videos: list[Path], spec: CharucoSpec, progress: Progress) -> list[BoardView]:
    """The board's corners in every frame of each video, stamped by the frame's PTS; videos
    follow each other with an hour between them, so no velocity spans two."""
    import cv2

    from annotator.core.calibration import detect_board
    from annotator.core.readout import BoardView
    from annotator.io.video import iter_frames as video_frames

    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    views = []
    task = progress.add_task("readout", total=len(videos))
    for k, path in enumerate(videos):
        for t, frame in video_frames(path, gray=True):
            found = detect_board(frame, detector, board)
            if found is not None:
                views.append(BoardView(3600.0 * k + t, found[0], found[1]))
        progress.advance(task)
    return views


def register(app: typer.Typer) -> None:
    app.command("calibrate", short_help="Calibrate a camera from views of a ChArUco board.")(
        calibrate
    )
