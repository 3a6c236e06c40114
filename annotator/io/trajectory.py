"""trajectory.csv: ``t,x,y,z,r11..r33`` then optional quality columns; NaN rows are gaps.

R is R_world_bundle, row-major; t is wall-clock Unix seconds. The type itself is
annotator.core.trajectory.Trajectory.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from annotator.core.trajectory import Trajectory
from annotator.errors import AnnotatorError

POSE_COLUMNS = ("t", "x", "y", "z", "r11", "r12", "r13", "r21", "r22", "r23", "r31", "r32", "r33")


def _fmt(v: float, digits: int) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.{digits}f}"


def write_trajectory(path: str | Path, traj: Trajectory) -> None:
    """Write atomically (temp file, then rename) so a failed run never leaves half a file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    qnames = list(traj.quality)
    with tmp.open("w", encoding="utf-8", newline="") as f:
        f.write(",".join([*POSE_COLUMNS, *qnames]) + "\n")
        rot = traj.rotation.reshape(-1, 9)
        for i in range(len(traj.t)):
            cells = [_fmt(traj.t[i], 6)]
            cells += [_fmt(v, 6) for v in traj.position[i]]
            cells += [_fmt(v, 12) for v in rot[i]]  # 12 decimals keep R orthonormal to ~1e-12
            for q in qnames:
                v = float(traj.quality[q][i])
                cells.append(
                    "nan" if not math.isfinite(v) else (str(int(v)) if v == int(v) else f"{v:.6g}")
                )
            f.write(",".join(cells) + "\n")
    tmp.replace(path)


# Times must be Unix seconds in 1970..2100; positions within ±100 km (a room, with margin).
T_MAX_S = 4_102_444_800.0
POSITION_MAX_M = 1e5


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory.csv; every problem is one AnnotatorError line naming the file and line.

    ``t`` must be finite, sorted and in 1970..2100; pose columns may be NaN (a gap) but never
    infinite, and positions lie within ±100 km."""
    from bgt_core.formats._textio import read_text

    path = Path(path)
    text = read_text(path, AnnotatorError, "trajectory")
    try:
        rows = list(csv.reader(text.splitlines()))
    except csv.Error as e:
        raise AnnotatorError(f"{path}: not CSV ({e})") from None
    if not rows:
        raise AnnotatorError(f"{path}: empty file, expected a header '{','.join(POSE_COLUMNS)}'")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise AnnotatorError(f"{path}: header lacks column(s) {', '.join(missing)}")
    if len(set(header)) != len(header):
        raise AnnotatorError(f"{path}: header names a column twice")
    values: list[list[float]] = []
    for lineno, r in enumerate(rows[1:], 2):
        if not r:
            continue
        if len(r) != len(header):
            raise AnnotatorError(f"{path}:{lineno}: not {len(header)} numbers ({len(r)} fields)")
        try:
            values.append([float(c) for c in r])
        except ValueError:
            raise AnnotatorError(f"{path}:{lineno}: not {len(header)} numbers") from None
    data = np.array(values, dtype=float).reshape(-1, len(header))
    col = {h: data[:, i] for i, h in enumerate(header)}
    _check_columns(path, col)
    rot = np.stack([col[c] for c in POSE_COLUMNS[4:]], 1).reshape(-1, 3, 3)
    quality = {h: col[h] for h in header if h not in POSE_COLUMNS}
    return Trajectory(col["t"], np.stack([col["x"], col["y"], col["z"]], 1), rot, quality)


def _check_columns(path: Path, col: dict[str, np.ndarray]) -> None:
    def line(mask: np.ndarray) -> int:  # first offending row -> its line number (header = 1)
        return int(np.argmax(mask)) + 2

    t = col["t"]
    bad = ~np.isfinite(t) | (t < 0) | (t >= T_MAX_S)
    if bad.any():
        raise AnnotatorError(
            f"{path}:{line(bad)}: t must be Unix seconds in 1970..2100, not {t[bad][0]:g}"
        )
    if len(t) > 1 and np.any(np.diff(t) < 0):
        raise AnnotatorError(f"{path}:{line(np.r_[False, np.diff(t) < 0])}: column t is not sorted")
    for name in POSE_COLUMNS[1:]:
        v = col[name]
        limit = POSITION_MAX_M if name in ("x", "y", "z") else 1.0 + 1e-6
        bad = np.isinf(v) | (np.abs(np.nan_to_num(v)) > limit)
        if bad.any():
            raise AnnotatorError(
                f"{path}:{line(bad)}: {name} = {v[bad][0]:g} is out of range "
                f"(|{name}| <= {limit:g}; NaN marks a gap)"
            )
