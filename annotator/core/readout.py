"""The rolling-shutter readout from a video of a ChArUco board moved in front of the camera.

A rolling shutter sees row ``v`` of a frame stamped ``t`` at ``t + readout * v / height``, so a
moving board is drawn a little from each of several poses. Every frame's board pose (at its
stamp) and one readout for the whole video are fitted together to the corners seen: between
frames the board moves as the neighbouring frames' poses say (its velocity is their central
difference), within a frame each corner is seen from the pose at its own row's time. A board
held still determines nothing; waving it (turns about both axes, 50-150 deg/s) determines the
readout to a fraction of a millisecond. Kalibr's rolling-shutter calibration fits a continuous
spline instead of per-frame poses; on a video of consecutive frames the two are alike.

Pure functions on arrays; finding the corners in a video is the calibrate command's job.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from annotator.errors import NoDataError

MAX_GAP_FRAMES = 2  # views further apart than this do not share a velocity


@dataclass(frozen=True, eq=False)
class BoardView:
    """The board's corners found in one frame."""

    t: float  # the frame's stamp, s
    obj: np.ndarray  # (N, 3) corners on the board, m
    img: np.ndarray  # (N, 2) where the image shows them, px (distorted)


@dataclass(frozen=True)
class ReadoutEstimate:
    readout_s: float
    sigma_s: float  # 1-sigma: the fit's own and, when the lens's was given, what it adds
    fit_sigma_s: float  # from the fit's curvature, scaled by its residuals
    views_used: int
    rms_px_global: float  # reprojection RMS with a global shutter (readout 0)
    rms_px: float  # with the readout found
    rotation_deg_s: float  # median angular speed of the board: how much the video showed
    lens_sigma_s: float = float("nan")  # the part the lens calibration's uncertainty adds


LENS_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def estimate_readout(
    views: Sequence[BoardView],
    camera_matrix: np.ndarray,
    dist_coeffs: np.ndarray,
    height: int,
    *,
    frame_interval: float | None = None,
    max_readout: float | None = None,
    intrinsics_sigma: Sequence[float] | None = None,
) -> ReadoutEstimate:
    """Fit the readout (s) to ``views`` of a moving board, in time order.

    The corners are undistorted with the calibration first; residuals are in pixels (normalised
    image coordinates times the focal length). ``intrinsics_sigma`` (1-sigma of fx, fy, cx, cy,
    k1, k2, p1, p2, k3, as ``cv2.calibrateCameraExtended`` gives them) adds what the lens's own
    uncertainty does to the readout: the fit is repeated with each one moved by its sigma (a
    first-order propagation; on renders the lens is most of the error). Raises NoDataError when
    fewer than 10 views lie in runs of consecutive frames."""
    k = np.asarray(camera_matrix, float)
    d = np.asarray(dist_coeffs, float).ravel()
    est = _fit_readout(views, k, d, height, frame_interval, max_readout)
    if intrinsics_sigma is None:
        return est
    var = 0.0
    for j, sig in enumerate(list(intrinsics_sigma)[: len(LENS_PARAMETERS)]):
        if not (np.isfinite(sig) and sig > 0):
            continue
        k2, d2 = k.copy(), np.zeros(max(5, d.size))
        d2[: d.size] = d
        if j < 4:
            k2[(0, 1, 0, 1)[j], (0, 1, 2, 2)[j]] += sig
        else:
            d2[j - 4] += sig
        moved = _fit_readout(views, k2, d2, height, frame_interval, max_readout)
        var += (moved.readout_s - est.readout_s) ** 2
    lens = math.sqrt(var)
    return ReadoutEstimate(
        est.readout_s,
        math.hypot(est.fit_sigma_s, lens),
        est.fit_sigma_s,
        est.views_used,
        est.rms_px_global,
        est.rms_px,
        est.rotation_deg_s,
        lens,
    )


def _runs(t: np.ndarray, frame_interval: float) -> list[np.ndarray]:
    """Index runs of views no more than MAX_GAP_FRAMES frames apart, at least three long."""
    cuts = np.flatnonzero(np.diff(t) > (MAX_GAP_FRAMES + 0.5) * frame_interval) + 1
    return [r for r in np.split(np.arange(len(t)), cuts) if len(r) >= 3]


