"""Method ``paper``: the per-marker averaging of Daniş et al. (PMC 2022), kept for comparison.

Each marker gives its own IPPE_SQUARE pose (t_wc = t_wm - R_wm R_cm^T t_cm). Frames of all
cameras are taken in time order and counted together; every F frames close a batch, stamped
with the time of the frame that closed it (as the authors' program did: F = 15 at two 30 fps
cameras is 0.25 s). The C poses from the closest markers are kept, the pose farthest from the
mean is dropped until U remain, and their mean feeds a random-walk Kalman filter (A = H = I,
P starting as the all-ones matrix, process noise 0.01 I, measurement noise q I).

One difference on purpose: the batch rotation is a proper rotation mean of the kept poses, not
nine matrix entries filtered as independent numbers (which made the published trajectories
contain matrices that are not rotations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import RigCamera
from annotator.vision.detection import Detections
from annotator.vision.geometry import MarkerRoom, camera_to_bundle, ippe_square


@dataclass(frozen=True, slots=True)
class PaperSettings:
    frames: int = 15  # F: frames per batch, counted over all cameras together
    close: int = 20  # C: poses kept from the closest markers
    keep: int = 10  # U: poses left after greedy outlier elimination
    q: float = 0.15  # measurement noise of the Kalman filter
    process: float = 0.01  # process noise of the Kalman filter


@dataclass(frozen=True, eq=False)
class MarkerPoses:
    """Bundle poses implied by each marker seen in one frame, with the marker's distance."""

    position: np.ndarray  # (n, 3)
    rotation: np.ndarray  # (n, 3, 3) R_world_bundle
    distance: np.ndarray  # (n,) camera-marker distance, m


def marker_poses(det: Detections, room: MarkerRoom, cam: RigCamera) -> MarkerPoses:
    """One bundle pose per detected marker, each from that marker alone."""
    cal = cam.calibration
    pos, rot, dist = [], [], []
    for mid, corners in zip(det.ids, det.corners, strict=True):
        k = room.index(np.array([mid]))[0]
        sols = (
            ippe_square(corners, room.length, cal.camera_matrix, cal.dist_coeffs) if k >= 0 else []
        )
        if not sols:
            continue
        R_cm, t_cm, _ = sols[0]  # the paper keeps the better-fitting of the two
        R_wm, t_wm = room.R_world_marker[k], room.t_world_marker[k]
        # t_wc = t_wm - R_wm R_cm^T t_cm ; R_wc = R_wm R_cm^T
        R_wc = R_wm @ R_cm.T
        R_wb, t_wb = camera_to_bundle(
            R_wc, t_wm - R_wc @ t_cm, cam.R_bundle_camera, cam.t_bundle_camera
        )
        pos.append(t_wb)
        rot.append(R_wb)
        dist.append(float(np.linalg.norm(t_cm)))
    if not pos:
        return MarkerPoses(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
    return MarkerPoses(np.array(pos), np.array(rot), np.array(dist))


def select_poses(pos: np.ndarray, distance: np.ndarray, close: int, keep: int) -> np.ndarray:
    """Indices kept: the ``close`` nearest-marker poses, then greedily the ``keep`` most central."""
    idx = [int(i) for i in np.argsort(distance, kind="stable")[:close]]
    while len(idx) > keep:
        p = pos[idx]
        worst = int(np.argmax(np.linalg.norm(p - p.mean(0), axis=1)))
        idx.pop(worst)
    return np.array(idx, dtype=int)


def batch_bounds(n_frames: int, frames: int) -> np.ndarray:
    """(B, 2) [start, stop) of each batch over ``n_frames`` time-ordered frames of all cameras.

    Every ``frames`` frames counted close a batch; a last, incomplete batch is never closed.
    """
    b = n_frames // frames
    starts = np.arange(b) * frames
    return np.column_stack([starts, starts + frames]).astype(int)


def random_walk_filter(z: np.ndarray, q: float, process: float) -> np.ndarray:
    """Filtered states (B, 3) of a random-walk Kalman filter over measurements ``z`` (B, 3).

    A = H = I; the state starts at the first finite measurement with P the all-ones matrix (as
    in the original program); every measurement, the first included, is a predict and an
    update. NaN rows (no measurement) stay NaN and leave the filter untouched.
    """
    out = np.full_like(z, np.nan, dtype=float)
    x, P = None, np.ones((3, 3))
    eye = np.eye(3)
    for b, zb in enumerate(z):
        if not np.isfinite(zb).all():
            continue
        if x is None:
            x = zb.astype(float).copy()
        P = P + process * eye  # predict: A = I
        K = P @ np.linalg.inv(P + q * eye)  # update: H = I
        x = x + K @ (zb - x)
        P = (eye - K) @ P
        out[b] = x
    return out


def paper_track(
    t: np.ndarray, poses: list[MarkerPoses], settings: PaperSettings | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Batch times (B,), filtered positions (B, 3), rotations (B, 3, 3) and poses used (B,).

    ``t`` (N,) are the frame times of all cameras, ``poses`` each frame's marker poses. Frames
    are put in time order, counted regardless of camera or detections, and every
    ``settings.frames`` of them form one batch stamped with its last frame's time. A batch with
    no pose is a NaN row.
    """
    s = settings or PaperSettings()
    if len(t) != len(poses):
        raise ValueError(f"{len(t)} frame times but {len(poses)} frames of marker poses")
    order = np.argsort(np.asarray(t, float), kind="stable")
    t = np.asarray(t, float)[order]
    poses = [poses[i] for i in order]
    bounds = batch_bounds(len(t), s.frames)
    n = len(bounds)
    times = t[bounds[:, 1] - 1] if n else np.zeros(0)
    zs = np.full((n, 3), np.nan)
    rots = np.full((n, 3, 3), np.nan)
    used = np.zeros(n, dtype=int)
    for b, (lo, hi) in enumerate(bounds):
        batch = poses[lo:hi]
        pos = np.concatenate([mp.position for mp in batch])
        if len(pos) == 0:
            continue
        rot = np.concatenate([mp.rotation for mp in batch])
        dist = np.concatenate([mp.distance for mp in batch])
        keep = select_poses(pos, dist, s.close, s.keep)
        zs[b] = pos[keep].mean(0)
        rots[b] = Rotation.from_matrix(rot[keep]).mean().as_matrix()
        used[b] = len(keep)
    return times, random_walk_filter(zs, s.q, s.process), rots, used
