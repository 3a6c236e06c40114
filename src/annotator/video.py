"""Reading video frames with their container timestamps (PTS), never a frame counter."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from annotator.errors import AnnotatorError


@dataclass(frozen=True, slots=True)
class VideoInfo:
    path: Path
    width: int
    height: int
    fps: float
    frame_count: int  # what the container claims; may be approximate


def _open(path: Path, threads: int | None = None) -> cv2.VideoCapture:
    if not Path(path).is_file():
        raise AnnotatorError(f"no such video: {path}")
    params = [] if threads is None else [cv2.CAP_PROP_N_THREADS, int(threads)]
    cap = cv2.VideoCapture(str(path), cv2.CAP_ANY, params)
    if not cap.isOpened():
        raise AnnotatorError(f"{path}: cannot open as video (unknown container or codec)")
    return cap


def video_info(path: str | Path) -> VideoInfo:
    path = Path(path)
    cap = _open(path)
    try:
        return VideoInfo(path, int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                         float(cap.get(cv2.CAP_PROP_FPS)), int(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
    finally:
        cap.release()


def iter_frames(path: str | Path, gray: bool = False,
                threads: int | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (pts_seconds, frame) in decode order; pts is relative to the stream start.

    After ``read()``, CAP_PROP_POS_MSEC is the presentation time of the frame just returned,
    so dropped or variable-rate frames keep their true times. ``threads`` caps the decoder's
    threads (1 when videos are already decoded in parallel processes: less CPU per frame).
    """
    path = Path(path)
    cap = _open(path, threads)
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                return
            pts = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if gray and frame.ndim == 3:
                frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            yield pts, frame
    finally:
        cap.release()