def _fit_readout(
    views: Sequence[BoardView],
    camera_matrix: np.ndarray,
    dist_coeffs: np.ndarray,
    height: int,
    frame_interval: float | None,
    max_readout: float | None,
) -> ReadoutEstimate:
    views = sorted(views, key=lambda v: v.t)
    if len(views) < 3:
        raise NoDataError(f"the board was found in {len(views)} frames; need at least 10")
    t_all = np.array([v.t for v in views])
    dt = frame_interval or float(np.median(np.diff(t_all)))
    runs = _runs(t_all, dt)
    keep = np.concatenate(runs) if runs else np.zeros(0, int)
    if keep.size < 10:
        raise NoDataError(
            f"only {keep.size} views of the board lie in runs of consecutive frames; need 10 "
            "(give every frame of the video: --every 1)"
        )
    views = [views[i] for i in keep]
    t = t_all[keep]
    n = len(views)
    k = np.asarray(camera_matrix, float)
    f = float(k[0, 0])
    prev, nxt = np.arange(n), np.arange(n)
    start = 0
    for r in _runs(t, dt):
        m = len(r)
        idx = np.arange(start, start + m)
        prev[idx] = np.concatenate([[idx[0]], idx[:-1]])
        nxt[idx] = np.concatenate([idx[1:], [idx[-1]]])
        start += m
    # Initial poses: a global-shutter PnP per view.
    pose0 = np.zeros((n, 6))
    obj_l, norm_l, rows_l, view_l = [], [], [], []
    for i, v in enumerate(views):
        ok, rvec, tvec = cv2.solvePnP(
            v.obj.astype(np.float64), v.img.astype(np.float64), k, dist_coeffs
        )
        if not ok:
            raise NoDataError(f"no board pose in the view at {v.t:.3f} s")
        pose0[i] = np.concatenate([rvec.ravel(), tvec.ravel()])
        und = cv2.undistortPoints(v.img.reshape(-1, 1, 2).astype(np.float64), k, dist_coeffs)
        obj_l.append(v.obj)
        norm_l.append(und.reshape(-1, 2))
        rows_l.append(v.img[:, 1])
        view_l.append(np.full(len(v.obj), i))
    obj = np.vstack(obj_l).astype(float)
    norm = np.vstack(norm_l)
    rows = np.concatenate(rows_l).astype(float)
    vid = np.concatenate(view_l)
    span = np.maximum(t[nxt] - t[prev], 1e-9)

    def velocities(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rot = Rotation.from_rotvec(p[:, :3])
        w = (rot[nxt] * rot[prev].inv()).as_rotvec() / span[:, None]
        v = (p[nxt, 3:] - p[prev, 3:]) / span[:, None]
        return w, v

    def residuals(x: np.ndarray) -> np.ndarray:
        p = x[:-1].reshape(n, 6)
        readout = x[-1]
        w, v = velocities(p)
        tau = readout * rows / height  # each corner's time after its frame's stamp
        rot = Rotation.from_rotvec(w[vid] * tau[:, None]) * Rotation.from_rotvec(p[vid, :3])
        pc = rot.apply(obj) + p[vid, 3:] + v[vid] * tau[:, None]
        return (f * (pc[:, :2] / pc[:, 2:3] - norm)).ravel()

    sparsity = lil_matrix((2 * len(vid), 6 * n + 1), dtype=np.int8)
    for rr, i in enumerate(vid):
        for j in {int(prev[i]), int(i), int(nxt[i])}:
            sparsity[2 * rr : 2 * rr + 2, 6 * j : 6 * j + 6] = 1
    sparsity[:, -1] = 1
    hi = max_readout if max_readout is not None else dt
    x0 = np.concatenate([pose0.ravel(), [0.0]])
    lower = np.full(x0.size, -np.inf)
    upper = np.full(x0.size, np.inf)
    lower[-1], upper[-1] = 0.0, hi
    rms0 = float(np.sqrt(np.mean(residuals(x0) ** 2)) * math.sqrt(2))
    x0[-1] = 0.25 * hi  # start inside the bounds
    sol = least_squares(
        residuals,
        x0,
        jac_sparsity=sparsity,
        bounds=(lower, upper),
        x_scale="jac",
        method="trf",
    )
    res = sol.fun
    dof = max(res.size - sol.x.size, 1)
    s2 = float(res @ res) / dof
    jac = sol.jac
    # The readout's variance: the Schur complement of the poses in J^T J.
    jr = np.asarray(jac[:, -1].todense()).ravel() if hasattr(jac, "todense") else jac[:, -1]
    jp = jac[:, :-1]
    jtj_pp = (jp.T @ jp).toarray() if hasattr(jp, "toarray") else jp.T @ jp
    jtj_pr = np.asarray(jp.T @ jr).ravel()
    schur = float(jr @ jr - jtj_pr @ np.linalg.solve(jtj_pp + 1e-12 * np.eye(len(jtj_pr)), jtj_pr))
    sigma = math.sqrt(s2 / schur) if schur > 0 else math.inf
    w, _ = velocities(sol.x[:-1].reshape(n, 6))
    return ReadoutEstimate(
        readout_s=float(sol.x[-1]),
        sigma_s=sigma,
        fit_sigma_s=sigma,
        views_used=n,
        rms_px_global=rms0,
        rms_px=float(np.sqrt(np.mean(res**2)) * math.sqrt(2)),
        rotation_deg_s=float(np.degrees(np.median(np.linalg.norm(w, axis=1)))),
    )
