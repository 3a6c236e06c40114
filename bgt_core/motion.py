"""Where a simulated beacon is at any moment: a looping waypoint path and "cover" events.

Standard library only. The simulated sensor agent and (later) the synthetic video renderer
share this model, so both see exactly the same trajectory for the same path and start time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from bgt_core.keys import unknown_key

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
# The keys of a cover event's and of a path's mapping (to_dict / from_dict).
COVER_KEYS = ("start_s", "duration_s", "attenuation_db", "drop_prob")
PATH_KEYS = ("waypoints", "speed_mps", "dwell_s", "corner_radius")


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
            raise MotionError(
                f"cover event attenuation_db must be >= 0, got {self.attenuation_db!r}"
            )

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s

    def to_dict(self) -> dict[str, float]:
        return {
            "start_s": self.start_s,
            "duration_s": self.duration_s,
            "attenuation_db": self.attenuation_db,
            "drop_prob": self.drop_prob,
        }

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> CoverEvent:
        message = unknown_key(d, COVER_KEYS, "cover event")
        if message is not None:
            raise MotionError(message)
        try:
            return CoverEvent(
                float(d["start_s"]),
                float(d["duration_s"]),
                float(d.get("attenuation_db", 20.0)),
                float(d.get("drop_prob", 0.6)),
            )
        except KeyError as e:
            raise MotionError(f"cover event: missing {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise MotionError(f"cover event: {e}") from None


def cover_at(events: Iterable[CoverEvent], t_s: float) -> CoverEvent | None:
    """The strongest cover event active at ``t_s``, or None."""
    active = [e for e in events if e.active(t_s)]
    return max(active, key=lambda e: e.attenuation_db) if active else None


@dataclass(frozen=True, slots=True)
class _Piece:
    """One stretch of the path: a straight line a -> b, or (``arc`` set) a circular arc a -> b."""

    start: float  # path time at which its dwell begins
    dwell: float
    travel: float
    a: Point
    b: Point
    # (centre, u, n, radius, angle): p(phi) = centre + radius (u sin phi - n cos phi), phi in [0, angle];
    # u is the direction of travel at a, n the unit vector from a towards the centre.
    arc: tuple[Point, Point, Point, float, float] | None = None


@dataclass(frozen=True, slots=True)
class PathModel:
    """A closed polyline walked at constant speed, pausing ``dwell_s`` at every waypoint, forever.

    Time 0 is at the first waypoint (start of its dwell); after the last waypoint the path
    returns to the first one and starts again.

    With ``corner_radius`` > 0 every corner is rounded by a circular arc of that radius, tangent
    to both sides and walked at the same constant speed: the velocity never changes direction in
    an instant (a person does not turn on the spot). The path then passes inside each corner's
    waypoint; time 0 and each dwell are where the arc of that waypoint begins. 0 keeps the sharp
    polyline.
    """

    waypoints: tuple[Point, ...] = DEFAULT_WAYPOINTS
    speed_mps: float = DEFAULT_SPEED_MPS
    dwell_s: float = 0.0
    corner_radius: float = 0.0
    _pieces: tuple[_Piece, ...] = field(init=False, repr=False, compare=False)
    _period: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        pts = tuple(_point(p, i) for i, p in enumerate(self.waypoints))
        if len(pts) < 2:
            raise MotionError(f"a path needs at least 2 waypoints, got {len(pts)}")
        if not (isinstance(self.speed_mps, int | float) and self.speed_mps > 0):
            raise MotionError(f"path speed_mps must be > 0, got {self.speed_mps!r}")
        if not (isinstance(self.dwell_s, int | float) and self.dwell_s >= 0):
            raise MotionError(f"path dwell_s must be >= 0, got {self.dwell_s!r}")
        r = self.corner_radius
        if isinstance(r, bool) or not (isinstance(r, int | float) and math.isfinite(r) and r >= 0):
            raise MotionError(f"path corner_radius must be a number >= 0, got {r!r}")
        corners = _corners(pts, float(r))
        pieces = []
        t = 0.0
        n = len(pts)
        for i in range(n):
            arc_a, arc_b, arc = corners[i]
            travel = 0.0 if arc is None else arc[3] * arc[4] / self.speed_mps
            pieces.append(_Piece(t, float(self.dwell_s), travel, arc_a, arc_b, arc))
            t += self.dwell_s + travel
            nxt = corners[(i + 1) % n][0]
            travel = math.dist(arc_b, nxt) / self.speed_mps
            pieces.append(_Piece(t, 0.0, travel, arc_b, nxt))
            t += travel
        if t <= 0:
            raise MotionError("a path whose waypoints all coincide has no length")
        object.__setattr__(self, "waypoints", pts)
        object.__setattr__(self, "_pieces", tuple(pieces))
        object.__setattr__(self, "_period", t)

    @property
    def period_s(self) -> float:
        """Time for one full lap, dwells included."""
        return self._period

    def _locate(self, t_s: float) -> tuple[_Piece, float, bool]:
        t = t_s % self._period
        pieces = self._pieces
        for k in range(len(pieces) - 1, -1, -1):
            piece = pieces[k]
            if t >= piece.start:
                u = t - piece.start - piece.dwell
                if u < 0 or piece.travel == 0:
                    # Standing still: at the start of the next piece that goes anywhere, facing its way.
                    for j in range(len(pieces)):
                        nxt = pieces[(k + j) % len(pieces)]
                        if nxt.travel > 0:
                            return nxt, 0.0, False
                    return piece, 0.0, False
                return piece, min(u / piece.travel, 1.0), True
        return pieces[0], 0.0, False

    def position_at(self, t_s: float) -> Point:
        """(x, y, z) in metres, ``t_s`` seconds after t0 (any real number; the path loops)."""
        piece, f, _ = self._locate(t_s)
        a, b = piece.a, piece.b
        if piece.arc is None:
            return (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)
        c, u, n, rad, angle = piece.arc
        s, k = rad * math.sin(f * angle), -rad * math.cos(f * angle)
        return (c[0] + s * u[0] + k * n[0], c[1] + s * u[1] + k * n[1], c[2] + s * u[2] + k * n[2])

    def direction_at(self, t_s: float) -> Point:
        """Unit vector of the direction of travel (also while dwelling at a piece's start)."""
        piece, f, _ = self._locate(t_s)
        if piece.arc is not None:
            _, u, n, _, angle = piece.arc
            cs, sn = math.cos(f * angle), math.sin(f * angle)
            return (cs * u[0] + sn * n[0], cs * u[1] + sn * n[1], cs * u[2] + sn * n[2])
        a, b = piece.a, piece.b
        d = math.dist(a, b)
        if d == 0:
            return (1.0, 0.0, 0.0)
        return ((b[0] - a[0]) / d, (b[1] - a[1]) / d, (b[2] - a[2]) / d)

    def is_moving(self, t_s: float) -> bool:
        return self._locate(t_s)[2]

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "waypoints": [list(p) for p in self.waypoints],
            "speed_mps": self.speed_mps,
            "dwell_s": self.dwell_s,
        }
        if self.corner_radius:
            d["corner_radius"] = (
                self.corner_radius
            )  # absent = sharp corners, as older readers expect
        return d

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> PathModel:
        message = unknown_key(d, PATH_KEYS, "path")
        if message is not None:
            raise MotionError(message)
        wps = d.get("waypoints", DEFAULT_WAYPOINTS)
        if not isinstance(wps, Sequence) or isinstance(wps, str):
            raise MotionError("path waypoints must be a list of [x, y, z]")
        return PathModel(
            tuple(wps),
            d.get("speed_mps", DEFAULT_SPEED_MPS),
            d.get("dwell_s", 0.0),
            d.get("corner_radius", 0.0),
        )


