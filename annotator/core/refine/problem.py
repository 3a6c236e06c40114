"""Building a self-calibration problem from the first pass's detections at keyframes."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.priors import Priors
from annotator.core.refine.model import CameraParams, Observations, Problem

if TYPE_CHECKING:
    from annotator.core.experiment import CameraCalibration

log = logging.getLogger(__name__)

# --- building a problem from detections -------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FrameView:
    """One camera frame of a keyframe: its detections and the bundle's motion at its time."""

    camera: int
    ids: np.ndarray  # (n,)
    corners: np.ndarray  # (n, 4, 2) distorted pixels
    R_D: np.ndarray = field(
        default_factory=lambda: np.eye(3)
    )  # bundle at this frame, from the keyframe's
    t_D: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))  # keyframe-bundle frame, rad/s
    vel: np.ndarray = field(default_factory=lambda: np.zeros(3))  # keyframe-bundle frame, m/s
    weight: float = 1.0


@dataclass(frozen=True, eq=False)
class Keyframe:
    R_wb: np.ndarray  # start pose (first pass)
    t_wb: np.ndarray
    views: list[FrameView]


def _calibration(cam: CameraParams) -> CameraCalibration:
    from annotator.core.experiment import CameraCalibration

    return CameraCalibration(
        cam.K, np.asarray(cam.dist, float), 0, cam.height, "", cam.model, cam.readout_s
    )


def _medoid_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    rots = Rotation.from_matrix(np.array(Rs))
    if len(Rs) == 1:
        return Rs[0]
    sample = rots if len(Rs) <= 60 else rots[np.linspace(0, len(Rs) - 1, 60).astype(int)]
    cost = [np.sum((sample.inv() * r).magnitude()) for r in sample]
    best = sample[int(np.argmin(cost))]
    near = rots[(best.inv() * rots).magnitude() < np.radians(5)]
    return near.mean().as_matrix()


def _camera_in_world(
    kf: Keyframe, v: FrameView, cam: CameraParams
) -> tuple[np.ndarray, np.ndarray]:
    """The view's camera in the world at the frame time: (R_wc, centre)."""
    R_b, t_b = kf.R_wb @ v.R_D, kf.R_wb @ v.t_D + kf.t_wb  # bundle at the frame time
    return R_b @ cam.R_bc, R_b @ cam.t_bc + t_b


def marker_views(
    keyframes: list[Keyframe], cameras: list[CameraParams], length: float
) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Each marker's world pose (R, centre) as each keyframe view sees it (IPPE of its square)."""
    from annotator.vision.geometry import ippe_square
    from annotator.vision.lens import undistort_points

    cals = [_calibration(c) for c in cameras]
    out: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for kf in keyframes:
        for v in kf.views:
            if not len(v.ids):
                continue
            R_wc, c_w = _camera_in_world(kf, v, cameras[v.camera])
            xn = undistort_points(cals[v.camera], v.corners)
            for mid, pts in zip(v.ids, xn, strict=True):
                sols = ippe_square(pts, length, np.eye(3), None)
                if not sols:
                    continue
                R_cm, t_cm, _ = sols[0]
                if len(sols) > 1 and sols[1][2] < 2 * sols[0][2] + 1e-4:
                    continue  # ambiguous square: no vote
                out.setdefault(int(mid), []).append((R_wc @ R_cm, R_wc @ t_cm + c_w))
    return out


def _seeable(
    kf: Keyframe, v: FrameView, cam: CameraParams, R_m: np.ndarray, t_m: np.ndarray
) -> np.ndarray:
    """(n,) bool: markers at poses (R_m, t_m) in front of the view's camera and facing it.

    A detection of a surveyed marker that fails this is a misread id, not a survey error: a
    survey a few centimetres off does not put a marker behind the camera or turn its back."""
    R_wc, c_w = _camera_in_world(kf, v, cam)
    to_cam = c_w - t_m  # (n, 3)
    facing = np.einsum("nk,nk->n", R_m[:, :, 2], to_cam) > 0  # marker z: out of its face
    depth = (t_m - c_w) @ R_wc[:, 2]
    return np.asarray(facing & (depth > 0))


