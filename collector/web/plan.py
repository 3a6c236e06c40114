"""The floor plan the console draws the sensors on: a site's ``.dev`` (sensor positions), ``.par``
(map geometry) and map image, as the published dataset and the built-in sites carry them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bgt_core.formats.devices import MapParams, read_dev, read_par
from bgt_core.sites import site_dir


class PlanError(ValueError):
    """A plan that cannot be used; the message names the file."""


@dataclass(frozen=True)
class FloorPlan:
    image: Path
    width: int
    height: int
    sensors: dict[str, tuple[float, float, str]]  # MAC -> map pixel x, y and alias
    params: MapParams

    def pixels(self, x: float, y: float, r_m: float = 0.0) -> tuple[float, float, float]:
        """Site metres -> map pixels, and a length in metres -> pixels."""
        px, py = self.params.world_to_pixel(x, y)
        return round(float(px), 1), round(float(py), 1), round(r_m / self.params.parity, 1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "sensors": {m: [round(x, 1), round(y, 1), a] for m, (x, y, a) in self.sensors.items()},
        }


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        raise PlanError(f"{path}: not a PNG image")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def load_plan(where: str) -> FloorPlan:
    """A built-in site's name (``tetam``) or a folder holding one ``.dev``, ``.par`` and ``.png``."""
    folder = Path(where)
    if not folder.is_dir():
        try:
            folder = site_dir(where)
        except (FileNotFoundError, ValueError):
            raise PlanError(f"--plan {where!r}: neither a folder nor a built-in site") from None
    found = {ext: sorted(folder.glob(f"*.{ext}")) for ext in ("dev", "par", "png")}
    missing = [ext for ext, files in found.items() if len(files) != 1]
    if missing:
        raise PlanError(
            f"{folder}: needs exactly one .dev, .par and .png (check: {', '.join(missing)})"
        )
    devices, params = read_dev(found["dev"][0]), read_par(found["par"][0])
    width, height = _png_size(found["png"][0])
    sensors = {}
    for mac, d in devices.dongles.items():
        if len(d.position) >= 2:
            x, y = params.world_to_pixel(float(d.position[0]), float(d.position[1]))
            sensors[mac] = (float(x), float(y), d.alias)
    return FloorPlan(found["png"][0], width, height, sensors, params)
