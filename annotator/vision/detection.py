"""ArUco detection for one camera: known ids only, sub-pixel corners, board-based recovery.

Wide frames are detected on a downscaled copy and the corners refined at full resolution; each
frame is thresholded once, and again at three window sizes only when that finds too little.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from annotator.core.experiment import CameraCalibration
from annotator.vision.corners import refine_corners_by_edges
from annotator.vision.geometry import MarkerRoom
from annotator.vision.profile_corners import marker_bits, profile_corners

_REFINE = {
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
    "none": cv2.aruco.CORNER_REFINE_NONE,
}
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)


@dataclass(frozen=True, slots=True, kw_only=True)  # many knobs: name them
class DetectorSettings:
    dictionary: str = "DICT_6X6_50"
    corner_refine: str = "subpix"  # subpix | contour | apriltag | none
    # Detect on a frame scaled by this (0 < s <= 1), corners refined at full resolution.
    # None: halve the frame while it is wider than AUTO_MAX_WIDTH (1080p -> 960x540).
    downscale: float | None = None
    board_refine: bool = (
        True  # recover missed markers by projecting the room (refineDetectedMarkers)
    )
    # Adaptive-threshold window sizes (min, max, step) in detection pixels. One window (7 px) is
    # ~2-3x faster than OpenCV's three (3, 13, 23) and finds ~98-99 % of the markers on our
    # renders with the same pose accuracy; frames where it finds fewer than `retry_below` known
    # markers are detected again with `retry_windows` (None: never).
    threshold_windows: tuple[int, int, int] = (7, 7, 10)
    retry_windows: tuple[int, int, int] | None = (3, 23, 10)
    retry_below: int = 2
    # Frames that still show fewer than `sharpen_below` known markers are detected once more on
    # a sharpened copy (unsharp mask of this sigma, detection pixels; None: never), and the
    # markers it finds are added: a lens slightly out of focus (1.5 px) blurs small markers'
    # cells past reading, and sharpening brings back a quarter of them (bench/detection_recall.py).
    sharpen_px: float | None = 1.5
    sharpen_below: int = 3
    # Board refinement only on frames with fewer than this many known markers (0 = every frame):
    # where several are found, one more adds little, and the search costs as much as a detection.
    board_refine_below: int = 4
    # Keep markers of the dictionary that are not in the map (the refinement maps them from video).
    keep_unknown: bool = False
    # Finish every corner as the intersection of the square's fitted border edges
    # (annotator.vision.corners): unbiased whatever the marker's size in the image, where the
    # corner window is not. None: on when detection runs on a downscaled copy (frames wider than
    # AUTO_MAX_WIDTH, e.g. 1080p), where cornerSubPix's size-dependent bias made the
    # self-calibration take a clean 1080p capture from 0.04 to ~1 cm; off at full-size detection,
    # where on the 960x540 field renders it is a wash (better on average over five seeds, worse on
    # some); the self-calibration measures with them there too (edge_corners_for_refine); on
    # with profile_corners. See docs/annotator.md, "Corners".
    edge_corners: bool | None = None
    # Finish the edge-fit corners with the profile model (annotator.vision.profile_corners): each
    # side's blurred image fitted with the marker's own bits, which stays on the edge where the
    # bits and the quiet zone's end pull the edge fit (small or blurred markers); a marker the
    # model does not fit keeps the edge fit's corners. Off by default: on the field matrix it
    # finds the printed size and cuts the fast walks' error, but the other cells came out
    # 0.02-0.07 cm worse, and detection costs about 3x (docs/annotator.md, "Corners").
    profile_corners: bool = False
    # Board refinement accepts a projected marker this close (full-resolution pixels) to a
    # candidate; a wide one lets it take a small marker's inner contour, one cell in.
    # None: EDGE_BOARD_REFINE_PX with edge corners, else OpenCV's 10 px in the detection image;
    # and 10 px with the profile model at full size (more markers found).
    board_refine_px: float | None = None
    # Where the corners above are the window's, fit the edge corners too, for the
    # self-calibration alone (Detections.edge; +0.8-1 ms CPU per frame). The window corner's bias
    # grows as a marker shrinks in the image, and a free map reads it as markers farther away:
    # on clean 960x540 walks a few markers took corrections of 1-2 cm and the trajectory 0.5 cm.
    # The edge corner has no such bias on sharp frames but is pulled inward on blurred small
    # markers, so the final pass, which also uses blurred frames, keeps the window corners
    # (docs/annotator.md, "Corners"; the profile model, when asked for, finishes these too).
    edge_corners_for_refine: bool = False
    # Where detection runs on a downscaled copy, look again at full resolution where the markers
    # found put the map's others (a pose from two or more found markers): a 30 px marker is
    # 15 px in a half-size copy, too small to read once a real lens and compression soften it.
    # Markers predicted at least `roi_min_side_px` (full-resolution pixels) on a side and wholly
    # in the picture are searched in a crop around their predicted square, on frames where fewer
    # than `roi_below` map markers were found (0: every frame; docs/annotator.md, "Detection").
    roi_search: bool = True
    roi_min_side_px: float = 12.0
    roi_below: int = 4


EDGE_BOARD_REFINE_PX = 6.0
AUTO_MAX_WIDTH = 1280


def auto_downscale(width: int) -> float:
    """The detection scale ``downscale=None`` picks for frames ``width`` pixels wide."""
    s = 1.0
    while width * s > AUTO_MAX_WIDTH:
        s /= 2
    return s


@dataclass(frozen=True, eq=False)
class Detections:
    """Markers seen in one frame: ids (n,) and corners (n, 4, 2) in distorted pixels."""

    ids: np.ndarray
    corners: np.ndarray
    # The same markers' edge-fit corners where ``corners`` are the window's and the detector was
    # asked for both (``DetectorSettings.edge_corners_for_refine``): what the self-calibration
    # measures the map, rig and lenses with. None otherwise.
    edge: np.ndarray | None = None

    @classmethod
    def empty(cls) -> Detections:
        return cls(np.zeros(0, dtype=int), np.zeros((0, 4, 2)))


class MarkerDetector:
    """Holds the OpenCV detector and the room board for one camera (not thread-safe)."""

    def __init__(
        self, settings: DetectorSettings, room: MarkerRoom, calibration: CameraCalibration
    ) -> None:
        if settings.corner_refine not in _REFINE:
            raise ValueError(f"corner_refine must be one of {sorted(_REFINE)}")
        s = auto_downscale(calibration.width) if settings.downscale is None else settings.downscale
        if not 0 < s <= 1:
            raise ValueError("downscale must be in (0, 1]")
        self.settings = settings
        self.scale = s
        edges = s < 1 or settings.profile_corners
        self.edge_corners = edges if settings.edge_corners is None else settings.edge_corners
        self.room = room
        self.calibration = calibration
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, settings.dictionary))
        self._dictionary = dictionary
        self._bits: dict[int, np.ndarray] = {}
        # When corners are refined at full resolution afterwards, skip the detector's own refinement.
        refine = _REFINE["none" if s < 1 else settings.corner_refine]
        board_px = settings.board_refine_px
        if board_px is None and self.edge_corners and (s < 1 or not settings.profile_corners):
            board_px = EDGE_BOARD_REFINE_PX
        rep = 10.0 if board_px is None else max(1.0, board_px * s)
        self._detector = _aruco_detector(dictionary, refine, settings.threshold_windows, rep)
        self._retry = (
            None
            if settings.retry_windows is None
            or settings.retry_windows == settings.threshold_windows
            else _aruco_detector(dictionary, refine, settings.retry_windows, rep)
        )
        self._board = cv2.aruco.Board(
            [c.astype(np.float32) for c in room.corners_world],
            dictionary,
            room.ids.astype(np.int32).reshape(-1, 1),
        )
        K = calibration.camera_matrix.copy()
        K[:2] *= s  # the intrinsics of the downscaled image (pixel centres ignored: sub-pixel only)
        self._K_small = K
        self._dist = calibration.dist_coeffs
        self._roi = (
            _aruco_detector(dictionary, _REFINE["none"], settings.retry_windows or (3, 23, 10))
            if settings.roi_search and s < 1
            else None
        )

    def _add_sharpened(
        self, small: np.ndarray, corners: Any, ids: np.ndarray | None, rejected: Any
    ) -> tuple[Any, np.ndarray | None, Any]:
        """The detection plus the markers found on an unsharp-masked copy that it lacks."""
        sigma = float(self.settings.sharpen_px or 0.0)
        blurred = cv2.GaussianBlur(small, (0, 0), sigma)
        sharp = cv2.addWeighted(small, 2.0, blurred, -1.0, 0)
        more, more_ids, more_rejected = self._detector.detectMarkers(sharp)
        if more_ids is None or len(more_ids) == 0:
            return corners, ids, rejected
        have = set() if ids is None else {int(i) for i in np.asarray(ids).reshape(-1)}
        add = [k for k, i in enumerate(np.asarray(more_ids).reshape(-1)) if int(i) not in have]
        if not add:
            return corners, ids, rejected
        new_corners = list(corners) + [more[k] for k in add]
        new_ids = np.concatenate(
            [
                np.zeros((0, 1), np.int32) if ids is None else np.asarray(ids).reshape(-1, 1),
                np.asarray(more_ids).reshape(-1, 1)[add],
            ]
        ).astype(np.int32)
        return tuple(new_corners), new_ids, rejected

    def _profiled(self, gray: np.ndarray, ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """``pts`` (edge-fit corners of markers ``ids``) finished by the profile model."""
        if not self.settings.profile_corners or len(ids) == 0:
            return np.asarray(pts, np.float64)
        for i in ids:
            if int(i) not in self._bits:
                self._bits[int(i)] = marker_bits(self._dictionary, int(i))
        bits = np.stack([self._bits[int(i)] for i in ids])
        return profile_corners(gray, pts, bits, self.calibration)[0]

    def _known(self, ids: np.ndarray | None) -> int:
        return 0 if ids is None else int(np.count_nonzero(self.room.index(ids.reshape(-1)) >= 0))

    def detect(self, image: np.ndarray) -> Detections:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        s = self.scale
        small = gray if s == 1 else cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        found: tuple[Any, Any, Any] = self._detector.detectMarkers(small)
        corners, ids, rejected = found
        if self._retry is not None and self._known(ids) < self.settings.retry_below:
            again = self._retry.detectMarkers(small)
            if self._known(again[1]) > self._known(ids):
                corners, ids, rejected = again
        if self.settings.sharpen_px is not None and self._known(ids) < self.settings.sharpen_below:
            corners, ids, rejected = self._add_sharpened(small, corners, ids, rejected)
        if ids is None or len(ids) == 0:
            if not self.settings.board_refine or not rejected:
                return Detections.empty()
            corners, ids = (), np.zeros((0, 1), dtype=np.int32)
        ids = ids.reshape(-1)
        # Ids not in the map are someone else's markers, or ones the surveyor skipped (keep_unknown).
        keep = (self.room.index(ids) >= 0) | self.settings.keep_unknown
        corners = [c for c, k in zip(corners, keep, strict=True) if k]
        ids = ids[keep].reshape(-1, 1).astype(np.int32)
        few = self.settings.board_refine_below <= 0 or len(ids) < self.settings.board_refine_below
        if self.settings.board_refine and few and len(ids) > 0 and rejected:
            corners, ids, _, _ = self._detector.refineDetectedMarkers(
                small, self._board, corners, ids, rejected, self._K_small, self._dist
            )
        if ids is None or len(ids) == 0:
            return Detections.empty()
        ids = np.asarray(ids).reshape(-1)
        pts = np.asarray(corners, dtype=np.float32).reshape(-1, 4, 2)
        if s != 1:
            # Pixel centres: (x + 0.5) / s - 0.5 maps a small-image coordinate to the full image.
            pts = ((pts + 0.5) / s - 0.5).astype(np.float32)
            flat = pts.reshape(-1, 1, 2)
            win = max(2, int(round(2.5 / s)))
            cv2.cornerSubPix(gray, flat, (win, win), (-1, -1), _SUBPIX_CRITERIA)
            pts = flat.reshape(-1, 4, 2)
        if self._roi is not None:
            ids, pts = self._search_predicted(gray, ids, pts)
        if self.edge_corners:
            pts = refine_corners_by_edges(gray, pts, self.calibration)
            pts = self._profiled(gray, ids, pts).astype(np.float32)
        # A marker detected twice (reflections, refine) keeps its first copy only.
        _, first = np.unique(ids, return_index=True)
        first.sort()
        keep = first[~nested_quads(pts[first])]
        corners = pts[keep].astype(np.float64)
        edge = None
        if not self.edge_corners and self.settings.edge_corners_for_refine:
            edge = self._profiled(
                gray, ids[keep], refine_corners_by_edges(gray, corners, self.calibration)
            )
        return Detections(ids[keep].astype(int), corners, edge)

    def _search_predicted(
        self, gray: np.ndarray, ids: np.ndarray, pts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``ids``/``pts`` (full-resolution corners) plus the map's markers found at full
        resolution in a crop around where the found ones put them (``roi_search``)."""
        assert self._roi is not None
        idx = self.room.index(ids)
        known = idx >= 0
        n_known = int(np.count_nonzero(known))
        if n_known < 2:  # one square's pose is ambiguous: no prediction
            return ids, pts
        if 0 < self.settings.roi_below <= n_known:
            return ids, pts
        cal = self.calibration
        ok, rvec, tvec = cv2.solvePnP(
            self.room.corners_world[idx[known]].reshape(-1, 3).astype(np.float64),
            pts[known].reshape(-1, 2).astype(np.float64),
            cal.camera_matrix,
            cal.dist_coeffs,
            flags=cv2.SOLVEPNP_SQPNP,
        )
        if not ok:
            return ids, pts
        R = cv2.Rodrigues(rvec)[0]
        missing = np.setdiff1d(np.arange(len(self.room.ids)), idx[known])
        if not len(missing):
            return ids, pts
        world = self.room.corners_world[missing]  # (m, 4, 3)
        cam = world @ R.T + tvec.reshape(1, 1, 3)
        centre = cam.mean(axis=1)
        normal = np.cross(cam[:, 1] - cam[:, 0], cam[:, 2] - cam[:, 1])
        facing = (cam[..., 2] > 0.05).all(1) & (np.einsum("ij,ij->i", normal, centre) > 0)
        if not facing.any():
            return ids, pts
        uv = cv2.projectPoints(
            world[facing].reshape(-1, 1, 3), rvec, tvec, cal.camera_matrix, cal.dist_coeffs
        )[0].reshape(-1, 4, 2)
        h, w = gray.shape[:2]
        side = np.linalg.norm(np.roll(uv, -1, 1) - uv, axis=2).mean(1)
        pad = np.maximum(8.0, 0.4 * side)
        lo, hi = uv.min(1) - pad[:, None], uv.max(1) + pad[:, None]
        inside = (lo[:, 0] >= 0) & (lo[:, 1] >= 0) & (hi[:, 0] < w) & (hi[:, 1] < h)
        want = inside & (side >= self.settings.roi_min_side_px)
        new_ids, new_pts = [], []
        for k in np.flatnonzero(want):
            mid = int(self.room.ids[missing[np.flatnonzero(facing)[k]]])
            x0, y0 = int(lo[k, 0]), int(lo[k, 1])
            x1, y1 = int(np.ceil(hi[k, 0])) + 1, int(np.ceil(hi[k, 1])) + 1
            found_c, found_i, _ = self._roi.detectMarkers(gray[y0:y1, x0:x1])
            if found_i is None:
                continue
            for c, i in zip(found_c, np.asarray(found_i).reshape(-1), strict=True):
                quad = np.asarray(c, np.float32).reshape(4, 2) + np.array([x0, y0], np.float32)
                # The id the map puts there, where it puts it (a quarter of a side).
                if int(i) == mid and np.abs(quad - uv[k]).max() < 0.25 * side[k]:
                    new_ids.append(mid)
                    new_pts.append(quad)
                    break
        if not new_ids:
            return ids, pts
        flat = np.asarray(new_pts, np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(gray, flat, (3, 3), (-1, -1), _SUBPIX_CRITERIA)
        return (
            np.concatenate([ids, np.asarray(new_ids, ids.dtype)]),
            np.concatenate([pts, flat.reshape(-1, 4, 2)]).astype(np.float32),
        )


def nested_quads(corners: np.ndarray) -> np.ndarray:
    """(n,) bool: quads whose centre lies inside a larger quad of the same frame.

    Markers do not overlap, so such a quad is a few cells of a bigger marker's pattern read as a
    marker. The board refinement makes them: it projects every marker of the room with a pose
    fitted to the ones found, a marker behind the camera lands somewhere in the image through the
    lens polynomial, and a candidate there that passes its tolerant bit check gets that id (seen
    on a field render: a 12 px "marker 13" inside marker 8, which the camera faced away from)."""
    if len(corners) < 2:
        return np.zeros(len(corners), bool)
    c = corners.astype(np.float64)
    x, y = c[..., 0], c[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y, axis=1))
    edge = np.roll(c, -1, 1) - c  # (n, 4, 2)
    rel = c.mean(1)[:, None, None] - c[None]  # [i, j]: centre i from quad j's corners, (n, n, 4, 2)
    cross = edge[None, ..., 0] * rel[..., 1] - edge[None, ..., 1] * rel[..., 0]
    inside = (cross > 0).all(2) | (cross < 0).all(2)  # [i, j]: centre i inside quad j
    # No quad is larger than itself, so a quad's own centre never counts.
    return np.asarray((inside & (area[None] > area[:, None])).any(1))


def _aruco_detector(
    dictionary: cv2.aruco.Dictionary,
    refine: int,
    windows: tuple[int, int, int],
    min_rep_distance: float = 10.0,
) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = refine
    params.cornerRefinementWinSize = 5
    params.cornerRefinementMaxIterations = 50
    params.cornerRefinementMinAccuracy = 0.01
    (
        params.adaptiveThreshWinSizeMin,
        params.adaptiveThreshWinSizeMax,
        params.adaptiveThreshWinSizeStep,
    ) = windows
    board = cv2.aruco.RefineParameters()
    board.minRepDistance = float(min_rep_distance)
    return cv2.aruco.ArucoDetector(dictionary, params, board)
