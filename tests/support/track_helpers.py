"""Builders for the tracking tests: a rig, camera calibrations and projected marker corners."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration, RigCamera
from annotator.vision.detection import Detections
from annotator.vision.geometry import MarkerRoom
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir

FRONT_R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
BACK_R = np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], dtype=float)


def make_room() -> MarkerRoom:
    return MarkerRoom.from_map(read_marker_map(site_dir("tetam") / "marker_positions.dat"), 0.298)


def make_calibration(width: int = 960, height: int = 540, f: float = 700.0) -> CameraCalibration:
    K = np.array([[f, 0, width / 2 - 0.5], [0, f * 1.002, height / 2 - 0.5], [0, 0, 1]])
    return CameraCalibration(
        K, np.array([-0.08, 0.03, 0.0005, -0.0003, 0.0]), width, height, "synthetic"
    )


def make_rig(cal: CameraCalibration | None = None) -> dict[str, RigCamera]:
    cal = cal or make_calibration()
    return {
        "front": RigCamera("front", cal, FRONT_R, np.array([0.04, 0.0, 0.0])),
        "back": RigCamera("back", cal, BACK_R, np.array([-0.04, 0.0, 0.0])),
    }


def make_path(n: int, dt: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, Rotation]:
    """Times, positions and bundle rotations of a smooth walk (~0.4 m/s) inside the tetam room."""
    t = np.arange(n) * dt
    s = 0.4 * t
    pos = np.stack(
        [9.5 + 2.5 * np.cos(s / 2.5), 8.9 + 2.5 * np.sin(s / 2.5), 1.5 + 0.1 * np.sin(t)], 1
    )
    yaw = s / 2.5 + np.pi / 2  # heading along the circle
    rot = Rotation.from_euler(
        "zyx", np.stack([yaw, 0.05 * np.sin(1.3 * t), 0.04 * np.cos(0.9 * t)], 1)
    )
    return t, pos, rot


def project(
    room: MarkerRoom,
    cam: RigCamera,
    R_wb: np.ndarray,
    t_wb: np.ndarray,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
    max_dist: float = 9.0,
) -> Detections:
    """What the camera would detect: markers in front of it, facing it, inside the image."""
    R_wc = R_wb @ cam.R_bundle_camera
    c_w = R_wb @ cam.t_bundle_camera + t_wb
    R_cw = R_wc.T
    ids, corners = [], []
    for i, mid in enumerate(room.ids):
        Xc = (room.corners_world[i] - c_w) @ R_cw.T
        if np.any(Xc[:, 2] < 0.3):
            continue
        normal_c = R_cw @ room.R_world_marker[i][:, 2]
        centre_c = R_cw @ (room.t_world_marker[i] - c_w)
        if (
            normal_c @ centre_c > -0.25 * np.linalg.norm(centre_c)
            or np.linalg.norm(centre_c) > max_dist
        ):
            continue  # seen edge-on or from behind, or too small to decode
        cal = cam.calibration
        px, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
        px = px.reshape(4, 2)
        if np.any(px < 2) or np.any(px[:, 0] > cal.width - 3) or np.any(px[:, 1] > cal.height - 3):
            continue
        if rng is not None and noise_px > 0:
            px = px + rng.normal(0, noise_px, px.shape)
        ids.append(int(mid))
        corners.append(px)
    if not ids:
        return Detections.empty()
    return Detections(np.array(ids), np.array(corners))


def errors_against_truth(traj, truth) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (deg) errors of a trajectory's posed rows inside truth's span."""
    from annotator.core.evaluate import compare_to_truth

    cmp = compare_to_truth(
        traj.t, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    ok = np.isfinite(cmp.position_error)
    return cmp.position_error[ok], cmp.rotation_error_deg[ok]


def simulate_and_track(folder, *simulate_args: str):
    """`annotator simulate --out folder ... --jobs 2`, then the default `annotator track` into
    folder/track; both must succeed. Returns the track folder."""
    from typer.testing import CliRunner

    from annotator.cli import app

    res = CliRunner().invoke(app, ["simulate", "--out", str(folder), *simulate_args, "--jobs", "2"])
    assert res.exit_code == 0, res.output
    out = folder / "track"
    res = CliRunner().invoke(
        app, ["track", str(folder / "experiment.yaml"), "--out", str(out), "--jobs", "2"]
    )
    assert res.exit_code == 0, res.output
    return out