_Arc = tuple[Point, Point, Point, float, float]


def _unit(a: Point, b: Point) -> Point | None:
    d = math.dist(a, b)
    return None if d == 0 else ((b[0] - a[0]) / d, (b[1] - a[1]) / d, (b[2] - a[2]) / d)


def _corners(pts: tuple[Point, ...], radius: float) -> list[tuple[Point, Point, _Arc | None]]:
    """Per waypoint: where its rounding arc starts and ends, and the arc (None: a sharp corner).

    The arc of radius ``radius`` is tangent to the incoming and outgoing sides, in the plane they
    span, and starts ``radius * tan(turn / 2)`` before the waypoint. Raises MotionError if two
    arcs would overlap on a side or the path turns straight back (no arc can round a U-turn).
    """
    n = len(pts)
    out: list[tuple[Point, Point, _Arc | None]] = []
    cut = [0.0] * n  # how much of each side (before waypoint i) its arc takes away
    for i, w in enumerate(pts):
        u = _unit(pts[i - 1], w)
        v = _unit(w, pts[(i + 1) % n])
        if radius == 0 or u is None or v is None:
            out.append((w, w, None))
            continue
        cos_turn = max(-1.0, min(1.0, sum(x * y for x, y in zip(u, v, strict=True))))
        turn = math.acos(cos_turn)
        if turn < 1e-9:
            out.append((w, w, None))
            continue
        if turn > math.pi - 1e-6:
            raise MotionError(
                f"path corner_radius: waypoint {i} turns straight back; a U-turn cannot be "
                "rounded (add a waypoint beside it)"
            )
        d = radius * math.tan(turn / 2)
        nv = tuple(vv - cos_turn * uu for uu, vv in zip(u, v, strict=True))
        nn = math.sqrt(sum(x * x for x in nv))
        n_hat = (nv[0] / nn, nv[1] / nn, nv[2] / nn)
        a = (w[0] - d * u[0], w[1] - d * u[1], w[2] - d * u[2])
        b = (w[0] + d * v[0], w[1] + d * v[1], w[2] + d * v[2])
        centre = (a[0] + radius * n_hat[0], a[1] + radius * n_hat[1], a[2] + radius * n_hat[2])
        out.append((a, b, (centre, u, n_hat, radius, turn)))
        cut[i] = d
    for i in range(n):
        j = (i + 1) % n
        side = math.dist(pts[i], pts[j])
        d_out = 0.0 if out[i][2] is None else math.dist(pts[i], out[i][1])
        if d_out + cut[j] > side + 1e-9:
            raise MotionError(
                f"path corner_radius {radius:g} m is too large: the arcs at waypoints {i} and {j} "
                f"need {d_out + cut[j]:.3f} m of the {side:.3f} m side between them"
            )
    return out


def _point(p: Any, i: int) -> Point:
    if isinstance(p, str) or not isinstance(p, Sequence) or len(p) != 3:
        raise MotionError(f"waypoint {i} must be [x, y, z], got {p!r}")
    out = []
    for v in p:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise MotionError(f"waypoint {i} must be three finite numbers, got {p!r}")
        out.append(float(v))
    return (out[0], out[1], out[2])
