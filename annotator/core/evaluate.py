"""Trajectory accuracy metrics on arrays: error against a reference trajectory (no alignment),
and the paper's deviation from a planned polyline with along-track "drag" at segment ends."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.trajectory import Trajectory


@dataclass(frozen=True)
class ErrorStats:
    n: int
    median: float
    mean: float
    p75: float
    p95: float
    max: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def error_stats(errors: np.ndarray) -> ErrorStats:
    """Summary of the finite values (NaN = not compared); all NaN -> n 0 and NaN figures."""
    e = np.asarray(errors, float)
    e = e[np.isfinite(e)]
    if not len(e):
        return ErrorStats(0, *(5 * [float("nan")]))
    p50, p75, p95 = np.percentile(e, [50, 75, 95])
    return ErrorStats(
        int(len(e)), float(p50), float(e.mean()), float(p75), float(p95), float(e.max())
    )


def rotation_angles_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """Angle of the rotation taking each R_a to R_b, degrees; NaN where either is missing."""
    out = np.full(len(rot_a), np.nan)
    ok = np.isfinite(rot_a).all((1, 2)) & np.isfinite(rot_b).all((1, 2))
    if ok.any():
        rel = Rotation.from_matrix(rot_a[ok]).inv() * Rotation.from_matrix(rot_b[ok])
        out[ok] = np.degrees(rel.magnitude())
    return out


@dataclass(frozen=True)
class TruthComparison:
    t: np.ndarray
    position_error: np.ndarray  # (N,) metres, NaN where not compared
    rotation_error_deg: np.ndarray  # (N,)
    missing: int  # estimate rows without a pose
    outside: int  # estimate poses with no reference at their time

    def report(self) -> dict[str, object]:
        return {
            "rows": len(self.t),
            "compared": int(np.isfinite(self.position_error).sum()),
            "missing_poses": self.missing,
            "outside_reference": self.outside,
            "position_error_m": error_stats(self.position_error).as_dict(),
            "rotation_error_deg": error_stats(self.rotation_error_deg).as_dict(),
        }


def compare_to_truth(
    t: np.ndarray,
    pos: np.ndarray,
    rot: np.ndarray,
    ref_t: np.ndarray,
    ref_pos: np.ndarray,
    ref_rot: np.ndarray,
) -> TruthComparison:
    """Per-row errors of an estimate against a reference interpolated to its times; no alignment."""
    has_pose = np.isfinite(pos).all(1) & np.isfinite(rot).all((1, 2))
    ref_p, ref_r, ok = Trajectory(np.asarray(ref_t, float), ref_pos, ref_rot).interpolate(t)
    use = has_pose & ok
    perr = np.full(len(t), np.nan)
    perr[use] = np.linalg.norm(pos[use] - ref_p[use], axis=1)
    rerr = np.full(len(t), np.nan)
    rerr[use] = rotation_angles_deg(ref_r[use], rot[use])
    return TruthComparison(
        np.asarray(t, float), perr, rerr, int((~has_pose).sum()), int((has_pose & ~ok).sum())
    )


def _segments(waypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(waypoints, float)[:-1]
    d = np.diff(np.asarray(waypoints, float), axis=0)
    length = np.linalg.norm(d, axis=1)
    return a, d, length


def nearest_segment(
    xy: np.ndarray, waypoints: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point: distance to the polyline, index of the nearest segment, and the
    along-track coordinate on that segment's line (metres from its start, not clipped)."""
    a, d, length = _segments(waypoints)
    rel = xy[:, None, :] - a[None, :, :]  # (N, S, 2)
    along = np.einsum("nsk,sk->ns", rel, d) / length
    clipped = np.clip(along, 0.0, length)
    closest = a[None] + clipped[..., None] * (d / length[:, None])[None]
    dist = np.linalg.norm(xy[:, None, :] - closest, axis=2)
    seg = np.argmin(dist, axis=1)
    rows = np.arange(len(xy))
    return dist[rows, seg], seg, along[rows, seg]


@dataclass(frozen=True)
class PathComparison:
    deviation: np.ndarray  # (N,) horizontal distance to the planned polyline, metres; NaN gaps
    segment: np.ndarray  # (N,) nearest segment index, -1 for gaps
    drag: (
        np.ndarray
    )  # (S,) per segment end: planned end minus furthest progress along it; NaN if never on it

    def report(self) -> dict[str, object]:
        finite = self.drag[np.isfinite(self.drag)]
        return {
            "rows": len(self.deviation),
            "compared": int(np.isfinite(self.deviation).sum()),
            "deviation_m": error_stats(self.deviation).as_dict(),
            "drag_m": [None if not np.isfinite(v) else float(v) for v in self.drag],
            "drag_mean_abs_m": float(np.abs(finite).mean()) if len(finite) else None,
        }


def compare_to_path(pos: np.ndarray, waypoints: np.ndarray) -> PathComparison:
    """The paper's path metrics on the horizontal plane.

    Deviation: distance of each pose to the planned polyline. Drag at the end of segment k:
    its length minus the furthest along-track progress of the poses nearest to it, so a
    trajectory turning early (lagging, cutting the corner) gives a positive value and an
    overshoot a negative one.
    """
    wp = np.asarray(waypoints, float)
    xy = np.asarray(pos, float)[:, :2]
    ok = np.isfinite(xy).all(1)
    dev = np.full(len(xy), np.nan)
    seg = np.full(len(xy), -1)
    _, _, length = _segments(wp)
    drag = np.full(len(length), np.nan)
    if ok.any():
        dist, s_idx, along = nearest_segment(xy[ok], wp)
        dev[ok], seg[ok] = dist, s_idx
        for k in range(len(length)):
            on = s_idx == k
            if on.any():
                drag[k] = length[k] - along[on].max()
    return PathComparison(dev, seg, drag)
