"""Ground-truth trajectories for renders in the tetam room: the default rounded-rectangle loop,
and polylines walked like the paper's planned paths (presets ``rectangle`` and ``zigzag``).

Heading follows the path; yaw, pitch and roll wobble a little, the height drifts between
about 1.3 and 1.8 m. Each is callable on an array of wall times like any `pose_at`.
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
    bounce_m: float = 0.0  # vertical bounce at the step frequency (hand-carried)
    shake_deg: float = 0.0  # pitch and roll jolts at the step frequency (hand-carried)

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
        for start, end, centre, ang in segments:
            a, b = np.array(start), np.array(end)
            n = max(2, int(np.linalg.norm(b - a) / 0.01))
            s = np.linspace(0, 1, n, endpoint=False)[:, None]
            pts.append(a + s * (b - a))
            d = b - a
            heads.append(np.full(n, np.arctan2(d[1], d[0])))
            if centre is not None:
                th = ang + np.linspace(0, np.pi / 2, int(r * np.pi / 2 / 0.01), endpoint=False)
                pts.append(
                    np.column_stack([centre[0] + r * np.cos(th), centre[1] + r * np.sin(th)])
                )
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
        z = _height(tau, self.height, self.height_swing, self.bounce_m)
        rot = _wobbly_rotation(
            np.interp(s, length, heading) + 2 * np.pi * laps, tau, self.wobble_deg, self.shake_deg
        )
        return np.column_stack([x, y, z]), rot


# A person walking takes about 1.8 steps a second: the bounce and jolts of a hand-held bundle.
STEP_HZ = 1.8


def _height(tau: np.ndarray, height: float, swing: float, bounce: float = 0.0) -> np.ndarray:
    return (
        height + swing * np.sin(2 * np.pi * tau / 11.0) + bounce * np.sin(2 * np.pi * STEP_HZ * tau)
    )


def _wobbly_rotation(
    heading: np.ndarray,
    tau: np.ndarray,
    wobble_deg: tuple[float, float, float],
    shake_deg: float = 0.0,
) -> Rotation:
    """R_world_bundle with the bundle's x along ``heading`` plus a slow yaw/pitch/roll wobble and
    (``shake_deg``) pitch and roll jolts at the step frequency."""
    wy, wp, wr = np.radians(wobble_deg)
    shake = np.radians(shake_deg)
    yaw = heading + wy * np.sin(2 * np.pi * 0.17 * tau)
    pitch = wp * np.sin(2 * np.pi * 0.23 * tau + 0.7) + shake * np.sin(
        2 * np.pi * STEP_HZ * tau + 0.4
    )
    roll = wr * np.sin(2 * np.pi * 0.31 * tau + 1.9) + shake * np.sin(np.pi * STEP_HZ * tau + 1.1)
    # Intrinsic z-y'-x'': R_world_bundle = Rz(yaw) Ry(pitch) Rx(roll).
    return Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]))


# Planned paths inside the loop's region of the tetam room (x 7.7-11.8, y 7.0-10.9), where the
# four pillars' markers are in view. `rectangle` is closed (walked round and round, counter-
# clockwise like the loop); `zigzag` is open (walked there and back).
PRESET_PATHS: dict[str, tuple[tuple[float, float], ...]] = {
    "rectangle": ((8.0, 7.3), (11.5, 7.3), (11.5, 10.6), (8.0, 10.6), (8.0, 7.3)),
    "zigzag": ((8.0, 7.4), (8.9, 10.5), (9.8, 7.4), (10.7, 10.5), (11.5, 7.4)),
}


@dataclass(frozen=True)
class PolylineTrajectory:
    """Walk straight lines between xy waypoints at constant speed, like a person following a
    planned path; at each corner stop for ``dwell`` s and turn in place to the new heading.

    A closed polyline (last waypoint == first) is walked round and round; an open one there and
    back (turning round at each end). With ``turn`` False the bundle keeps its first heading all
    the way (the paper's paths "without rotation"); otherwise its x axis points along the segment.
    """

    waypoints: tuple[tuple[float, float], ...]
    t0: float = 1_700_000_000.0
    speed: float = 0.4  # m/s while walking
    dwell: float = 2.0  # s standing at each corner (turning when `turn`)
    turn: bool = True
    height: float = 1.55
    height_swing: float = 0.25
    wobble_deg: tuple[float, float, float] = (4.0, 3.0, 2.5)  # yaw, pitch, roll amplitudes
    bounce_m: float = 0.0  # vertical bounce at the step frequency (hand-carried)
    shake_deg: float = 0.0  # pitch and roll jolts at the step frequency (hand-carried)

    def __post_init__(self) -> None:
        wp = np.asarray(self.waypoints, float)
        if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 2 or not np.isfinite(wp).all():
            raise ValueError("waypoints must be at least two finite (x, y) pairs")
        if np.any(np.linalg.norm(np.diff(wp, axis=0), axis=1) == 0):
            raise ValueError("two consecutive waypoints are the same point")
        if self.speed < 0 or self.dwell < 0:
            raise ValueError("speed and dwell must be >= 0")

    @property
    def closed(self) -> bool:
        wp = np.asarray(self.waypoints, float)
        return bool(np.allclose(wp[0], wp[-1]))

    def _tour(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (n+1, 2) of one repeat of the walk and the heading (n,) of each segment."""
        wp = np.asarray(self.waypoints, float)
        tour = wp if self.closed else np.vstack([wp, wp[-2::-1]])
        d = np.diff(tour, axis=0)
        return tour, np.arctan2(d[:, 1], d[:, 0])

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        t = np.atleast_1d(np.asarray(t, float))
        tau = t - self.t0
        tour, heading = self._tour()
        n = len(heading)
        if self.speed == 0:  # standing at the start
            xy = np.repeat(tour[:1], len(t), 0)
            yaw = np.full(len(t), heading[0])
        else:
            # One repeat: walk segment k, then stand at its end turning to segment k+1's heading.
            walk = np.linalg.norm(np.diff(tour, axis=0), axis=1) / self.speed
            phase_len = np.column_stack([walk, np.full(n, self.dwell)]).ravel()
            phase_start = np.concatenate([[0.0], np.cumsum(phase_len)[:-1]])
            period = float(phase_len.sum())
            tp = np.mod(tau, period)
            # 'right' skips zero-length phases (dwell 0).
            j = np.clip(np.searchsorted(phase_start, tp, side="right") - 1, 0, 2 * n - 1)
            k = j // 2
            frac = np.clip((tp - phase_start[j]) / np.maximum(phase_len[j], 1e-12), 0.0, 1.0)
            walking = j % 2 == 0
            xy = np.where(
                walking[:, None], tour[k] + frac[:, None] * (tour[k + 1] - tour[k]), tour[k + 1]
            )
            change = np.mod(heading[(k + 1) % n] - heading[k] + np.pi, 2 * np.pi) - np.pi
            ease = (1 - np.cos(np.pi * frac)) / 2  # start and end the turn gently
            yaw = heading[k] + np.where(walking, 0.0, ease * change)
        if not self.turn:
            yaw = np.full(len(t), heading[0])
        z = _height(tau, self.height, self.height_swing, self.bounce_m)
        return np.column_stack([xy, z]), _wobbly_rotation(yaw, tau, self.wobble_deg, self.shake_deg)


@dataclass(frozen=True)
class RestFirst:
    """``walk`` preceded by a rest: for ``rest`` s from ``walk``'s t0 the bundle sits still at the
    walk's start pose (on a jig, see annotator.core.jig), then walks it from the start."""

    walk: LoopTrajectory | PolylineTrajectory
    rest: float

    @property
    def t0(self) -> float:
        return self.walk.t0

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        t = np.atleast_1d(np.asarray(t, float))
        return self.walk(np.where(t < self.t0 + self.rest, self.t0, t - self.rest))


# How the bundle is carried (`annotator simulate --motion`): the trajectory fields each sets.
MOTION_PROFILES: dict[str, dict[str, object]] = {
    # held in front while walking: slow wobble, height drifting between 1.3 and 1.8 m (the default)
    "walk": {},
    # on a level cart pushed along: no wobble, constant height
    "cart": {"height": 1.2, "height_swing": 0.0, "wobble_deg": (0.0, 0.0, 0.0)},
    # carried in one hand: more wobble, a 2 cm bounce and 2 deg jolts at every step
    "hand": {
        "height": 1.4,
        "height_swing": 0.1,
        "wobble_deg": (8.0, 6.0, 5.0),
        "bounce_m": 0.02,
        "shake_deg": 2.0,
    },
}
