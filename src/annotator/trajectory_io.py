"""trajectory.csv: ``t,x,y,z,r11..r33`` then optional quality columns; NaN rows are gaps.

R is R_world_bundle, row-major; t is wall-clock Unix seconds.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.errors import AnnotatorError

POSE_COLUMNS = ("t", "x", "y", "z", "r11", "r12", "r13", "r21", "r22", "r23", "r31", "r32", "r33")


@dataclass(frozen=True, eq=False)
class Trajectory:
    t: np.ndarray  # (N,) Unix seconds, sorted
    position: np.ndarray  # (N, 3) metres; NaN where no pose
    rotation: np.ndarray  # (N, 3, 3) R_world_bundle; NaN where no pose
    quality: dict[str, np.ndarray] = field(default_factory=dict)  # extra per-row columns

    def __len__(self) -> int:
        return len(self.t)

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.position).all(1) & np.isfinite(self.rotation).all((1, 2))


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
                cells.append("nan" if not math.isfinite(v) else (str(int(v)) if v == int(v) else f"{v:.6g}"))
            f.write(",".join(cells) + "\n")
    tmp.replace(path)


def read_trajectory(path: str | Path) -> Trajectory:
    path = Path(path)
    try:
        with path.open(encoding="utf-8", newline="") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise AnnotatorError(f"cannot read trajectory {path}: {e.strerror}") from None
    if not rows:
        raise AnnotatorError(f"{path}: empty file, expected a header '{','.join(POSE_COLUMNS)}'")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise AnnotatorError(f"{path}: header lacks column(s) {', '.join(missing)}")
    try:
        data = np.array([[float(c) for c in r] for r in rows[1:] if r], dtype=float).reshape(-1, len(header))
    except ValueError as e:
        line = next(i for i, r in enumerate(rows[1:], 2) if r and not _all_float(r, len(header)))
        raise AnnotatorError(f"{path}:{line}: not {len(header)} numbers ({e})") from None
    col = {h: data[:, i] for i, h in enumerate(header)}
    if len(data) > 1 and np.any(np.diff(col["t"]) < 0):
        raise AnnotatorError(f"{path}: column t is not sorted")
    rot = np.stack([col[c] for c in POSE_COLUMNS[4:]], 1).reshape(-1, 3, 3)
    quality = {h: col[h] for h in header if h not in POSE_COLUMNS}
    return Trajectory(col["t"], np.stack([col["x"], col["y"], col["z"]], 1), rot, quality)


def _all_float(row: list[str], n: int) -> bool:
    if len(row) != n:
        return False
    try:
        [float(c) for c in row]
    except ValueError:
        return False
    return True
