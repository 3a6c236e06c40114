"""Method ``paper``: the per-marker averaging of Daniş et al. (PMC 2022), kept for comparison.

Each marker gives its own IPPE_SQUARE pose (t_wc = t_wm - R_wm R_cm^T t_cm); poses of both
cameras over F frames form a batch; the C poses from the closest markers are kept; the pose
farthest from the mean is dropped until U remain; their mean feeds a random-walk Kalman filter
(A = H = I, process noise 0.01 I, measurement noise q I). One difference on purpose: the batch
rotation is a proper rotation mean, not nine independently filtered numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.experiment import RigCamera
from annotator.vision.detection import Detections
from annotator.vision.geometry import MarkerRoom, camera_to_bundle, ippe_square


@dataclass(frozen=True, slots=True)
class PaperSettings:
    frames: int = 15  # F: frames per batch (per camera)
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
        sols = ippe_square(corners, room.length, cal.camera_matrix, cal.dist_coeffs) if k >= 0 else []
        if not sols:
            continue
        R_cm, t_cm, _ = sols[0]  # the paper keeps the better-fitting of the two
        R_wm, t_wm = room.R_world_marker[k], room.t_world_marker[k]
        # t_wc = t_wm - R_wm R_cm^T t_cm ; R_wc = R_wm R_cm^T
        R_wc = R_wm @ R_cm.T
        R_wb, t_wb = camera_to_bundle(R_wc, t_wm - R_wc @ t_cm, cam.R_bundle_camera, cam.t_bundle_camera)
        pos.append(t_wb)
        rot.append(R_wb)
        dist.append(float(np.linalg.norm(t_cm)))
    if not pos:
        return MarkerPoses(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
    return MarkerPoses(np.array(pos), np.array(rot), np.array(dist))


def select_poses(pos: np.ndarray, distance: np.ndarray, close: int, keep: int) -> np.ndarray:
    """Indices kept: the ``close`` nearest-marker poses, then greedily the ``keep`` most central."""
    idx = np.argsort(distance, kind="stable")[:close]
    idx = list(idx)
    while len(idx) > keep:
        p = pos[idx]
        worst = int(np.argmax(np.linalg.norm(p - p.mean(0), axis=1)))
        idx.pop(worst)
    return np.array(idx, dtype=int)


def paper_track(t: np.ndarray, poses: list[MarkerPoses], frame_interval: float,
                settings: PaperSettings | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Batch times (B,), filtered positions (B, 3), rotations (B, 3, 3) and poses used (B,).

    ``t`` (N,) are the frame times of all cameras with their per-frame marker poses. A batch with
    no pose is a NaN row.
    """
    s = settings or PaperSettings()
    order = np.argsort(t, kind="stable")
    t = np.asarray(t, float)[order]
    poses = [poses[i] for i in order]
    if len(t) == 0:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    span = s.frames * frame_interval
    batch = np.floor((t - t[0]) / span + 1e-9).astype(int)
    times, zs, rots, used = [], [], [], []
    x, P = None, None
    for b in range(batch.max() + 1):
        sel = np.flatnonzero(batch == b)
        if len(sel) == 0:
            continue
        times.append(float(t[sel].mean()))
        pos = np.concatenate([poses[i].position for i in sel])
        if len(pos) == 0:
            zs.append(np.full(3, np.nan))
            rots.append(np.full((3, 3), np.nan))
            used.append(0)
            continue
        rot = np.concatenate([poses[i].rotation for i in sel])
        dist = np.concatenate([poses[i].distance for i in sel])
        keep = select_poses(pos, dist, s.close, s.keep)
        z = pos[keep].mean(0)
        if x is None:
            x, P = z.copy(), s.q * np.eye(3)
        else:
            P = P + s.process * np.eye(3)  # predict: A = I
            K = P @ np.linalg.inv(P + s.q * np.eye(3))  # update: H = I
            x = x + K @ (z - x)
            P = (np.eye(3) - K) @ P
        zs.append(x.copy())
        rots.append(Rotation.from_matrix(rot[keep]).mean().as_matrix())
        used.append(len(keep))
    return np.array(times), np.array(zs), np.array(rots), np.array(used)
