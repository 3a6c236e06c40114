"""The marker room as arrays: world coordinates of every marker corner, and pose conversions."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bgt_core.formats.markers import MarkerPose


def marker_corners_local(length: float) -> np.ndarray:
    """(4, 3) corners in the marker frame, in ArUco's order (top-left, clockwise)."""
    h = length / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: skew(a) @ b = a x b."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


@dataclass(frozen=True, eq=False)
class MarkerRoom:
    """Marker poses and corner coordinates in the world frame, indexed by marker id."""

    ids: np.ndarray  # (M,) sorted
    R_world_marker: np.ndarray  # (M, 3, 3)
    t_world_marker: np.ndarray  # (M, 3) marker centres
    corners_world: np.ndarray  # (M, 4, 3)
    length: float

    @classmethod
    def from_map(cls, markers: dict[int, MarkerPose], length: float) -> MarkerRoom:
        ids = np.array(sorted(markers), dtype=int)
        R = Rotation.from_euler("xyz", [markers[i].euler_xyz for i in ids]).as_matrix()
        t = np.array([markers[i].position for i in ids], dtype=float)
        local = marker_corners_local(length)
        corners = np.einsum("mij,kj->mki", R, local) + t[:, None, :]
        return cls(ids, R, t, corners, length)

    def index(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id in the arrays above; -1 for ids not in the room."""
        pos = np.searchsorted(self.ids, ids)
        pos = np.clip(pos, 0, len(self.ids) - 1)
        return np.where(self.ids[pos] == ids, pos, -1)


def camera_to_bundle(
    R_wc: np.ndarray, c_w: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bundle pose in the world from a camera pose (R_world_camera, camera centre) and the rig."""
    R_wb = R_wc @ R_bc.T
    return R_wb, c_w - R_wb @ t_bc


def pnp_to_camera(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """solvePnP's world->camera (rvec, tvec) as (R_world_camera, camera centre in the world)."""
    R_cw = Rotation.from_rotvec(np.ravel(rvec)).as_matrix()
    return R_cw.T, -R_cw.T @ np.ravel(tvec)


_RZ_PI = np.diag([-1.0, -1.0, 1.0])


def ippe_square(
    image_points: np.ndarray,
    length: float,
    camera_matrix: np.ndarray,
    dist_coeffs: np.ndarray | None,
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Both IPPE poses (R_camera_marker, t_camera_marker, reprojection error) of one square, best first.

    OpenCV's IPPE_SQUARE breaks down numerically when R_camera_marker is close to a half turn
    about the camera's y axis (an upside-down camera facing a marker squarely). Solving a second
    time with the corners relabelled by half a turn moves away from that case; the two runs'
    answers are pooled and the broken ones (non-finite, or not reprojecting) discarded.
    """
    local = marker_corners_local(length)
    pts = np.asarray(image_points, dtype=np.float64).reshape(4, 2)
    out: list[tuple[np.ndarray, np.ndarray, float]] = []
    for shift, fix in ((0, np.eye(3)), (2, _RZ_PI)):
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
            local,
            np.roll(pts, -shift, axis=0).reshape(-1, 1, 2),
            camera_matrix,
            dist_coeffs,
            flags=cv2.SOLVEPNP_IPPE_SQUARE,
        )
        for rv, tv, e in zip(rvecs[:n], tvecs[:n], np.ravel(errs)[:n], strict=True):
            rv, tv = np.ravel(rv), np.ravel(tv)
            if (
                not (np.all(np.isfinite(rv)) and np.all(np.isfinite(tv)) and np.linalg.norm(rv) < 7)
                or tv[2] <= 0
            ):
                continue
            # The relabelled square is the real one turned half a turn about its normal.
            R = cv2.Rodrigues(rv)[0] @ fix.T
            out.append((R, tv, float(e)))
    out.sort(key=lambda s: s[2])
    unique: list[tuple[np.ndarray, np.ndarray, float]] = []
    for R, t, e in out:
        if all(np.abs(R - R2).max() > 1e-6 or np.abs(t - t2).max() > 1e-6 for R2, t2, _ in unique):
            unique.append((R, t, e))
    return unique[:2]
