"""The ArUco marker map: ``marker_positions.dat`` (``<id>: [x, y, z]:[rx, ry, rz]``) and YAML.

Rotation marker->world is R = Rz(rz) @ Ry(ry) @ Rx(rx) (extrinsic x-y-z Euler angles).
Standard library only: rotations are returned as nested lists; the annotator converts them.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path


class MarkerMapError(ValueError):
    """A malformed marker map; the message names the file and line or entry."""


@dataclass(frozen=True, slots=True)
class MarkerPose:
    id: int
    position: tuple[float, float, float]  # marker centre, world frame, metres
    euler_xyz: tuple[float, float, float]  # rx, ry, rz radians (R = Rz Ry Rx)

    def rotation(self) -> list[list[float]]:
        """3x3 marker->world rotation as nested lists."""
        rx, ry, rz = self.euler_xyz
        cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
        return [
            [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
            [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
            [-sy, cy * sx, cy * cx],
        ]


_LINE = re.compile(r"^\s*(\d+)\s*:\s*(\[[^\]]*\])\s*:\s*(\[[^\]]*\])\s*$")


def _triple(text: str, what: str) -> tuple[float, float, float]:
    v = json.loads(text)
    if not (isinstance(v, list) and len(v) == 3 and all(isinstance(a, int | float) for a in v)):
        raise ValueError(f"{what} must be three numbers")
    return (float(v[0]), float(v[1]), float(v[2]))


def parse_dat(text: str, source: str = "<markers>") -> dict[int, MarkerPose]:
    out: dict[int, MarkerPose] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _LINE.match(line)
        if not m:
            raise MarkerMapError(f"{source}:{lineno}: expected '<id>: [x, y, z]:[rx, ry, rz]'")
        try:
            mid = int(m.group(1))
            pose = MarkerPose(mid, _triple(m.group(2), "position"), _triple(m.group(3), "rotation"))
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
        for m in sorted(markers.values(), key=lambda m: m.id))


def parse_yaml_obj(obj: object, source: str = "<markers.yaml>") -> dict[int, MarkerPose]:
    """YAML form: ``markers: [{id: 0, position: [x, y, z], rotation_xyz: [rx, ry, rz]}, ...]``."""
    items = obj.get("markers") if isinstance(obj, dict) else None
    if not isinstance(items, list) or not items:
        raise MarkerMapError(f"{source}: expected a non-empty 'markers:' list")
    out: dict[int, MarkerPose] = {}
    for i, it in enumerate(items):
        try:
            mid = int(it["id"])
            pose = MarkerPose(mid, _triple(json.dumps(it["position"]), "position"),
                              _triple(json.dumps(it["rotation_xyz"]), "rotation_xyz"))
        except (KeyError, TypeError, ValueError) as e:
            raise MarkerMapError(f"{source}: markers[{i}]: needs id, position [x,y,z], rotation_xyz [rx,ry,rz] ({e})") from None
        if mid in out:
            raise MarkerMapError(f"{source}: marker {mid} listed twice")
        out[mid] = pose
    return out


def read_marker_map(path: str | Path) -> dict[int, MarkerPose]:
    """Either form, chosen by extension (.yaml/.yml -> YAML, anything else -> .dat)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise MarkerMapError(f"cannot read marker map {path}: {e.strerror}") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            return parse_yaml_obj(yaml.safe_load(text), str(path))
        except yaml.YAMLError as e:
            raise MarkerMapError(f"{path}: not valid YAML ({e})") from None
    return parse_dat(text, str(path))
