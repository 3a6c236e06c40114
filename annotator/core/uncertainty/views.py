"""The trajectory's frames as the uncertainty sees them: each camera frame at the smoothed pose
and twist of its own time, the output rows it belongs to."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration, Experiment
from annotator.core.uncertainty.records import VideoFrames


def trajectory_twist(
    t: np.ndarray, pos: np.ndarray, R: np.ndarray, h: float = 0.02
) -> tuple[np.ndarray, np.ndarray]:
    """World-frame angular velocity (rad/s) and velocity (m/s) at each row by central differences
    over +-h (one-sided at a run's ends); NaN where the trajectory has no pose."""
    ok = np.isfinite(pos).all(1) & np.isfinite(R).all((1, 2))
    w = np.full((len(t), 3), np.nan)
    v = np.full((len(t), 3), np.nan)
    if ok.sum() < 2:
        return w, v
    tv, pv = t[ok], pos[ok]
    rv = Rotation.from_matrix(R[ok])
    i = np.flatnonzero(ok)
    a = np.clip(np.searchsorted(tv, tv - h), 0, len(tv) - 1)
    b = np.clip(np.searchsorted(tv, tv + h, side="right") - 1, 0, len(tv) - 1)
    a = np.where(b > a, a, np.maximum(b - 1, 0))
    b = np.where(b > a, b, np.minimum(a + 1, len(tv) - 1))
    dt = tv[b] - tv[a]
    good = (dt > 0) & (dt < 4 * h)
    dt = np.where(good, dt, np.nan)
    v[i] = (pv[b] - pv[a]) / dt[:, None]
    w[i] = (rv[b] * rv[a].inv()).as_rotvec() / dt[:, None]
    return w, v


@dataclass(frozen=True, eq=False)
class FrameView:
    """One camera frame seen from the smoothed trajectory: the data for its Jacobians."""

    camera: str
    cal: CameraCalibration
    R_bc: np.ndarray
    t_bc: np.ndarray
    ids: np.ndarray  # (n,)
    pixels: np.ndarray  # (n, 4, 2) detected corners, distorted pixels
    R_wb: np.ndarray  # bundle pose at the frame's own time
    t_wb: np.ndarray
    twist: np.ndarray  # (6,) world-frame (omega, velocity) at the frame's time


def views_at(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_out: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    omega: np.ndarray,
    vel: np.ndarray,
) -> list[list[FrameView]]:
    """Each output row's frames (every camera's frame within half a frame), each at its own pose."""
    rows: list[list[FrameView]] = [[] for _ in t_out]
    ok = np.isfinite(pos).all(1) & np.isfinite(R).all((1, 2))
    for cf in frames:
        cam = exp.rig.cameras[cf.camera]
        times = np.asarray(cf.t, float)
        half = 0.5 * float(cf.frame_interval)
        at = np.clip(np.searchsorted(t_out, times), 0, len(t_out) - 1)
        exact = np.abs(t_out[at] - times) < 1e-6
        for j in np.flatnonzero(exact):
            k = at[j]
            det = cf.detections[int(j)]
            if not ok[k] or not len(det.ids) or not np.isfinite(vel[k]).all():
                continue
            view = FrameView(
                cf.camera,
                cam.calibration,
                cam.R_bundle_camera,
                cam.t_bundle_camera,
                np.asarray(det.ids),
                np.asarray(det.corners, float).reshape(-1, 4, 2),
                R[k],
                pos[k],
                np.concatenate([omega[k], vel[k]]),
            )
            lo = np.searchsorted(t_out, times[j] - half)
            hi = np.searchsorted(t_out, times[j] + half, side="right")
            for kk in range(lo, hi):
                rows[kk].append(view)
    return rows
