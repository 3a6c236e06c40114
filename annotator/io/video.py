"""Reading video frames with their container timestamps (PTS), never a frame counter."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from annotator.errors import AnnotatorError

# FFmpeg's own messages ("moov atom not found") would precede our one-line error about a file
# that is not a video; keep them quiet unless the user asks (OpenCV reads this at the first open).
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


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
        return VideoInfo(
            path,
            int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            float(cap.get(cv2.CAP_PROP_FPS)),
            int(cap.get(cv2.CAP_PROP_FRAME_COUNT)),
        )
    finally:
        cap.release()


# Codec pixel formats whose first plane is 8-bit luma, so a raw frame is a grey image as is.
_LUMA_FIRST = {"I420", "YV12", "IYUV", "Y800", "GREY"}


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's per-frame warning that raw (unconverted) frames are 'at your own risk'."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def _open_luma(path: Path, threads: int | None) -> cv2.VideoCapture | None:
    """A capture returning the decoder's own luma plane (no YUV -> BGR -> grey), or None if the
    stream's pixel format is not one whose first plane is the whole grey image."""
    params = [cv2.CAP_PROP_CONVERT_RGB, 0] + (
        [] if threads is None else [cv2.CAP_PROP_N_THREADS, int(threads)]
    )
    with _quiet_opencv():
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, params)
    if not cap.isOpened():
        return None
    fourcc = int(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT)).to_bytes(4, "little").decode("latin-1")
    if cap.get(cv2.CAP_PROP_CONVERT_RGB) != 0 or fourcc not in _LUMA_FIRST:
        cap.release()
        return None
    return cap


def iter_frames(
    path: str | Path, gray: bool = False, threads: int | None = None, luma: bool = False
) -> Iterator[tuple[float, np.ndarray]]:
    """Yield (pts_seconds, frame) in decode order; pts is relative to the stream start.

    After ``read()``, CAP_PROP_POS_MSEC is the presentation time of the frame just returned,
    so dropped or variable-rate frames keep their true times. ``threads`` caps the decoder's
    threads (1 when videos are already decoded in parallel processes: less CPU per frame).
    ``luma`` (with ``gray``) yields the stream's own Y plane when the codec's pixel format allows
    (4:2:0 planar, grey): about a third less CPU than decoding to BGR and converting, at the cost
    of video-range levels (16..235) instead of 0..255 - fine for marker detection, whose
    thresholds are local; other formats fall back to BGR -> grey.
    """
    path = Path(path)
    cap = None
    if gray and luma:
        if not path.is_file():
            raise AnnotatorError(f"no such video: {path}")
        cap = _open_luma(path, threads)
    raw = cap is not None
    if cap is None:
        cap = _open(path, threads)
    try:
        while True:
            if raw:
                with _quiet_opencv():
                    ok, frame = cap.read()
            else:
                ok, frame = cap.read()
            if not ok:
                return
            pts = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if gray and frame.ndim == 3:
                frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            yield pts, frame
    finally:
        cap.release()
