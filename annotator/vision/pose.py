"""Bundle pose from marker corners: per-camera PnP for a start, then one robust joint solve.

The joint solve is an iteratively re-weighted (Huber) Gauss-Newton over the bundle pose
(rotation perturbation in the world frame + translation), with every camera's corners projected
through the rig extrinsics; its covariance is sigma^2 (J^T W J)^-1. Residuals are in pixels.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration
from annotator.core.rolling_shutter import moved_points
from annotator.vision.detection import Detections
from annotator.vision.geometry import MarkerRoom, camera_to_bundle, ippe_square, pnp_to_camera
from annotator.vision.lens import undistort_points

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SolverSettings:
    huber_px: float = 1.5  # residuals beyond this many pixels are down-weighted
    marker_gate_px: float = 3.0  # a marker whose RMS exceeds max(this, 4 x median) is dropped
    min_sigma_px: float = 0.3  # floor on the fitted noise, so few-corner fits are not overconfident
    # A lone square's linearised covariance ignores how far corner bias moves it (its pose is
    # nearly ambiguous); widen it so the smoother leans on multi-marker frames.
    single_marker_cov_scale: float = 25.0
    iterations: int = 12


@dataclass(frozen=True, eq=False)
class CameraObservation:
    """One camera's corners in one frame, undistorted to normalised image coordinates."""

    ids: np.ndarray  # (n,)
    xn: np.ndarray  # (n, 4, 2) normalised coordinates (pinhole, distortion removed)
    world: np.ndarray  # (n, 4, 3) the same corners in the world
    R_bc: np.ndarray  # camera -> bundle rotation (possibly motion-compensated)
    t_bc: np.ndarray
    focal: float  # pixels per normalised unit, to express residuals in pixels


@dataclass(frozen=True, eq=False)
class BundlePose:
    R_wb: np.ndarray  # (3, 3) bundle -> world
    t_wb: np.ndarray  # (3,) bundle origin (the beacon) in the world
    cov: np.ndarray  # (6, 6): world-frame rotation perturbation (rad), then position (m)
    rms_px: float
    n_markers: int
    alternatives: tuple[BundlePose, ...] = field(
        default=()
    )  # other poses that fit as well (one marker)


