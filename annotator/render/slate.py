"""The clock slate as a camera sees it: the page's layout (four markers in a row, the time in
text below) drawn for a given time, then placed in the camera's picture as a screen held in
front of it. Rows of a rolling-shutter frame that span a refresh of the screen show both values,
as a real camera does; the reader refuses such frames by the check digit."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.core.rolling_shutter import row_delay
from annotator.core.sync.slate import SLATE_DICTIONARY, encode_slate, slate_value_shown

# The page's layout, in units of one marker side: markers with a quarter-side gap, a one-side
# quiet zone around them, and a line of text below.
PAGE_ASPECT = 16 / 9


def slate_page(values_ms: tuple[int, int], width: int = 960) -> np.ndarray:
    """The slate page's picture (gray, ``width`` x ``width / PAGE_ASPECT``): the two codes, the
    upper one showing ``values_ms[0]``, each with its time in text beside it."""
    height = int(round(width / PAGE_ASPECT))
    img = np.full((height, width), 255, np.uint8)
    side = int(width / 6.5)
    gap = side // 4
    x0 = (width - 4 * side - 3 * gap) // 2
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, SLATE_DICTIONARY))
    for row, value in enumerate(values_ms):
        y0 = int(height * (0.27 + 0.46 * row) - side / 2)
        for k, marker_id in enumerate(encode_slate(value)):
            x = x0 + k * (side + gap)
            img[y0 : y0 + side, x : x + side] = cv2.aruco.generateImageMarker(
                dictionary, int(marker_id), side
            )
        cv2.putText(
            img,
            f"{value / 1000:.3f}",
            (x0, y0 + side + side // 4),
            cv2.FONT_HERSHEY_SIMPLEX,
            side / 200,
            0,
            1,
        )
    return img


@dataclass(frozen=True)
class SlateShot:
    """How a camera films the slate: the screen's refresh and where it sits in the picture."""

    refresh_hz: float = 60.0
    phase: float = 0.0  # time of one refresh, s
    fill: float = 0.7  # the screen's width as a share of the picture's
    tilt_px: float = 20.0  # perspective: how far the screen's corners stray from a rectangle
    seed: int = 0


def _screen_corners(shot: SlateShot, width: int, height: int) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence([shot.seed & 0xFFFFFFFF, 17]))
    w = shot.fill * width
    h = w / PAGE_ASPECT
    cx, cy = width / 2, height / 2
    box = np.array([[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2], [cx + w / 2, cy + h / 2]])
    box = np.vstack([box, [cx - w / 2, cy + h / 2]])
    return (box + rng.uniform(-shot.tilt_px, shot.tilt_px, box.shape)).astype(np.float32)


def slate_frame(
    shot: SlateShot, t: float, width: int, height: int, readout: float, exposure: float = 0.0
) -> np.ndarray:
    """The gray picture of a frame stamped ``t`` that films the slate (a dim room around the
    screen's glow). Each row integrates what the screen showed during its exposure (centred on
    the row's time), so a refresh inside it blends two codes, as on a real camera."""
    rows = np.arange(height)
    t_row = t + row_delay(rows, height, readout)
    subs = 4 if exposure > 0 else 1
    page_w = 960
    page_h = int(round(page_w / PAGE_ASPECT))
    src = np.array([[0, 0], [page_w, 0], [page_w, page_h], [0, page_h]], np.float32)
    h = cv2.getPerspectiveTransform(src, _screen_corners(shot, width, height))
    mask = cv2.warpPerspective(
        np.full((page_h, page_w), 255, np.uint8), h, (width, height), flags=cv2.INTER_LINEAR
    )
    acc = np.zeros((height, width), np.float32)
    pictures: dict[tuple[int, int], np.ndarray] = {}
    for k in range(subs):
        ts = t_row + exposure * ((k + 0.5) / subs - 0.5)
        codes = np.stack(
            [slate_value_shown(ts, shot.refresh_hz, shot.phase, r) for r in (0, 1)], axis=1
        )
        pairs: set[tuple[int, int]] = {(int(a), int(b)) for a, b in codes}
        for pair in pairs:
            if pair not in pictures:
                pictures[pair] = cv2.warpPerspective(
                    slate_page(pair, page_w), h, (width, height), flags=cv2.INTER_AREA
                ).astype(np.float32)
            sel = (codes[:, 0] == pair[0]) & (codes[:, 1] == pair[1])
            acc[sel] += pictures[pair][sel] / subs
    # The screen's black is not black and its white not full scale; a dim room around it.
    lit = 30 + acc * (200 / 255)
    return np.where(mask > 127, lit, 40).astype(np.uint8)
