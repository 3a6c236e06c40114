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
    from annotator.core.calibration import Calibration

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


def write_filestorage(path: Path, cal: Calibration) -> None:
    """The YAML cv2.FileStorage writes: camera_matrix, distortion_coefficients, image size, RMS."""
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
        fs.write("avg_reprojection_error", float(cal.rms))
        fs.write("views_used", int(cal.views_used))
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
) -> None:
    """Calibrate a camera from views of a ChArUco board; prints the RMS reprojection error and
    writes camera_matrix, distortion_coefficients, image_width and image_height."""
    with one_line_errors():
        from annotator.core.calibration import CharucoSpec, calibrate_charuco, parse_squares

        if every < 1:
            raise ConfigError("--every must be at least 1")
        spec = CharucoSpec(parse_squares(squares), square_length, marker_length, dictionary)
        spec.board()  # bad board settings fail before any decoding
        with Progress(console=console, transient=True) as bar:
            cal = calibrate_charuco(iter_frames(inputs, every, bar), spec)
        write_filestorage(out, cal)
        k = cal.camera_matrix
        console.print(
            f"RMS reprojection error {cal.rms:.3f} px over {cal.views_used} of {cal.views_total} "
            f"views; fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}; "
            f"wrote {out}",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.command("calibrate", short_help="Calibrate a camera from views of a ChArUco board.")(
        calibrate
    )
