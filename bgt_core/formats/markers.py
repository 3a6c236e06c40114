"""The ArUco marker map: ``marker_positions.dat`` (``<id>: [x, y, z]:[rx, ry, rz]``) and YAML.

Rotation marker->world is R = Rz(rz) @ Ry(ry) @ Rx(rx) (extrinsic x-y-z Euler angles).
Standard library only: rotations are returned as nested lists; the annotator converts them.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats._textio import finite, json_loads, read_text
from bgt_core.keys import unknown_key


class MarkerMapError(ValueError):
    """A malformed marker map; the message names the file and line or entry."""


@dataclass(frozen=True, slots=True)
class MarkerPose:
    id: int
    position: tuple[float, float, float]  # marker centre, world frame, metres
    euler_xyz: tuple[float, float, float]  # rx, ry, rz radians (R = Rz Ry Rx)

    @classmethod
    def from_values(
        cls, mid: int, position: Iterable[float], euler_xyz: Iterable[float]
    ) -> MarkerPose:
        """From any three numbers each (numpy rows, lists) as floats; ValueError unless three."""
        x, y, z = (float(v) for v in position)
        rx, ry, rz = (float(v) for v in euler_xyz)
        return cls(int(mid), (x, y, z), (rx, ry, rz))


_LINE = re.compile(r"^\s*(\d+)\s*:\s*(\[[^\]]*\])\s*:\s*(\[[^\]]*\])\s*$")
# Marker ids the map may name: ArUco dictionaries hold at most 1,000 markers (AprilTag 36h11: 587).
MAX_MARKER_ID = 9999
# |coordinate| limit, metres: a room, not the solar system (also keeps squares finite).
MAX_COORDINATE_M = 1e5


def _marker_id(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError(f"marker id must be an integer, not {value!r:.40}")  # noqa: TRY004
    text = str(value).strip()
    if not (text.isascii() and text.isdigit()) or len(text) > 12 or int(text) > MAX_MARKER_ID:
        raise ValueError(f"marker id {text[:24]!r} is not an integer in 0..{MAX_MARKER_ID}")
    return int(text)


def _triple(value: object, what: str, limit: float) -> tuple[float, float, float]:
    if isinstance(value, str):
        value = json_loads(value)
    if not (isinstance(value, list) and len(value) == 3):
        raise ValueError(f"{what} must be three numbers")
    x, y, z = (finite(a, what) for a in value)
    if any(abs(a) > limit for a in (x, y, z)):
        raise ValueError(f"{what} {[x, y, z]}: values beyond ±{limit:g}")
    return x, y, z


def _pose(mid: int, position: object, rotation: object, rotation_name: str) -> MarkerPose:
    return MarkerPose(
        mid, _triple(position, "position", MAX_COORDINATE_M), _triple(rotation, rotation_name, 1e6)
    )


def parse_dat(text: str, source: str = "<markers>") -> dict[int, MarkerPose]:
    out: dict[int, MarkerPose] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _LINE.match(line)
        if not m:
            raise MarkerMapError(f"{source}:{lineno}: expected '<id>: [x, y, z]:[rx, ry, rz]'")
        try:
            mid = _marker_id(m.group(1))
            pose = _pose(mid, m.group(2), m.group(3), "rotation")
        except ValueError as e:
            raise MarkerMapError(f"{source}:{lineno}: {e}") from None
        if mid in out:
            raise MarkerMapError(f"{source}:{lineno}: marker {mid} listed twice")
        out[mid] = pose
    if not out:
        raise MarkerMapError(f"{source}: no markers")
    return out


def format_dat(markers: dict[int, MarkerPose]) -> str:
    return "".join(
        f"{m.id}: [{m.position[0]!r}, {m.position[1]!r}, {m.position[2]!r}]:"
        f"[{m.euler_xyz[0]!r}, {m.euler_xyz[1]!r}, {m.euler_xyz[2]!r}]\n"
        for m in sorted(markers.values(), key=lambda m: m.id)
    )


def parse_yaml_obj(obj: object, source: str = "<markers.yaml>") -> dict[int, MarkerPose]:
    """YAML form: ``markers: [{id: 0, position: [x, y, z], rotation_xyz: [rx, ry, rz]}, ...]``."""
    if isinstance(obj, dict) and (message := unknown_key(obj, ("markers",), source)):
        raise MarkerMapError(message)
    items = obj.get("markers") if isinstance(obj, dict) else None
    if not isinstance(items, list) or not items:
        raise MarkerMapError(f"{source}: expected a non-empty 'markers:' list")
    out: dict[int, MarkerPose] = {}
    for i, it in enumerate(items):
        if isinstance(it, dict) and (
            message := unknown_key(it, ("id", "position", "rotation_xyz"), source, f"markers[{i}]")
        ):
            raise MarkerMapError(message)
        try:
            mid = _marker_id(it["id"])
            pose = _pose(mid, it["position"], it["rotation_xyz"], "rotation_xyz")
        except (KeyError, TypeError, ValueError) as e:
            raise MarkerMapError(
                f"{source}: markers[{i}]: needs id, position [x,y,z], rotation_xyz [rx,ry,rz] ({e})"
            ) from None
        if mid in out:
            raise MarkerMapError(f"{source}: marker {mid} listed twice")
        out[mid] = pose
    return out


def read_marker_map(path: str | Path) -> dict[int, MarkerPose]:
    """Either form, chosen by extension (.yaml/.yml -> YAML, anything else -> .dat)."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        from bgt_core.safe_yaml import YamlError, load_file

        try:
            return parse_yaml_obj(load_file(path), str(path))
        except YamlError as e:
            raise MarkerMapError(f"marker map: {e}") from None
    return parse_dat(read_text(path, MarkerMapError, "marker map"), str(path))
