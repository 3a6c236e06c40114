"""`.grd` radio-map grids: one sensor's RSSI histogram for every grid cell and beacon.
Standard library only; see docs/formats.md.

The published files carry one value per bin *edge* (``len(bins)`` values, e.g. 81 for the edges
-100..-20 dBm), the last always 0: the probabilities of the ``len(bins) - 1`` bins followed by a
0 for "above the last edge". We write them that way, so loaders written for the published files
read ours, and read either spelling (``len(bins)`` or ``len(bins) - 1`` values). In memory a
histogram always has ``len(bins) - 1`` entries."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats._textio import finite, json_loads, read_text, write_text_atomic
from bgt_core.formats.hst import check_edges
from bgt_core.formats.occ import (
    Cell,
    GridFormatError,
    Limits,
    check_cell,
    format_cell_key,
    format_limits,
    parse_cell_key,
    parse_limits,
)
from bgt_core.wire import WireError, normalize_mac

__all__ = ["GridFormatError", "RadioMapGrid", "format_grd", "parse_grd", "read_grd", "write_grd"]


@dataclass(frozen=True, slots=True)
class RadioMapGrid:
    sensor: str  # MAC
    limits: Limits
    cell: float
    bins: tuple[float, ...]  # edges; each histogram has len(bins) - 1 entries
    cells: dict[Cell, dict[str, tuple[float, ...]]]  # lower-left corner -> beacon -> histogram


def _floats(text: str, n: int | None, what: str) -> tuple[float, ...]:
    v = json_loads(text)
    if not isinstance(v, list) or (n is not None and len(v) != n):
        raise ValueError(
            f"{what}: expected a list of {n if n is not None else 'numbers'}, "
            f"got {len(v) if isinstance(v, list) else type(v).__name__}"
        )
    return tuple(finite(x, what) for x in v)


def _histogram(text: str, n_edges: int) -> tuple[float, ...]:
    v = _floats(text, None, "histogram")
    if len(v) == n_edges:
        if v[-1] != 0.0:
            raise ValueError(
                f"the value after the last bin (number {n_edges}) must be 0, got {v[-1]}"
            )
        return v[:-1]
    if len(v) != n_edges - 1:
        raise ValueError(
            f"histogram: expected {n_edges} values (one per bin edge, the last 0) or "
            f"{n_edges - 1}, got {len(v)}"
        )
    return v


def parse_grd(text: str, source: str = "<grd>") -> RadioMapGrid:
    lines = text.splitlines()
    header_no = next((i for i, line in enumerate(lines) if line.strip()), None)
    if header_no is None:
        raise GridFormatError(f"{source}: empty file")
    try:
        mac, lim_text, cell_text, bins_text = lines[header_no].split("::")
        sensor, limits, cell = normalize_mac(mac), parse_limits(lim_text), float(cell_text)
        bins = check_edges(json_loads(bins_text))
        cell = check_cell(cell)
    except (ValueError, TypeError, WireError, OverflowError) as e:
        raise GridFormatError(
            f"{source}:{header_no + 1}: expected "
            f"'<sensor>::[[x0, y0], [x1, y1]]::<cell>::[bins]' ({e})"
        ) from None
    cells: dict[Cell, dict[str, tuple[float, ...]]] = {}
    for lineno, line in enumerate(lines[header_no + 1 :], header_no + 2):
        if not line.strip():
            continue
        try:
            key_text, beacon, hist_text = line.split("::")
            key = parse_cell_key(key_text)
            beacon = normalize_mac(beacon)
            hist = _histogram(hist_text, len(bins))
        except (ValueError, TypeError, WireError) as e:
            raise GridFormatError(
                f"{source}:{lineno}: expected '[gx, gy]::<beacon>::[p, ...]' ({e})"
            ) from None
        per_cell = cells.setdefault(key, {})
        if beacon in per_cell:
            raise GridFormatError(
                f"{source}:{lineno}: cell {list(key)} beacon {beacon} listed twice"
            )
        per_cell[beacon] = hist
    return RadioMapGrid(sensor, limits, cell, bins, cells)


def read_grd(path: str | Path) -> RadioMapGrid:
    path = Path(path)
    return parse_grd(read_text(path, GridFormatError), str(path))


def format_grd(g: RadioMapGrid) -> str:
    bins = "[" + ", ".join(repr(float(b)) for b in g.bins) + "]"
    out = [f"{g.sensor}::{format_limits(g.limits)}::{float(g.cell)!r}::{bins}\n"]
    for c, beacons in g.cells.items():
        key = format_cell_key(c)
        for beacon, hist in beacons.items():
            # one value per bin edge, as the published files: the bins' probabilities, then 0.0
            values = ", ".join(repr(float(p)) for p in (*hist, 0.0))
            out.append(f"{key}::{beacon}::[{values}]\n")
    return "".join(out)


def write_grd(g: RadioMapGrid, path: str | Path) -> None:
    write_text_atomic(Path(path), format_grd(g))
