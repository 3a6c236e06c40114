"""Reading what the sync needs from a video file: the per-frame brightness (hands-cover sync) and
the frames that show the clock slate (slate sync)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from annotator.errors import NoDataError
from annotator.io.video import iter_frames

if TYPE_CHECKING:
    from annotator.core.sync.slate import SlateReading


def brightness_series(
    path: str | Path, progress: Callable[[int], None] | None = None, stride: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """(pts seconds, mean grey level) of every frame; every ``stride``-th pixel is plenty."""
    pts, level = [], []
    for k, (t, frame) in enumerate(iter_frames(path, gray=True)):
        pts.append(t)
        level.append(float(frame[::stride, ::stride].mean()))
        if progress is not None and k % 30 == 0:
            progress(k + 1)
    if not pts:
        raise NoDataError(f"{path}: no frames to read")
    return np.asarray(pts), np.asarray(level)


def slate_readings(
    path: str | Path,
    windows: list[tuple[float, float]],
    progress: Callable[[int], None] | None = None,
) -> list[SlateReading]:
    """The frames inside the PTS ``windows`` (s) that show a readable clock slate. Frames wider
    than 1280 px are searched at half size (the slate fills much of the picture)."""
    import cv2

    from annotator.core.sync.slate import SLATE_DICTIONARY, SlateReading, read_slate_markers

    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, SLATE_DICTIONARY)),
        cv2.aruco.DetectorParameters(),
    )
    out: list[SlateReading] = []
    for k, (t, frame) in enumerate(iter_frames(path, gray=True)):
        if progress is not None and k % 30 == 0:
            progress(k + 1)
        if not any(lo <= t <= hi for lo, hi in windows):
            continue
        scale = 2 if frame.shape[1] > 1280 else 1
        img = frame[::scale, ::scale] if scale > 1 else frame
        corners, ids, _ = detector.detectMarkers(img)
        if ids is None:
            continue
        for value, row in read_slate_markers(np.asarray(corners) * scale, np.asarray(ids)):
            out.append(SlateReading(float(t), row, value))
    return out
