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
    """Intrinsics of one camera: OpenCV K and a lens model with its coefficients.

    ``model`` "radtan": OpenCV's radial-tangential model, dist = (k1, k2, p1, p2[, k3]);
    "fisheye": OpenCV's equidistant fisheye model, dist = (k1, k2, k3, k4).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    model: str = "radtan"

    def __post_init__(self) -> None:
        if self.model not in ("radtan", "fisheye"):
            raise ValueError(f"unknown lens model {self.model!r} (radtan or fisheye)")
        if self.model == "fisheye" and len(self.dist) != 4:
            raise ValueError("the fisheye model takes 4 coefficients (k1 k2 k3 k4)")

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name for the camera matrix
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.array(self.dist, float)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N,3) -> distorted pixel coordinates (N,2), as cv2.projectPoints."""
        pts = np.asarray(points_cam, float).reshape(-1, 1, 3)
        if self.model == "fisheye":
            uv, _ = cv2.fisheye.projectPoints(
                pts, np.zeros(3), np.zeros(3), self.K, self.dist_array.reshape(4, 1)
            )
        else:
            uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return uv.reshape(-1, 2)

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N, 2) -> normalised pinhole coordinates (N, 2), exactly.

        OpenCV's fixed-point undistortion can stop short of the solution for a strong lens
        (k1 = -0.28) near the picture's corners; a few Newton steps on projectPoints finish it,
        so the renderer inverts the model it claims to the last hundredth of a pixel.
        """
        pix = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        if self.model == "fisheye":
            xn = cv2.fisheye.undistortPoints(
                pix, self.K, self.dist_array.reshape(4, 1), criteria=crit
            )
        else:
            xn = cv2.undistortPoints(pix, self.K, self.dist_array, criteria=crit)
        xn = xn.reshape(-1, 2)
        target = pix.reshape(-1, 2)
        eps = 1e-7
        for _ in range(5):
            uv = self.project(np.column_stack([xn, np.ones(len(xn))]))
            res = target - uv
            if np.abs(res).max() < 1e-6:
                break
            # Numeric 2x2 Jacobian per point; the lens models are smooth, so this converges fast.
            ju = (self.project(np.column_stack([xn + [eps, 0.0], np.ones(len(xn))])) - uv) / eps
            jv = (self.project(np.column_stack([xn + [0.0, eps], np.ones(len(xn))])) - uv) / eps
            det = ju[:, 0] * jv[:, 1] - jv[:, 0] * ju[:, 1]
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (jv[:, 1] * res[:, 0] - jv[:, 0] * res[:, 1]) / det
            dy = (-ju[:, 1] * res[:, 0] + ju[:, 0] * res[:, 1]) / det
            xn = xn + np.column_stack([dx, dy])
        return xn


# Lenses of the rendered cameras, (front, back) coefficients per model:
# mild: today's default, gentle barrel distortion; wide: a strong radial-tangential lens
# (k1 = -0.28 with the positive k2 that keeps such a lens' distortion monotonic over the
# picture); fisheye: OpenCV's equidistant model with small corrections.
LENSES: dict[str, tuple[str, tuple[float, ...], tuple[float, ...]]] = {
    "mild": ("radtan", (-0.08, 0.02, 0.0004, -0.0003, 0.0), (-0.075, 0.018, -0.0002, 0.0002, 0.0)),
    "wide": ("radtan", (-0.28, 0.074, 0.0002, 0.00002, 0.0), (-0.275, 0.071, -0.0003, 0.0001, 0.0)),
    "fisheye": ("fisheye", (0.03, -0.012, 0.004, -0.0008), (0.028, -0.01, 0.0035, -0.0006)),
}


def default_cameras(
    width: int = 960, height: int = 540, lens: str = "mild", k1: float | None = None
) -> dict[str, CameraModel]:
    """Two slightly different cameras (fx ~ 620 at 960 px wide) with the named lens (`LENSES`);
    `k1` replaces both cameras' first radial coefficient."""
    if lens not in LENSES:
        raise ValueError(f"unknown lens {lens!r} ({', '.join(LENSES)})")
    model, d_front, d_back = LENSES[lens]
    if k1 is not None:
        d_front, d_back = (k1, *d_front[1:]), (k1, *d_back[1:])
    s = width / 960.0
    return {
        "front": CameraModel(
            width,
            height,
            620.0 * s,
            621.5 * s,
            width / 2 + 3.2 * s,
            height / 2 - 2.1 * s,
            d_front,
            model,
        ),
        "back": CameraModel(
            width,
            height,
            616.0 * s,
            617.0 * s,
            width / 2 - 2.6 * s,
            height / 2 + 1.7 * s,
            d_back,
            model,
        ),
    }


def camera_pose(
    bundle_rot: Rotation, bundle_pos: np.ndarray, camera: str
) -> tuple[Rotation, np.ndarray]:
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
    row_span: np.ndarray  # (height, 2) int: canvas rows [lo, hi) each output row samples from


def build_distortion_map(cam: CameraModel) -> DistortionMap:
    """For each output pixel, where its ray lands on an undistorted pinhole canvas."""
    u, v = np.meshgrid(
        np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64)
    )
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    # Exact inversion: the renderer must invert the projection it claims, not approximate it.
    norm = cam.undistort(pix)
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
    # Bilinear sampling reads the row below too: one row of slack each side.
    span = np.column_stack([np.floor(my.min(axis=1)) - 1, np.ceil(my.max(axis=1)) + 2]).astype(int)
    span = np.clip(span, 0, cam.height + 2 * pad_y)
    return DistortionMap(map1, map2, k, (cam.width + 2 * pad_x, cam.height + 2 * pad_y), span)


def write_calibration(
    path: str, cam: CameraModel, readout_s: float | None = None, exposure_s: float | None = None
) -> None:
    """OpenCV FileStorage YAML with camera_matrix, distortion_coefficients, image size; the
    lens model when it is not the default radial-tangential one, and the rolling-shutter
    readout and the exposure time when given."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", cam.dist_array.reshape(1, -1))
        if cam.model != "radtan":
            fs.write("distortion_model", cam.model)
        if readout_s is not None:
            fs.write("rolling_shutter_readout_s", float(readout_s))
        if exposure_s is not None:
            fs.write("exposure_s", float(exposure_s))
    finally:
        fs.release()


def rig_yaml(extrinsics: dict[str, tuple[np.ndarray, np.ndarray]]) -> str:
    """rig.yaml for cameras at the given (R_bundle_camera, t_bundle_camera); the standard rig
    gives exactly `RIG_YAML`."""
    if all(
        np.array_equal(extrinsics[n][0], RIG_EXTRINSICS[n][0])
        and np.array_equal(extrinsics[n][1], RIG_EXTRINSICS[n][1])
        for n in RIG_EXTRINSICS
    ) and set(extrinsics) == set(RIG_EXTRINSICS):
        return RIG_YAML
    lines = [
        "# Rig as written for the annotator (see perturbation.yaml for the true one).",
        "cameras:",
    ]
    for name, (r, t) in extrinsics.items():
        rows = ", ".join(
            "[" + ", ".join(repr(float(v)) for v in row) + "]" for row in np.asarray(r)
        )
        lines += [
            f"  {name}:",
            f"    calibration: {name}.yaml",
            f"    R_bundle_camera: [{rows}]",
            "    t_bundle_camera: [" + ", ".join(repr(float(v)) for v in np.asarray(t)) + "]",
        ]
    return "\n".join(lines) + "\n"