def build_problem(
    survey: dict[int, tuple[np.ndarray, np.ndarray]],
    length: float,
    cameras: list[CameraParams],
    keyframes: list[Keyframe],
    priors: Priors,
    moved_m: float = 0.05,
    initial: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    length_sigma_rel: float = 0.0,
) -> tuple[Problem, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """The problem over every marker seen in the keyframes (surveyed or not) and the start values.

    ``survey`` maps marker id -> (R_world_marker, centre). Markers not in it, or marked unknown in
    the priors, are free; they start from the median of their views. A surveyed marker whose views
    put it more than ``moved_m`` (and 5 sigma) away from the survey starts from the views too.
    ``initial`` gives start poses for free markers (an earlier refinement's) instead.
    ``length_sigma_rel`` > 0 lets the solve estimate the markers' printed size (prior 1 +- it).
    Returns the problem and the start poses that differ from the survey.
    """
    views = marker_views(keyframes, cameras, length)
    starts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for mid, vs in views.items():
        pos = np.median(np.array([c for _, c in vs]), axis=0)
        R = _medoid_rotation([r for r, _ in vs])
        starts[mid] = (R, pos)
    seen_ids = {int(i) for kf in keyframes for v in kf.views for i in v.ids}
    for mid, pose in (initial or {}).items():
        if mid not in survey and mid in seen_ids:
            starts[mid] = pose
    ids = sorted(set(survey) | set(starts))
    R_m, t_m, sig, start_moved, kept = [], [], [], {}, []
    for mid in ids:
        p = priors.marker(mid)
        known = mid in survey and p.known
        if known:
            R0, c0 = survey[mid]
            kept.append(mid)
            R_m.append(R0)
            t_m.append(c0)
            sig.append((math.radians(p.sigma_deg), p.sigma_m))
            if mid in starts and len(views[mid]) >= 5:
                centres = np.array([c for _, c in views[mid]])
                spread = float(np.linalg.norm(np.median(np.abs(centres - starts[mid][1]), axis=0)))
                d = np.linalg.norm(starts[mid][1] - c0)
                if d > max(moved_m, 5 * p.sigma_m * math.sqrt(3), 4 * spread):
                    start_moved[mid] = starts[mid]
        else:
            if mid not in starts:
                continue
            kept.append(mid)
            R_m.append(starts[mid][0])
            t_m.append(starts[mid][1])
            sig.append((math.inf, math.inf))
    ids = kept
    index = {mid: i for i, mid in enumerate(ids)}
    cols: dict[str, list[np.ndarray]] = {
        k: [] for k in ("kf", "cam", "mk", "corner", "uv", "R_D", "t_D", "om", "vel", "w")
    }
    R_arr, t_arr = np.array(R_m).reshape(-1, 3, 3), np.array(t_m, float).reshape(-1, 3)
    dropped = 0
    for k, kf in enumerate(keyframes):
        for v in kf.views:
            keep = np.array([int(i) in index for i in v.ids], bool)
            rows = np.array([index.get(int(i), -1) for i in v.ids], int)
            surveyed = keep & np.array(
                [int(i) in survey and int(i) not in start_moved for i in v.ids], bool
            )
            seeable = _seeable(kf, v, cameras[v.camera], R_arr[rows], t_arr[rows])
            dropped += int(np.count_nonzero(surveyed & ~seeable))
            keep &= ~surveyed | seeable
            n = int(keep.sum())
            if not n:
                continue
            mk = np.array([index[int(i)] for i in v.ids[keep]])
            cols["kf"].append(np.full(4 * n, k))
            cols["cam"].append(np.full(4 * n, v.camera))
            cols["mk"].append(np.repeat(mk, 4))
            cols["corner"].append(np.tile(np.arange(4), n))
            cols["uv"].append(v.corners[keep].reshape(-1, 2))
            cols["R_D"].append(np.repeat(v.R_D[None], 4 * n, 0))
            cols["t_D"].append(np.repeat(v.t_D[None], 4 * n, 0))
            cols["om"].append(np.repeat(v.omega[None], 4 * n, 0))
            cols["vel"].append(np.repeat(v.vel[None], 4 * n, 0))
            cols["w"].append(np.full(4 * n, v.weight))
    if dropped:
        log.info(
            "refine: %d detections of markers the camera faced away from were dropped", dropped
        )
    if not cols["kf"]:
        raise ValueError("no marker corners in the keyframes")
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    obs = Observations(
        cat["kf"],
        cat["cam"],
        cat["mk"],
        cat["corner"],
        cat["uv"],
        cat["R_D"],
        cat["t_D"],
        cat["om"],
        cat["vel"],
        cat["w"],
    )
    prob = Problem(
        ids,
        np.array(R_m),
        np.array(t_m),
        np.array(sig, float).reshape(-1, 2),
        length,
        cameras,
        np.array([kf.R_wb for kf in keyframes]),
        np.array([kf.t_wb for kf in keyframes], float),
        obs,
        priors,
        length_sigma_rel,
    )
    return prob, start_moved
