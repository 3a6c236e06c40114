"""Motion blur: each frame's corner smear (image speed x exposure) from the smoothed motion, and
the down-weighting of smeared frames."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from annotator.core.experiment import Experiment
from annotator.core.uncertainty.records import UncertaintySettings, VideoFrames
from annotator.core.uncertainty.views import FrameView, trajectory_twist, views_at
from annotator.vision.geometry import MarkerRoom, skew

if TYPE_CHECKING:
    pass


def kernel_average(t: np.ndarray, x: np.ndarray, h: float) -> np.ndarray:
    """Gaussian-weighted average over +-3h of the finite rows of x (N, k)."""
    ok = np.isfinite(x).all(1)
    out = np.full_like(x, np.nan)
    if not ok.any() or h <= 0:
        return x.copy()
    tv, xv = t[ok], x[ok]
    lo = np.searchsorted(tv, t - 3 * h)
    hi = np.searchsorted(tv, t + 3 * h, side="right")
    for i in range(len(t)):
        if hi[i] <= lo[i]:
            continue
        dt = tv[lo[i] : hi[i]] - t[i]
        wk = np.exp(-0.5 * (dt / h) ** 2)
        out[i] = wk @ xv[lo[i] : hi[i]] / wk.sum()
    return out


def fill_nearest(t: np.ndarray, x: np.ndarray, want: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x).all(1)
    if not ok.any():
        return x
    tv = t[ok]
    need = want & ~ok
    j = np.clip(np.searchsorted(tv, t[need]), 1, max(len(tv) - 1, 1))
    j0 = np.clip(j - 1, 0, len(tv) - 1)
    j1 = np.clip(j, 0, len(tv) - 1)
    pick = np.where(np.abs(tv[j0] - t[need]) <= np.abs(tv[j1] - t[need]), j0, j1)
    out = x.copy()
    out[need] = x[ok][pick]
    return out


def row_smear(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_out: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    settings: UncertaintySettings | None = None,
) -> np.ndarray:
    """Predicted corner smear (px) of every row's frames: median image speed of the detected
    corners under the trajectory's motion, times the exposure (worst camera of the row)."""
    s = settings or UncertaintySettings()
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    omega, vel = trajectory_twist(t_out, pos, R)
    views = views_at(frames, exp, t_out, pos, R, omega, vel)
    exposure = exposures(frames, exp, s)
    out = np.full(len(t_out), np.nan)
    for k, vs in enumerate(views):
        worst = np.nan
        for v in vs:
            speed = image_speed(v, room)
            if not len(speed):
                continue
            sm = float(np.median(speed)) * exposure[v.camera]
            worst = sm if not np.isfinite(worst) else max(worst, sm)
        out[k] = worst
    return out


def image_speed(view: FrameView, room: MarkerRoom) -> np.ndarray:
    """Image speed (px/s) of each detected map corner of one frame under the view's motion."""
    idx = room.index(view.ids)
    if not (idx >= 0).any():
        return np.zeros(0)
    J, _ = _pose_jacobian(view, room.corners_world[idx[idx >= 0]].reshape(-1, 3))
    return np.zeros(0) if J is None else np.linalg.norm(J @ view.twist, axis=1)


def exposures(
    frames: Sequence[VideoFrames], exp: Experiment, s: UncertaintySettings
) -> dict[str, float]:
    out = {}
    for cf in frames:
        cal = exp.rig.cameras[cf.camera].calibration
        given = getattr(cal, "exposure_s", None)
        out[cf.camera] = (
            float(given)
            if given is not None
            else s.default_exposure_frac * float(cf.frame_interval)
        )
    return out


def _pose_jacobian(v: FrameView, Xw: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """(m, 2, 6) pixel Jacobian of world points w.r.t. the bundle pose, and their projections."""
    K = v.cal.camera_matrix
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    d = Xw - v.t_wb
    Xc = (d @ v.R_wb - v.t_bc) @ v.R_bc
    z = Xc[:, 2]
    if np.any(z <= 1e-6):
        return None, np.zeros((0, 2))
    proj = Xc[:, :2] / z[:, None]
    dp = np.zeros((len(z), 2, 3))
    dp[:, 0, 0] = 1 / z
    dp[:, 1, 1] = 1 / z
    dp[:, :, 2] = -proj / z[:, None]
    a = focal * dp @ (v.R_bc.T @ v.R_wb.T)
    return np.concatenate([a @ skew(d), -a], axis=2), proj


def smear_weights(smear_px: np.ndarray, max_smear_px: float) -> np.ndarray:
    """Measurement covariance multiplier per frame: 1 up to max_smear_px, (smear/max)^2 beyond,
    inf (dropped) beyond three times max_smear_px; NaN smear -> 1."""
    sm = np.nan_to_num(np.asarray(smear_px, float), nan=0.0)
    f = np.maximum(1.0, (sm / max_smear_px) ** 2)
    return np.where(sm > 3 * max_smear_px, np.inf, f)