def observe(
    det: Detections,
    room: MarkerRoom,
    cal: CameraCalibration,
    R_bc: np.ndarray,
    t_bc: np.ndarray,
    motion: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> CameraObservation:
    """Undistort one frame's detections and attach their world corners.

    With a rolling shutter (``cal.readout_s`` > 0) and the bundle's ``motion`` at the frame time,
    (R_wb, p_wb, angular velocity, velocity; world frame), each corner is seen at frame time +
    readout x row / height. Its world point is moved so that the bundle pose at the frame time sees
    it where the bundle pose at its own time saw the real corner: every solver downstream stays a
    global-shutter solver.
    """
    idx = room.index(det.ids)
    keep = idx >= 0
    ids, corners, idx = det.ids[keep], det.corners[keep], idx[keep]
    if cal.corner_bias_px and len(ids):
        # The detector's corner bias (estimated by the refinement): move each corner back along
        # its square's diagonal.
        d = corners - corners.mean(axis=1, keepdims=True)
        corners = corners - cal.corner_bias_px * d / np.maximum(
            np.linalg.norm(d, axis=2, keepdims=True), 1e-9
        )
    xn = undistort_points(cal, corners.reshape(-1, 4, 2)) if len(ids) else np.zeros((0, 4, 2))
    focal = float(np.sqrt(cal.camera_matrix[0, 0] * cal.camera_matrix[1, 1]))
    world = room.corners_world[idx]
    if motion is not None and cal.readout_s > 0 and len(ids):
        world = rolling_shutter_points(world, corners, cal, *motion)
    return CameraObservation(ids, xn, world, R_bc, t_bc, focal)


def rolling_shutter_points(
    world: np.ndarray,
    pixels: np.ndarray,
    cal: CameraCalibration,
    R_wb: np.ndarray,
    p_wb: np.ndarray,
    omega: np.ndarray,
    vel: np.ndarray,
) -> np.ndarray:
    """World points (..., 3) moved by the bundle's motion over each pixel's readout delay
    (annotator.core.rolling_shutter.moved_points with this camera's height and readout)."""
    return moved_points(world, pixels, cal.height, cal.readout_s, R_wb, p_wb, omega, vel)


def _subset(obs: CameraObservation, keep: np.ndarray) -> CameraObservation:
    return CameraObservation(
        obs.ids[keep], obs.xn[keep], obs.world[keep], obs.R_bc, obs.t_bc, obs.focal
    )


_EYE = np.eye(3)


def camera_pose_candidates(
    obs: CameraObservation, room: MarkerRoom
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses (R_world_camera, centre) from one camera: one for several markers, two for one."""
    n = len(obs.ids)
    if n == 0:
        return []
    if n == 1:
        # A lone square has two IPPE solutions; keep both, the neighbours decide later.
        k = room.index(obs.ids)[0]
        out = []
        for R_cm, t_cm, _ in ippe_square(obs.xn[0], room.length, _EYE, None):
            R_mc, c_m = R_cm.T, -R_cm.T @ t_cm  # camera in the marker frame
            out.append(
                (
                    room.R_world_marker[k] @ R_mc,
                    room.R_world_marker[k] @ c_m + room.t_world_marker[k],
                )
            )
        return out
    ok, rv, tv = cv2.solvePnP(
        obs.world.reshape(-1, 3), obs.xn.reshape(-1, 1, 2), _EYE, None, flags=cv2.SOLVEPNP_SQPNP
    )
    if not ok:
        return []
    rv, tv = cv2.solvePnPRefineLM(
        obs.world.reshape(-1, 3), obs.xn.reshape(-1, 1, 2), _EYE, None, rv, tv
    )
    return [pnp_to_camera(rv, tv)]


@dataclass(frozen=True, eq=False)
class _Corners:
    """Every camera's corners of one solve, stacked once for all of its Gauss-Newton steps."""

    world: np.ndarray  # (m, 3)
    xn: np.ndarray  # (m, 2)
    R_bc: np.ndarray  # (m, 3, 3): the rig rotation of each corner's camera
    t_bc: np.ndarray  # (m, 3)
    focal: np.ndarray  # (m, 1)
    per_camera: tuple[int, ...]  # corners of each observation in turn

    @classmethod
    def of(cls, obs: list[CameraObservation]) -> _Corners:
        counts = tuple(4 * len(o.ids) for o in obs)
        if not sum(counts):
            z = np.zeros((0, 3))
            return cls(z, np.zeros((0, 2)), np.zeros((0, 3, 3)), z, np.zeros((0, 1)), counts)
        use = [o for o in obs if len(o.ids)]
        n = [4 * len(o.ids) for o in use]
        return cls(
            np.concatenate([o.world.reshape(-1, 3) for o in use]),
            np.concatenate([o.xn.reshape(-1, 2) for o in use]),
            np.repeat(np.stack([o.R_bc for o in use]), n, axis=0),
            np.repeat(np.stack([o.t_bc for o in use]), n, axis=0),
            np.repeat([o.focal for o in use], n)[:, None],
            counts,
        )


def _residuals(
    R_wb: np.ndarray, t_wb: np.ndarray, c: _Corners, jacobian: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Stacked pixel residuals (m, 2), Jacobian (m, 2, 6) and depth (m,) for all corners."""
    if not len(c.world):
        return np.zeros((0, 2)), None, np.zeros(0)
    d = c.world - t_wb
    Y = d @ R_wb  # rows: R_wb^T d, the corner in the bundle frame
    Xc = ((Y - c.t_bc)[:, None, :] @ c.R_bc)[:, 0]  # rows: R_bc^T (Y - t_bc)
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    proj = Xc[:, :2] / zs[:, None]
    r = c.focal * (proj - c.xn)
    if not jacobian:
        return r, None, z
    m = len(z)
    dp = np.zeros((m, 2, 3))
    dp[:, 0, 0] = 1 / zs
    dp[:, 1, 1] = 1 / zs
    dp[:, :, 2] = -proj / zs[:, None]
    # d(pixels)/d(world-frame point offset): focal dp R_bc^T R_wb^T, per corner
    a = c.focal[:, :, None] * dp @ (c.R_bc.transpose(0, 2, 1) @ R_wb.T)
    # R_wb = exp(w) R_wb0 moves the corner in the bundle frame by R_wb^T (d x w), so the
    # rotation columns are a . (d x w) = (a x d) . w for each Jacobian row a.
    dd = d[:, None, :]
    axd = np.stack(
        [
            a[..., 1] * dd[..., 2] - a[..., 2] * dd[..., 1],
            a[..., 2] * dd[..., 0] - a[..., 0] * dd[..., 2],
            a[..., 0] * dd[..., 1] - a[..., 1] * dd[..., 0],
        ],
        axis=-1,
    )
    return r, np.concatenate([axd, -a], axis=2), z


def refine_bundle_pose(
    obs: list[CameraObservation], R_wb: np.ndarray, t_wb: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Robust Gauss-Newton from a start pose; returns (R, t, cov 6x6, rms px) or None if degenerate."""
    R, t = R_wb.copy(), np.asarray(t_wb, dtype=float).copy()
    k = settings.huber_px
    corners = _Corners.of(obs)
    for _ in range(settings.iterations):
        r, J, _ = _residuals(R, t, corners, True)
        if J is None or len(r) < 3:
            return None
        norm = np.linalg.norm(r, axis=1)
        w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-12))
        Jf = J.reshape(-1, 6)
        wf = np.repeat(w, 2)
        H = Jf.T @ (Jf * wf[:, None])
        g = Jf.T @ (wf * r.ravel())
        try:
            step = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            return None
        R = Rotation.from_rotvec(step[:3]).as_matrix() @ R
        t = t + step[3:]
        if np.abs(step).max() < 1e-7:  # 0.1 urad / 0.1 um: far below what the corners resolve
            break
    r, J, depth = _residuals(R, t, corners, True)
    if J is None or np.any(depth <= 0):
        return None  # a corner behind its camera: not a physical solution
    norm = np.linalg.norm(r, axis=1)
    w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-12))
    Jf, wf = J.reshape(-1, 6), np.repeat(w, 2)
    dof = max(r.size - 6, 1)
    sigma2 = max(float(np.sum(wf * r.ravel() ** 2)) / dof, settings.min_sigma_px**2)
    try:
        cov = sigma2 * np.linalg.inv(Jf.T @ (Jf * wf[:, None]))
    except np.linalg.LinAlgError:
        return None
    # Re-orthonormalise should accumulated steps (or the start) leave SO(3).
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-12:
        R = Rotation.from_matrix(R).as_matrix()
    return R, t, cov, float(np.sqrt(np.mean(norm**2)))


