"""Site configuration: ``<site>.dev`` (sensors and beacons) and ``<site>.par`` (map geometry)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

from bgt_core.formats._textio import finite, json_loads, read_text
from bgt_core.wire import WireError, normalize_mac

if TYPE_CHECKING:  # numpy only for the types: this module is stdlib only
    import numpy as np
    from numpy.typing import NDArray


class SiteConfigError(ValueError):
    """A malformed .dev or .par file."""


@dataclass(frozen=True, slots=True)
class Device:
    mac: str
    position: tuple[float, ...]  # (x, y, z) in metres; empty for a moving beacon
    colour: int
    alias: str


@dataclass(frozen=True, slots=True)
class Devices:
    dongles: dict[str, Device]  # sensors by MAC
    beacons: dict[str, Device]

    def by_alias(self, alias: str) -> Device:
        for d in (*self.dongles.values(), *self.beacons.values()):
            if d.alias == alias:
                return d
        raise KeyError(alias)


def _devices(obj: object, what: str) -> dict[str, Device]:
    if not isinstance(obj, dict):
        raise SiteConfigError(f"{what} must be a JSON object")
    out = {}
    for mac, spec in obj.items():
        try:
            pos, colour, alias = spec
            position = tuple(finite(v, "position") for v in pos)
            out[normalize_mac(mac)] = Device(normalize_mac(mac), position, int(colour), str(alias))
        except (TypeError, ValueError, WireError, OverflowError) as e:
            raise SiteConfigError(
                f"{what} entry {mac!r:.40}: expected [[x, y, z], colour, alias] ({e})"
            ) from None
    return out


def parse_dev(text: str, source: str = "<dev>") -> Devices:
    fields: dict[str, object] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise SiteConfigError(f"{source}:{lineno}: expected 'Key:JSON'")
        try:
            fields[key.strip()] = json_loads(value)
        except ValueError as e:
            raise SiteConfigError(
                f"{source}:{lineno}: {key.strip()[:40]} is not valid JSON ({e})"
            ) from None
    if "Dongles" not in fields:
        raise SiteConfigError(f"{source}: no 'Dongles:' line")
    return Devices(
        _devices(fields["Dongles"], f"{source}: Dongles"),
        _devices(fields.get("Beacons", {}), f"{source}: Beacons"),
    )


def read_dev(path: str | Path) -> Devices:
    path = Path(path)
    return parse_dev(read_text(path, SiteConfigError, "devices file"), str(path))


def _device_json(d: Device) -> str:
    pos = "[" + ", ".join(f"{v:.2f}" for v in d.position) + "]"
    return f'"{d.mac}": [{pos}, {d.colour}, {json.dumps(d.alias)}]'


def format_dev(devices: Devices) -> str:
    dongles = ", ".join(_device_json(d) for d in devices.dongles.values())
    beacons = ", ".join(_device_json(d) for d in devices.beacons.values())
    return f"Dongles:{{{dongles}}}\nBeacons:{{{beacons}}}\n"


@dataclass(frozen=True, slots=True)
class MapParams:
    origin: tuple[float, float]  # pixel position of the world origin
    limits: tuple[float, float, float, float]  # x0, y0, x1, y1 in metres
    direction: tuple[int, int, int, int]  # a, b, sx, sy
    parity: float  # metres per pixel

    @overload
    def world_to_pixel(self, x: float, y: float) -> tuple[float, float]: ...
    @overload
    def world_to_pixel(
        self, x: NDArray[np.float64], y: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def world_to_pixel(self, x: Any, y: Any) -> tuple[Any, Any]:
        """World metres -> map pixels (works on numbers or numpy arrays)."""
        a, b, sx, sy = self.direction
        p = (x, y)
        return (self.origin[0] + p[a] / self.parity * sx, self.origin[1] + p[b] / self.parity * sy)


def parse_par(text: str, source: str = "<par>") -> MapParams:
    try:
        d = json_loads(text)
        ox, oy = (finite(v, "origin") for v in d["origin"])
        x0, y0, x1, y1 = (finite(v, "limits") for v in d["limits"])
        a, b, sx, sy = (int(v) for v in d["direction"])
        p = MapParams((ox, oy), (x0, y0, x1, y1), (a, b, sx, sy), finite(d["parity"], "parity"))
    except (ValueError, KeyError, TypeError, OverflowError) as e:
        raise SiteConfigError(
            f"{source}: expected origin, limits, direction, parity ({e})"
        ) from None
    if (
        len(p.origin) != 2
        or len(p.limits) != 4
        or len(p.direction) != 4
        or not p.parity > 0
        or not set(p.direction[:2]) <= {0, 1}
    ):
        raise SiteConfigError(
            f"{source}: expected origin [u, v], limits [x0, y0, x1, y1], "
            "direction [a, b, sx, sy] (a, b: 0 or 1) and parity > 0"
        )
    return p


def read_par(path: str | Path) -> MapParams:
    path = Path(path)
    return parse_par(read_text(path, SiteConfigError, "map parameters"), str(path))


def format_par(p: MapParams) -> str:
    return (
        json.dumps(
            {
                "origin": list(p.origin),
                "limits": list(p.limits),
                "direction": list(p.direction),
                "parity": p.parity,
            }
        )
        + "\n"
    )


def devices_from_obj(dongles: object, beacons: object, source: str = "<devices>") -> Devices:
    """Devices from already-decoded ``Dongles``/``Beacons`` objects (as embedded in .hst files)."""
    return Devices(_devices(dongles, f"{source}: Dongles"), _devices(beacons, f"{source}: Beacons"))


def devices_to_obj(devices: Devices) -> tuple[dict[str, list[Any]], dict[str, list[Any]]]:
    """The inverse of :func:`devices_from_obj`: ``{mac: [[x, y, z], colour, alias]}`` per kind."""

    def kind(ds: dict[str, Device]) -> dict[str, list[Any]]:
        return {d.mac: [list(d.position), d.colour, d.alias] for d in ds.values()}

    return kind(devices.dongles), kind(devices.beacons)
