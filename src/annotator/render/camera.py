"""Pinhole cameras with OpenCV lens distortion for the renderer, and the simulated rig.

A frame is drawn undistorted on a padded "ideal" canvas, then warped through a precomputed remap
so the distortion written to the calibration file is the distortion actually in the video.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

# The rig of the render contract: bundle frame x forward, y left, z up; origin at the beacon.
RIG_YAML = """\
cameras:
  front:
    calibration: front.yaml
    R_bundle_camera: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]   # camera-frame vectors -> bundle frame
    t_bundle_camera: [0.04, 0.0, 0.0]                      # camera centre in the bundle frame, m
  back:
    calibration: back.yaml
    R_bundle_camera: [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]   # facing backwards, upside down
    t_bundle_camera: [-0.04, 0.0, 0.0]
"""

RIG_EXTRINSICS: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "front": (np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), np.array([0.04, 0.0, 0.0])),
    "back": (np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], float), np.array([-0.04, 0.0, 0.0])),
}


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera: OpenCV K and distortion (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name for the camera matrix
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.array(self.dist, float)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N,3) -> distorted pixel coordinates (N,2), as cv2.projectPoints."""
        pts = np.asarray(points_cam, float).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return uv.reshape(-1, 2)


def default_cameras(width: int = 960, height: int = 540) -> dict[str, CameraModel]:
    """Two slightly different cameras (fx ~ 620 at 960 px wide) with mild barrel distortion."""
    s = width / 960.0
    return {
        "front": CameraModel(width, height, 620.0 * s, 621.5 * s, width / 2 + 3.2 * s,
                             height / 2 - 2.1 * s, (-0.08, 0.02, 0.0004, -0.0003, 0.0)),
        "back": CameraModel(width, height, 616.0 * s, 617.0 * s, width / 2 - 2.6 * s,
                            height / 2 + 1.7 * s, (-0.075, 0.018, -0.0002, 0.0002, 0.0)),
    }


def camera_pose(bundle_rot: Rotation, bundle_pos: np.ndarray, camera: str) -> tuple[Rotation, np.ndarray]:
    """World pose of a rig camera (R_world_camera, camera centre) from bundle poses (vectorised)."""
    r_bc, t_bc = RIG_EXTRINSICS[camera]
    r_wc = bundle_rot * Rotation.from_matrix(r_bc)
    return r_wc, np.asarray(bundle_pos, float) + bundle_rot.apply(t_bc)


@dataclass(frozen=True)
class DistortionMap:
    """Remap tables from the distorted output image into a padded undistorted canvas."""

    map1: np.ndarray
    map2: np.ndarray
    canvas_K: np.ndarray  # pinhole matrix of the canvas (principal point shifted by the padding)
    canvas_size: tuple[int, int]  # (width, height)


def build_distortion_map(cam: CameraModel) -> DistortionMap:
    """For each output pixel, where its ray lands on an undistorted pinhole canvas."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    # Tight criteria: the renderer must invert projectPoints' distortion model, not approximate it.
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    norm = cv2.undistortPoints(pix, cam.K, cam.dist_array, criteria=crit).reshape(-1, 2)
    x = norm[:, 0] * cam.fx + cam.cx
    y = norm[:, 1] * cam.fy + cam.cy
    pad_x = int(np.ceil(max(0.0, -x.min(), x.max() - (cam.width - 1)))) + 2
    pad_y = int(np.ceil(max(0.0, -y.min(), y.max() - (cam.height - 1)))) + 2
    mx = (x + pad_x).reshape(cam.height, cam.width).astype(np.float32)
    my = (y + pad_y).reshape(cam.height, cam.width).astype(np.float32)
    # Fixed-point maps remap about twice as fast; 1/32 px steps are far below the detector's noise.
    map1, map2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)
    k = cam.K.copy()
    k[0, 2] += pad_x
    k[1, 2] += pad_y
    return DistortionMap(map1, map2, k, (cam.width + 2 * pad_x, cam.height + 2 * pad_y))


def write_calibration(path: str, cam: CameraModel) -> None:
    """OpenCV FileStorage YAML with camera_matrix, distortion_coefficients, image size."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", cam.dist_array.reshape(1, -1))
    finally:
        fs.release()
