"""Reading the per-frame brightness series that automatic sync needs from a video file."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from annotator.errors import NoDataError
from annotator.io.video import iter_frames


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
