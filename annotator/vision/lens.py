"""Lens models of a calibration: pixels <-> normalised image coordinates, for both OpenCV models.

"radtan" is OpenCV's radial-tangential model (cv2.projectPoints / cv2.undistortPoints), "fisheye"
its equidistant model (cv2.fisheye.*). Everything that turns pixels into rays or points into
pixels goes through here, so a new lens model is added in one place.
"""

from __future__ import annotations

import cv2
import numpy as np

from annotator.core.experiment import CameraCalibration

# Tight enough that undistortion is exact to far below the detector's noise at 1080p.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


def undistort_points(cal: CameraCalibration, pixels: np.ndarray) -> np.ndarray:
    """Distorted pixel coordinates (..., 2) -> normalised pinhole coordinates (..., 2)."""
    pts = np.asarray(pixels, dtype=np.float64)
    shape = pts.shape
    if pts.size == 0:
        return np.zeros(shape)
    flat = pts.reshape(-1, 1, 2)
    if cal.model == "fisheye":
        xn = cv2.fisheye.undistortPoints(
            flat, cal.camera_matrix, cal.dist_coeffs.reshape(4, 1), criteria=_CRITERIA
        )
    else:
        xn = cv2.undistortPoints(flat, cal.camera_matrix, cal.dist_coeffs, criteria=_CRITERIA)
    return np.asarray(xn, dtype=float).reshape(shape)


def project_points(cal: CameraCalibration, points_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3) -> distorted pixel coordinates (..., 2)."""
    pts = np.asarray(points_cam, dtype=np.float64)
    out_shape = pts.shape[:-1] + (2,)
    if pts.size == 0:
        return np.zeros(out_shape)
    flat = pts.reshape(-1, 1, 3)
    zero = np.zeros(3)
    if cal.model == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(
            flat, zero, zero, cal.camera_matrix, cal.dist_coeffs.reshape(4, 1)
        )
    else:
        uv, _ = cv2.projectPoints(flat, zero, zero, cal.camera_matrix, cal.dist_coeffs)
    return np.asarray(uv, dtype=float).reshape(out_shape)


def opencv_dist_for_radtan_only(cal: CameraCalibration) -> np.ndarray | None:
    """Distortion coefficients for OpenCV calls that only know the radtan model, or None.

    For a fisheye lens such calls must be given undistorted data instead; None says so.
    """
    return None if cal.model == "fisheye" else cal.dist_coeffs
