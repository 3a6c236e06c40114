"""Where a simulated beacon is at any moment: a looping waypoint path and "cover" events.

Standard library only. The simulated sensor agent and (later) the synthetic video renderer
share this model, so both see exactly the same trajectory for the same path and start time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

Point = tuple[float, float, float]

# A loop through the tetam room (about 20.7 m x 17.6 m), clear of the walls, hand-held
# height between 1.2 m and 1.9 m; at 0.4 m/s one lap takes a little over two minutes.
DEFAULT_WAYPOINTS: tuple[Point, ...] = (
    (3.0, 3.0, 1.2),
    (10.0, 2.5, 1.4),
    (17.0, 3.5, 1.6),
    (17.5, 9.0, 1.9),
    (16.0, 14.5, 1.7),
    (10.0, 15.0, 1.5),
    (3.5, 14.0, 1.3),
    (2.5, 8.5, 1.2),
)
DEFAULT_SPEED_MPS = 0.4


class MotionError(ValueError):
    """A path or cover event that cannot be used (too few waypoints, non-positive speed...)."""


@dataclass(frozen=True, slots=True)
class CoverEvent:
    """A stretch of time during which hands cover the beacon: every sensor hears it weaker, and less."""

    start_s: float  # seconds after the path's t0
    duration_s: float
    attenuation_db: float = 20.0
    drop_prob: float = 0.6  # extra chance that any one advert is lost while covered

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise MotionError(f"cover event duration_s must be > 0, got {self.duration_s!r}")
        if not 0.0 <= self.drop_prob <= 1.0:
            raise MotionError(f"cover event drop_prob must be in [0, 1], got {self.drop_prob!r}")
        if self.attenuation_db < 0:
            raise MotionError(f"cover event attenuation_db must be >= 0, got {self.attenuation_db!r}")

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s

    def to_dict(self) -> dict[str, float]:
        return {"start_s": self.start_s, "duration_s": self.duration_s,
                "attenuation_db": self.attenuation_db, "drop_prob": self.drop_prob}

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> CoverEvent:
        unknown = set(d) - {"start_s", "duration_s", "attenuation_db", "drop_prob"}
        if unknown:
            raise MotionError(f"cover event: unknown key {sorted(unknown)[0]!r}")
        try:
            return CoverEvent(float(d["start_s"]), float(d["duration_s"]),
                              float(d.get("attenuation_db", 20.0)), float(d.get("drop_prob", 0.6)))
        except KeyError as e:
            raise MotionError(f"cover event: missing {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise MotionError(f"cover event: {e}") from None


def cover_at(events: Iterable[CoverEvent], t_s: float) -> CoverEvent | None:
    """The strongest cover event active at ``t_s``, or None."""
    active = [e for e in events if e.active(t_s)]
    return max(active, key=lambda e: e.attenuation_db) if active else None


@dataclass(frozen=True, slots=True)
class PathModel:
    """A closed polyline walked at constant speed, pausing ``dwell_s`` at every waypoint, forever.

    Time 0 is at the first waypoint (start of its dwell); after the last waypoint the path
    returns to the first one and starts again.
    """

    waypoints: tuple[Point, ...] = DEFAULT_WAYPOINTS
    speed_mps: float = DEFAULT_SPEED_MPS
    dwell_s: float = 0.0
    # Per segment: (start time, dwell, travel time, start point, end point); derived.
    _segments: tuple[tuple[float, float, float, Point, Point], ...] = field(
        init=False, repr=False, compare=False)
    _period: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        pts = tuple(_point(p, i) for i, p in enumerate(self.waypoints))
        if len(pts) < 2:
            raise MotionError(f"a path needs at least 2 waypoints, got {len(pts)}")
        if not (isinstance(self.speed_mps, int | float) and self.speed_mps > 0):
            raise MotionError(f"path speed_mps must be > 0, got {self.speed_mps!r}")
        if not (isinstance(self.dwell_s, int | float) and self.dwell_s >= 0):
            raise MotionError(f"path dwell_s must be >= 0, got {self.dwell_s!r}")
        segs = []
        t = 0.0
        for i, a in enumerate(pts):
            b = pts[(i + 1) % len(pts)]
            travel = math.dist(a, b) / self.speed_mps
            segs.append((t, float(self.dwell_s), travel, a, b))
            t += self.dwell_s + travel
        if t <= 0:
            raise MotionError("a path whose waypoints all coincide has no length")
        object.__setattr__(self, "waypoints", pts)
        object.__setattr__(self, "_segments", tuple(segs))
        object.__setattr__(self, "_period", t)

    @property
    def period_s(self) -> float:
        """Time for one full lap, dwells included."""
        return self._period

    def _locate(self, t_s: float) -> tuple[Point, Point, float, bool]:
        t = t_s % self._period
        for start, dwell, travel, a, b in reversed(self._segments):
            if t >= start:
                u = t - start - dwell
                if u < 0 or travel == 0:
                    return a, b, 0.0, False
                return a, b, min(u / travel, 1.0), True
        _, _, _, a, b = self._segments[0]
        return a, b, 0.0, False

    def position_at(self, t_s: float) -> Point:
        """(x, y, z) in metres, ``t_s`` seconds after t0 (any real number; the path loops)."""
        a, b, f, _ = self._locate(t_s)
        return (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)

    def direction_at(self, t_s: float) -> Point:
        """Unit vector of the current segment (also while dwelling at its start)."""
        a, b, _, _ = self._locate(t_s)
        d = math.dist(a, b)
        if d == 0:
            return (1.0, 0.0, 0.0)
        return ((b[0] - a[0]) / d, (b[1] - a[1]) / d, (b[2] - a[2]) / d)

    def is_moving(self, t_s: float) -> bool:
        return self._locate(t_s)[3]

    def to_dict(self) -> dict[str, Any]:
        return {"waypoints": [list(p) for p in self.waypoints], "speed_mps": self.speed_mps,
                "dwell_s": self.dwell_s}

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> PathModel:
        unknown = set(d) - {"waypoints", "speed_mps", "dwell_s"}
        if unknown:
            raise MotionError(f"path: unknown key {sorted(unknown)[0]!r}")
        wps = d.get("waypoints", DEFAULT_WAYPOINTS)
        if not isinstance(wps, Sequence) or isinstance(wps, str):
            raise MotionError("path waypoints must be a list of [x, y, z]")
        return PathModel(tuple(wps), d.get("speed_mps", DEFAULT_SPEED_MPS), d.get("dwell_s", 0.0))


def _point(p: Any, i: int) -> Point:
    if isinstance(p, str) or not isinstance(p, Sequence) or len(p) != 3:
        raise MotionError(f"waypoint {i} must be [x, y, z], got {p!r}")
    out = []
    for v in p:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise MotionError(f"waypoint {i} must be three finite numbers, got {p!r}")
        out.append(float(v))
    return (out[0], out[1], out[2])
