"""`.occ` occupancy grids: area limits, cell size and a 0/1 value per cell (lower-left corner).
In the published tetam grids 1 marks occupied cells (desks, cupboards) and 0 free floor: the
annotated trajectories run almost entirely through 0 cells. Standard library only; see
docs/formats.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats._textio import finite, json_loads, read_text, write_text_atomic

Limits = tuple[tuple[float, float], tuple[float, float]]  # ((x0, y0), (x1, y1)) metres
Cell = tuple[float, float]  # lower-left corner of a grid cell, metres


class GridFormatError(ValueError):
    """A malformed .occ or .grd file; the message names the file and line."""


@dataclass(frozen=True, slots=True)
class Occupancy:
    limits: Limits
    cell: float
    cells: dict[Cell, int]  # 0 or 1 per cell (1 = occupied in the published files); file order kept


def grid_corners(limits: Limits, cell: float) -> tuple[list[float], list[float]]:
    """Lower-left corners along x and y as the published grids lay them out: from x0 in steps of
    ``cell`` up to the first corner at or beyond x1 minus one step, i.e. ``arange(x0, x1 + cell, cell)``
    (a 20.66 m side in 1 m cells gives 22 columns, 0..21)."""
    (x0, y0), (x1, y1) = limits
    if not (cell > 0 and math.isfinite(cell)):
        raise ValueError(f"cell size must be a positive number, got {cell}")

    def axis(a: float, b: float) -> list[float]:
        n = math.ceil((b - a) / cell - 1e-9) + 1
        # round() keeps corners like 0.1 * 3 printable as 0.3, which is how the files spell them
        return [round(a + i * cell, 9) for i in range(max(n, 1))]

    return axis(x0, x1), axis(y0, y1)


def parse_limits(text: str) -> Limits:
    v = json_loads(text)
    (x0, y0), (x1, y1) = v
    lim = ((finite(x0, "x0"), finite(y0, "y0")), (finite(x1, "x1"), finite(y1, "y1")))
    if not (lim[1][0] > lim[0][0] and lim[1][1] > lim[0][1]):
        raise ValueError("limits must be [[x0, y0], [x1, y1]] with x1 > x0 and y1 > y0")
    return lim


def format_limits(limits: Limits) -> str:
    (x0, y0), (x1, y1) = limits
    return f"[[{float(x0)!r}, {float(y0)!r}], [{float(x1)!r}, {float(y1)!r}]]"


def parse_cell_key(text: str) -> Cell:
    v = json_loads(text)
    if not (isinstance(v, list) and len(v) == 2):
        raise ValueError("expected [gx, gy]")
    return (finite(v[0], "gx"), finite(v[1], "gy"))


def format_cell_key(c: Cell) -> str:
    return f"[{float(c[0])!r}, {float(c[1])!r}]"


def check_cell(cell: float) -> float:
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell size must be a positive number, got {cell}")
    return float(cell)


def _value(text: str) -> int:
    if text.strip() not in ("0", "1"):
        raise ValueError(f"value must be 0 or 1, got {text.strip()!r}")
    return int(text.strip())


def parse_occ(text: str, source: str = "<occ>") -> Occupancy:
    lines = text.splitlines()
    header_no = next((i for i, line in enumerate(lines) if line.strip()), None)
    if header_no is None:
        raise GridFormatError(f"{source}: empty file")
    try:
        lim_text, cell_text = lines[header_no].split("::")
        limits, cell = parse_limits(lim_text), check_cell(float(cell_text))
    except (ValueError, TypeError, OverflowError) as e:
        raise GridFormatError(
            f"{source}:{header_no + 1}: expected '[[x0, y0], [x1, y1]]::<cell>' ({e})"
        ) from None
    cells: dict[Cell, int] = {}
    for lineno, line in enumerate(lines[header_no + 1 :], header_no + 2):
        if not line.strip():
            continue
        try:
            key_text, value = line.split("::")
            key, v = parse_cell_key(key_text), _value(value)
        except (ValueError, TypeError) as e:
            raise GridFormatError(f"{source}:{lineno}: expected '[gx, gy]::<0|1>' ({e})") from None
        if key in cells:
            raise GridFormatError(f"{source}:{lineno}: cell {list(key)} listed twice")
        cells[key] = v
    return Occupancy(limits, cell, cells)


def read_occ(path: str | Path) -> Occupancy:
    path = Path(path)
    return parse_occ(read_text(path, GridFormatError), str(path))


def format_occ(occ: Occupancy) -> str:
    rows = "".join(f"{format_cell_key(c)}::{int(v)}\n" for c, v in occ.cells.items())
    return f"{format_limits(occ.limits)}::{float(occ.cell)!r}\n{rows}"


def write_occ(occ: Occupancy, path: str | Path) -> None:
    write_text_atomic(Path(path), format_occ(occ))
