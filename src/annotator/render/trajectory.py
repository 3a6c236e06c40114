"""A default ground-truth trajectory for renders: a rounded-rectangle loop through the tetam room.

Heading follows the path; yaw, pitch and roll wobble a little, the height drifts between
about 1.3 and 1.8 m. Callable on an array of wall times like any `pose_at`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class LoopTrajectory:
    """Walk a rounded rectangle counter-clockwise at constant speed, starting mid bottom edge."""

    t0: float = 1_700_000_000.0
    speed: float = 0.4  # m/s
    x_range: tuple[float, float] = (7.7, 11.8)
    y_range: tuple[float, float] = (7.0, 10.9)
    corner_radius: float = 1.2
    height: float = 1.55
    height_swing: float = 0.25
    wobble_deg: tuple[float, float, float] = (4.0, 3.0, 2.5)  # yaw, pitch, roll amplitudes

    def _path(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Dense samples (cumulative length, xy, heading) of the closed path."""
        (x0, x1), (y0, y1), r = self.x_range, self.y_range, self.corner_radius
        pts, heads = [], []
        segments = [  # straight start/end, arc centre, arc start angle
            ((x0 + (x1 - x0) / 2, y0), (x1 - r, y0), (x1 - r, y0 + r), -np.pi / 2),
            ((x1, y0 + r), (x1, y1 - r), (x1 - r, y1 - r), 0.0),
            ((x1 - r, y1), (x0 + r, y1), (x0 + r, y1 - r), np.pi / 2),
            ((x0, y1 - r), (x0, y0 + r), (x0 + r, y0 + r), np.pi),
            ((x0 + r, y0), (x0 + (x1 - x0) / 2, y0), None, 0.0),
        ]
        for a, b, centre, ang in segments:
            a, b = np.array(a), np.array(b)
            n = max(2, int(np.linalg.norm(b - a) / 0.01))
            s = np.linspace(0, 1, n, endpoint=False)[:, None]
            pts.append(a + s * (b - a))
            d = b - a
            heads.append(np.full(n, np.arctan2(d[1], d[0])))
            if centre is not None:
                th = ang + np.linspace(0, np.pi / 2, int(r * np.pi / 2 / 0.01), endpoint=False)
                pts.append(np.column_stack([centre[0] + r * np.cos(th), centre[1] + r * np.sin(th)]))
                heads.append(th + np.pi / 2)
        xy = np.vstack(pts + [pts[0][:1]])
        heading = np.unwrap(np.concatenate(heads + [heads[0][:1] + 2 * np.pi]))
        length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        return length, xy, heading

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        t = np.atleast_1d(np.asarray(t, float))
        length, xy, heading = self._path()
        perimeter = length[-1]
        s = np.mod(self.speed * (t - self.t0), perimeter)
        laps = np.floor(self.speed * (t - self.t0) / perimeter)
        x = np.interp(s, length, xy[:, 0])
        y = np.interp(s, length, xy[:, 1])
        tau = t - self.t0
        z = self.height + self.height_swing * np.sin(2 * np.pi * tau / 11.0)
        wy, wp, wr = np.radians(self.wobble_deg)
        yaw = np.interp(s, length, heading) + 2 * np.pi * laps + wy * np.sin(2 * np.pi * 0.17 * tau)
        pitch = wp * np.sin(2 * np.pi * 0.23 * tau + 0.7)
        roll = wr * np.sin(2 * np.pi * 0.31 * tau + 1.9)
        # Intrinsic z-y'-x'': R_world_bundle = Rz(yaw) Ry(pitch) Rx(roll).
        rot = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]))
        return np.column_stack([x, y, z]), rot
