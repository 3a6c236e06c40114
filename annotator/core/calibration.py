"""ChArUco camera calibration on arrays: detect board corners per image, then calibrateCamera.

Pure stage: images in, intrinsics out; reading images/videos and writing YAML is the command's job.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from annotator.errors import ConfigError, NoDataError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CharucoSpec:
    squares: tuple[int, int]  # (columns, rows) of chessboard squares
    square_length: float  # metres
    marker_length: float  # metres
    dictionary: str = "DICT_6X6_50"

    def board(self) -> cv2.aruco.CharucoBoard:
        code = getattr(cv2.aruco, self.dictionary, None)
        if not self.dictionary.startswith("DICT_") or not isinstance(code, int):
            raise ConfigError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_6X6_50)")
        if not 0 < self.marker_length < self.square_length:
            raise ConfigError("marker length must be positive and smaller than the square length")
        if min(self.squares) < 2:
            raise ConfigError(f"a ChArUco board needs at least 2x2 squares, not {self.squares}")
        return cv2.aruco.CharucoBoard(
            self.squares,
            self.square_length,
            self.marker_length,
            cv2.aruco.getPredefinedDictionary(code),
        )


@dataclass(frozen=True)
class Calibration:
    camera_matrix: np.ndarray  # 3x3
    dist_coeffs: np.ndarray  # (5,) k1 k2 p1 p2 k3
    rms: float  # reprojection error, px
    image_size: tuple[int, int]  # (width, height)
    views_used: int
    views_total: int
    # 1-sigma of fx, fy, cx, cy, k1, k2, p1, p2, k3 from the fit (OpenCV's estimate); None when
    # unknown (a calibration read from a file that does not state it)
    intrinsics_sigma: tuple[float, ...] | None = None


def parse_squares(text: str) -> tuple[int, int]:
    """'5x7' -> (5, 7)."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--squares {text!r}: expected COLUMNSxROWS, e.g. 5x7") from None
    return cols, rows


def detect_board(
    image: np.ndarray,
    detector: cv2.aruco.CharucoDetector,
    board: cv2.aruco.CharucoBoard,
    min_corners: int = 6,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Object and image points of the ChArUco corners in one image, or None if too few."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    # The stubs want a sequence of arrays; OpenCV also takes ChArUco's one (N, 1, 2) corner array.
    obj, img = board.matchImagePoints(corners, ids)  # type: ignore[call-overload]
    if obj is None or len(obj) < min_corners:
        return None
    return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


def calibrate_charuco(
    images: Iterable[np.ndarray], spec: CharucoSpec, min_corners: int = 6
) -> Calibration:
    """Calibrate from views of the board; NoDataError if fewer than 3 views show enough corners."""
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    obj_pts, img_pts, size, total = [], [], None, 0
    for image in images:
        total += 1
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise ConfigError(f"image {total} is {w}x{h}, the first was {size[0]}x{size[1]}")
        found = detect_board(image, detector, board, min_corners)
        if found is not None:
            obj_pts.append(found[0])
            img_pts.append(found[1])
    log.info("board found in %d of %d views", len(obj_pts), total)
    if len(obj_pts) < 3 or size is None:
        raise NoDataError(
            f"the ChArUco board was found in {len(obj_pts)} of {total} views; need at least 3 "
            "(check --squares, --dictionary and the lengths)"
        )
    # The starting matrix is ignored without CALIB_USE_INTRINSIC_GUESS (the stubs want one).
    rms, k, d, _, _, std, _, _ = cv2.calibrateCameraExtended(
        obj_pts, img_pts, size, np.eye(3), np.zeros(5)
    )
    sigma = tuple(float(v) for v in np.asarray(std).ravel()[:9])
    return Calibration(k, d.ravel()[:5], float(rms), size, len(obj_pts), total, sigma)