def _marker_rms(R: np.ndarray, t: np.ndarray, obs: list[CameraObservation]) -> list[np.ndarray]:
    """Each observation's markers' RMS pixel residual at the pose (R, t)."""
    corners = _Corners.of(obs)
    r, _, _ = _residuals(R, t, corners, False)
    rms = np.sqrt(np.mean(np.sum(r.reshape(-1, 4, 2) ** 2, axis=2), axis=1))
    return np.split(rms, np.cumsum([n // 4 for n in corners.per_camera])[:-1])


def _starts(
    obs: list[CameraObservation], room: MarkerRoom, prior: tuple[np.ndarray, np.ndarray] | None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Start poses: per-camera PnP through the rig, best-observed camera first, then any prior."""
    order = sorted(range(len(obs)), key=lambda i: -len(obs[i].ids))
    starts = []
    for i in order:
        o = obs[i]
        for R_wc, c_w in camera_pose_candidates(o, room):
            starts.append(camera_to_bundle(R_wc, c_w, o.R_bc, o.t_bc))
        if starts and len(o.ids) > 1:
            break
    if prior is not None:
        starts.append(prior)
    return starts


def solve_bundle_pose(
    obs: list[CameraObservation],
    room: MarkerRoom,
    settings: SolverSettings | None = None,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    prior_first: bool = False,
) -> BundlePose | None:
    """Joint robust pose of the bundle from all cameras' corners; None when nothing fits.

    Markers whose own residual is far above the rest are dropped and the pose re-solved. With a
    single marker in view the two mirror solutions are both returned (``alternatives``).
    ``prior`` is a fallback start; with ``prior_first`` it is tried before any PnP start.
    """
    settings = settings or SolverSettings()
    obs = [o for o in obs if len(o.ids)]
    if not obs:
        return None
    for _ in range(3):  # solve, gate markers, re-solve
        sols = []
        n_now = sum(len(o.ids) for o in obs)
        if prior_first and prior is not None and n_now > 1:
            # A trusted prior (the smoothed first pass) needs no PnP start when it already fits.
            fit = refine_bundle_pose(obs, prior[0], prior[1], settings)
            if fit is not None and fit[3] < settings.huber_px:
                sols.append(fit)
        if not sols:
            starts = _starts(obs, room, None)
            if prior is not None:
                starts.append(prior)
            for i, (R0, t0) in enumerate(starts):
                if (
                    prior is not None
                    and i == len(starts) - 1
                    and sols
                    and min(s[3] for s in sols) < settings.huber_px
                ):
                    break  # the prior is only a fallback for when PnP found nothing that fits
                fit = refine_bundle_pose(obs, R0, t0, settings)
                if fit is not None:
                    sols.append(fit)
        if not sols:
            return None
        sols.sort(key=lambda s: s[3])
        R, t, cov, rms = sols[0]
        per_marker = _marker_rms(R, t, obs)
        allr = np.concatenate(per_marker)
        if len(allr) < 2:
            break
        limit = max(settings.marker_gate_px, 4.0 * float(np.median(allr)))
        if np.all(allr <= limit):
            break
        worst = max(float(m.max()) for m in per_marker if len(m))
        log.debug("dropping marker(s) with residual %.2f px > %.2f px", worst, limit)
        # Drop only the single worst marker per round: one bad corner set can spoil all the others.
        obs = [_subset(o, m < worst) if len(m) else o for o, m in zip(obs, per_marker, strict=True)]
        obs = [o for o in obs if len(o.ids)]
    n = sum(len(o.ids) for o in obs)
    alternatives: tuple[BundlePose, ...] = ()
    if n == 1:
        k = settings.single_marker_cov_scale
        cov = cov * k
        distinct = [
            s
            for s in sols[1:]
            if np.linalg.norm(Rotation.from_matrix(s[0].T @ R).as_rotvec()) > 1e-3
        ]
        alternatives = tuple(BundlePose(s[0], s[1], s[2] * k, s[3], 1) for s in distinct[:1])
    return BundlePose(R, t, cov, rms, n, alternatives)
