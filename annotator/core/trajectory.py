"""The one trajectory type of the annotator, and the one way to read a pose between its rows.

A trajectory is a time series of bundle poses: wall-clock seconds, positions (N, 3) in metres and
R_world_bundle (N, 3, 3), plus optional per-row quality arrays (``sigma_m``, ``markers``,
``rms_px``, a covariance, ...). A row whose position or rotation holds a NaN is a gap. Tracking
(measurements and its output), labelling (readings between poses) and evaluation (a reference at
the estimate's times) all use it, and all interpolate with ``bracket`` + ``blend``: positions
linearly, rotations along the geodesic between the two rows around each time (slerp).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True, eq=False)
class Trajectory:
    t: np.ndarray  # (N,) Unix seconds, sorted
    position: np.ndarray  # (N, 3) metres; NaN where no pose
    rotation: np.ndarray  # (N, 3, 3) R_world_bundle; NaN where no pose
    quality: dict[str, np.ndarray] = field(default_factory=dict)  # extra per-row arrays

    def __len__(self) -> int:
        return len(self.t)

    @property
    def valid(self) -> np.ndarray:
        """Rows with a pose: finite time, position and rotation."""
        return (
            np.isfinite(self.t)
            & np.isfinite(self.position).all(1)
            & np.isfinite(self.rotation.reshape(-1, 9)).all(1)
        )

    @classmethod
    def empty(cls) -> Trajectory:
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))

    @classmethod
    def from_rotation(
        cls,
        t: np.ndarray,
        position: np.ndarray,
        rotation: Rotation,
        quality: dict[str, np.ndarray] | None = None,
    ) -> Trajectory:
        """From a scipy Rotation; the rows with a NaN position are gaps (their rotation NaN too)."""
        mats = np.array(rotation.as_matrix(), dtype=float).reshape(-1, 3, 3)
        position = np.asarray(position, dtype=float)
        mats[~np.isfinite(position).all(1)] = np.nan
        return cls(np.asarray(t, dtype=float), position, mats, dict(quality or {}))

    def select(self, rows: np.ndarray) -> Trajectory:
        """The rows ``rows`` (boolean mask or indices), quality arrays included."""
        return Trajectory(
            self.t[rows],
            self.position[rows],
            self.rotation[rows],
            {k: np.asarray(v)[rows] for k, v in self.quality.items()},
        )

    def compact(self) -> Trajectory:
        """Only the rows with a pose, in time order; of rows with the same time the first is kept
        (two cameras' frames fused at one time would make the interpolation between them ill-posed)."""
        idx = np.flatnonzero(self.valid)
        idx = idx[np.argsort(self.t[idx], kind="stable")]
        t = self.t[idx]
        keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, dtype=bool)
        return self.select(idx[keep])

    def bridged(self, max_gap_s: float) -> Trajectory:
        """The same rows with every gap no longer than ``max_gap_s`` (between the poses around it)
        filled by ``blend`` between those two poses; longer gaps and the ends stay gaps. A guess
        of the motion, for where only a rough pose is needed (a start, a row's time)."""
        ok = self.valid
        idx = np.flatnonzero(ok)
        if idx.size < 2 or ok.all():
            return self
        pos, rot = self.position.copy(), self.rotation.copy()
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            if b - a < 2 or self.t[b] - self.t[a] > max_gap_s:
                continue
            rows = np.arange(a + 1, b)
            w = (self.t[rows] - self.t[a]) / (self.t[b] - self.t[a])
            pos[rows], rot[rows] = blend(
                self.position, self.rotation, np.full(rows.size, a), np.full(rows.size, b), w
            )
        return Trajectory(self.t, pos, rot, dict(self.quality))

    def at_point(self, offset: np.ndarray) -> Trajectory:
        """The same motion followed at ``offset`` (metres, bundle frame) instead of the bundle's
        origin: position + R_world_bundle @ offset per row, rotations and quality unchanged (a
        lever of a few centimetres adds well under a millimetre of rotation uncertainty)."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        if not offset.any():
            return self
        moved = self.position + np.einsum("nij,j->ni", self.rotation, offset)
        return Trajectory(self.t, moved, self.rotation, dict(self.quality))

    def interpolate(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses at ``times``: (positions (M, 3), rotations (M, 3, 3), ok (M,)). A time outside the
        trajectory's span, or whose bracketing rows are not both poses, is not ok and gets NaN:
        a gap is never bridged and the ends are never extrapolated."""
        times = np.asarray(times, dtype=float)
        m = len(times)
        pos = np.full((m, 3), np.nan)
        rot = np.full((m, 3, 3), np.nan)
        if len(self.t) < 2:
            return pos, rot, np.zeros(m, dtype=bool)
        lo, hi, w = bracket(self.t, times)
        valid = self.valid
        ok = (
            np.isfinite(times)
            & (times >= self.t[0])
            & (times <= self.t[-1])
            & valid[lo]
            & valid[hi]
        )
        if ok.any():
            pos[ok], rot[ok] = blend(self.position, self.rotation, lo[ok], hi[ok], w[ok])
        return pos, rot, ok


def bracket(t_grid: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each time, the rows around it in the sorted ``t_grid``: (lo, hi, w) with hi = lo + 1
    (clipped into the grid, so times outside it get the first or last pair) and w the weight of
    row hi (0 at lo, 1 at hi). A grid of one row gives lo = hi = 0, w = 0."""
    t_grid = np.asarray(t_grid, dtype=float)
    times = np.asarray(times, dtype=float)
    n = t_grid.size
    hi = np.clip(np.searchsorted(t_grid, times, side="right"), 1, max(n - 1, 1))
    lo = hi - 1
    if n == 1:
        lo = hi = np.zeros(times.size, dtype=int)
    span = t_grid[hi] - t_grid[lo]
    w = np.divide(times - t_grid[lo], span, out=np.zeros_like(times), where=span > 0)
    return lo, hi, w


def blend(
    position: np.ndarray, rotation: np.ndarray, lo: np.ndarray, hi: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses between rows lo and hi at weight w: linear in position, slerp in rotation.
    Rotations are projected to the nearest rotation first (published references are not always
    orthonormal)."""
    pos = position[lo] + (position[hi] - position[lo]) * w[:, None]
    ra, rb = Rotation.from_matrix(rotation[lo]), Rotation.from_matrix(rotation[hi])
    rot = (ra * Rotation.from_rotvec((ra.inv() * rb).as_rotvec() * w[:, None])).as_matrix()
    return pos, rot
