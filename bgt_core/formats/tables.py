"""pandas / numpy views of the dataset formats: .mbd rows as DataFrames (and back), and
.hst / .grd / .occ as tidy frames or arrays. pandas and numpy are imported inside the functions,
so importing this module costs nothing on a sensor agent."""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from bgt_core.formats._textio import write_text_atomic
from bgt_core.formats.devices import Devices
from bgt_core.formats.grd import RadioMapGrid
from bgt_core.formats.hst import FingerprintHistograms, histograms_from_mapping
from bgt_core.formats.mbd import TRACK_COLUMNS, MbdError, iter_rows
from bgt_core.formats.occ import Occupancy, grid_corners
from bgt_core.wire import format_ts

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

POSE_COLUMNS = TRACK_COLUMNS[4:]  # x, y, z, r11 .. r33
ROTATION_COLUMNS = TRACK_COLUMNS[7:]
# Largest |R^T R - I| entry and |det R - 1| accepted as "a rotation" when writing tracks.
ROTATION_TOLERANCE = 1e-6


def _as_paths(paths: str | Path | Iterable[str | Path]) -> list[Path]:
    if isinstance(paths, str | Path):
        return [Path(paths)]
    return [Path(p) for p in paths]


def load_mbd(paths: str | Path | Iterable[str | Path]) -> pd.DataFrame:
    """Rows of one or more .mbd files, in file order, as a DataFrame.

    Columns: ``ts`` (float Unix seconds, for plotting and arithmetic), ``t_ns`` (int64, exact),
    ``sensor``, ``beacon`` (MACs), ``rssi`` (int) and, when any row carries a pose, ``x, y, z,
    r11 .. r33`` (float; NaN on rows without one). A row with neither 4 nor 16 fields is an
    :class:`MbdError` naming the file and line.
    """
    import numpy as np
    import pandas as pd

    t_ns: list[int] = []
    sensor: list[str] = []
    beacon: list[str] = []
    rssi: list[int] = []
    poses: list[tuple[float, ...] | None] = []
    any_pose = False
    for path in _as_paths(paths):
        try:
            for n, row in enumerate(iter_rows(path), 1):
                t_ns.append(row.t_ns)
                sensor.append(row.sensor)
                beacon.append(row.beacon)
                rssi.append(row.rssi)
                if not row.rest:
                    poses.append(None)
                    continue
                if len(row.rest) != len(POSE_COLUMNS):
                    raise MbdError(
                        f"{path}: row {n}: expected 4 or {len(TRACK_COLUMNS)} fields, "
                        f"got {4 + len(row.rest)}"
                    )
                try:
                    pose = tuple(float(v) for v in row.rest)
                except ValueError:
                    raise MbdError(f"{path}: row {n}: pose fields must be numbers") from None
                if not all(map(math.isfinite, pose)):
                    # a track row always carries a pose (writers skip rows without one)
                    raise MbdError(f"{path}: row {n}: pose fields must be finite numbers")
                poses.append(pose)
                any_pose = True
        except OSError as e:
            raise MbdError(f"cannot read {path}: {e.strerror}") from None
    t = np.array(t_ns, dtype=np.int64)
    df = pd.DataFrame(
        {
            "ts": t / 1e9,
            "t_ns": t,
            "sensor": pd.Series(sensor, dtype=object),
            "beacon": pd.Series(beacon, dtype=object),
            "rssi": np.array(rssi, dtype=np.int64),
        }
    )
    if any_pose:
        nan_row = (math.nan,) * len(POSE_COLUMNS)
        pose_arr = np.array([p if p is not None else nan_row for p in poses], dtype=float)
        for i, name in enumerate(POSE_COLUMNS):
            df[name] = pose_arr[:, i]
    return df


def _ts_text(t_ns: int) -> str:
    # Shortest exact spelling: the published files write 1581249601.4086823, not ...682300.
    text = format_ts(int(t_ns)).rstrip("0")
    return text + "0" if text.endswith(".") else text


def rotation_problems(r: np.ndarray, tol: float = ROTATION_TOLERANCE) -> np.ndarray:
    """Boolean mask of the (N, 3, 3) matrices that are not proper rotations (within ``tol``)."""
    import numpy as np

    r = np.asarray(r, dtype=float).reshape(-1, 3, 3)
    ortho = np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(r)
    ok: np.ndarray = (ortho <= tol) & (np.abs(det - 1.0) <= tol)
    return ~ok


def write_track_mbd(
    df: pd.DataFrame,
    path: str | Path,
    *,
    rotations: Literal["require", "project", "keep"] = "require",
) -> int:
    """Write track rows ``ts,sensor,beacon,rssi,x,y,z,r11..r33``; returns the number written.

    ``rotations``: ``"require"`` (default) refuses to write a matrix that is not a rotation
    (``ValueError`` naming the first bad row); ``"project"`` replaces every matrix by the nearest
    rotation (``scipy.spatial.transform.Rotation``); ``"keep"`` writes what it is given, which is
    only for reproducing published files byte for byte. Rows without a pose (NaN) are skipped:
    a track row always carries one. Timestamps come from ``t_ns`` (exact).
    """
    import numpy as np

    missing = [
        c for c in ("t_ns", "sensor", "beacon", "rssi", *POSE_COLUMNS) if c not in df.columns
    ]
    if missing:
        raise ValueError(f"{path}: cannot write a track file without columns {missing}")
    pose = df[POSE_COLUMNS].to_numpy(dtype=float)
    keep = np.isfinite(pose).all(axis=1)
    pose = pose[keep]
    rot = pose[:, 3:].reshape(-1, 3, 3)
    if rotations == "project" and len(rot):
        from scipy.spatial.transform import Rotation

        bad_det = np.linalg.det(rot) <= 0
        if bad_det.any():
            first = int(np.flatnonzero(keep)[np.argmax(bad_det)])
            raise ValueError(
                f"{path}: row {first}: orientation has det <= 0, no rotation is near it"
            )
        rot = Rotation.from_matrix(rot).as_matrix()
        pose[:, 3:] = rot.reshape(-1, 9)
    elif rotations == "require":
        bad = rotation_problems(rot)
        if bad.any():
            first = int(np.flatnonzero(keep)[np.argmax(bad)])
            raise ValueError(
                f"{path}: row {first}: orientation is not a rotation matrix "
                f"(use rotations='project' to replace it by the nearest one)"
            )
    elif rotations not in ("keep", "project"):
        raise ValueError(f"rotations must be 'require', 'project' or 'keep', not {rotations!r}")
    sub = df.loc[keep]
    lines = [
        f"{_ts_text(t)},{s},{b},{int(r)}," + ",".join(repr(float(v)) for v in p) + "\n"
        for t, s, b, r, p in zip(
            sub["t_ns"], sub["sensor"], sub["beacon"], sub["rssi"], pose, strict=True
        )
    ]
    write_text_atomic(Path(path), "".join(lines))
    return len(lines)


def write_mbd(df: pd.DataFrame, path: str | Path) -> int:
    """Write fingerprint-style rows ``ts,sensor,beacon,rssi`` (pose columns, if any, are dropped).
    Timestamps get nine decimals, as in the published fpt/ files and the collector's output."""
    lines = [
        f"{format_ts(int(t))},{s},{b},{int(r)}\n"
        for t, s, b, r in zip(df["t_ns"], df["sensor"], df["beacon"], df["rssi"], strict=True)
    ]
    write_text_atomic(Path(path), "".join(lines))
    return len(lines)


# ---------------------------------------------------------------------------------------------
# .hst / .grd / .occ


def hst_to_frame(h: FingerprintHistograms) -> pd.DataFrame:
    """Tidy form: one row per (position, sensor, beacon, bin) with ``x, y, z, sensor, beacon,
    rssi_lo, rssi_hi, p``."""
    import numpy as np
    import pandas as pd

    lo, hi = np.asarray(h.bins[:-1]), np.asarray(h.bins[1:])
    parts = []
    for (x, y, z), sensors in h.fingerprints.items():
        for s, beacons in sensors.items():
            for b, p in beacons.items():
                parts.append(
                    pd.DataFrame(
                        {
                            "x": x,
                            "y": y,
                            "z": z,
                            "sensor": s,
                            "beacon": b,
                            "rssi_lo": lo,
                            "rssi_hi": hi,
                            "p": np.asarray(p),
                        }
                    )
                )
    cols = ["x", "y", "z", "sensor", "beacon", "rssi_lo", "rssi_hi", "p"]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=cols)


def hst_from_frame(
    df: pd.DataFrame, bins: Iterable[float], devices: Devices
) -> FingerprintHistograms:
    """Inverse of :func:`hst_to_frame` (rows of one histogram must be in bin order)."""
    table: dict[Iterable[float], dict[str, dict[str, Iterable[float]]]] = {}
    for (x, y, z, s, b), g in df.groupby(["x", "y", "z", "sensor", "beacon"], sort=False):
        table.setdefault((x, y, z), {}).setdefault(s, {})[b] = g.sort_values("rssi_lo")[
            "p"
        ].to_numpy()
    return histograms_from_mapping(bins, devices, table)


def hst_to_arrays(h: FingerprintHistograms) -> tuple[np.ndarray, list[str], list[str], np.ndarray]:
    """``positions (N, 3)``, ``sensors``, ``beacons`` and ``P (N, S, B, K)`` with NaN rows where a
    position has no histogram for a sensor/beacon pair."""
    import numpy as np

    positions = np.array(list(h.fingerprints), dtype=float).reshape(-1, 3)
    sensors = sorted({s for v in h.fingerprints.values() for s in v})
    beacons = sorted({b for v in h.fingerprints.values() for bs in v.values() for b in bs})
    p = np.full((len(positions), len(sensors), len(beacons), len(h.bins) - 1), np.nan)
    si = {s: i for i, s in enumerate(sensors)}
    bi = {b: i for i, b in enumerate(beacons)}
    for n, per_sensor in enumerate(h.fingerprints.values()):
        for s, per_beacon in per_sensor.items():
            for b, hist in per_beacon.items():
                p[n, si[s], bi[b]] = hist
    return positions, sensors, beacons, p


def grd_to_frame(g: RadioMapGrid) -> pd.DataFrame:
    """Tidy form: ``gx, gy, beacon, rssi_lo, rssi_hi, p`` (one row per cell, beacon and bin)."""
    import numpy as np
    import pandas as pd

    lo, hi = np.asarray(g.bins[:-1]), np.asarray(g.bins[1:])
    parts = [
        pd.DataFrame(
            {"gx": gx, "gy": gy, "beacon": b, "rssi_lo": lo, "rssi_hi": hi, "p": np.asarray(p)}
        )
        for (gx, gy), beacons in g.cells.items()
        for b, p in beacons.items()
    ]
    cols = ["gx", "gy", "beacon", "rssi_lo", "rssi_hi", "p"]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=cols)


def occ_to_frame(occ: Occupancy) -> pd.DataFrame:
    import pandas as pd

    return pd.DataFrame(
        {
            "gx": [c[0] for c in occ.cells],
            "gy": [c[1] for c in occ.cells],
            "value": list(occ.cells.values()),
        }
    )


def occ_to_mask(occ: Occupancy, value: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``xs, ys`` (lower-left corners) and ``mask[iy, ix]``: True where the cell's value is
    ``value``. Cells the file does not list are False."""
    import numpy as np

    xs, ys = grid_corners(occ.limits, occ.cell)
    mask = np.zeros((len(ys), len(xs)), dtype=bool)
    ix = {round(x, 6): i for i, x in enumerate(xs)}
    iy = {round(y, 6): i for i, y in enumerate(ys)}
    for (gx, gy), v in occ.cells.items():
        i, j = ix.get(round(gx, 6)), iy.get(round(gy, 6))
        if i is None or j is None:
            raise ValueError(
                f"occupancy cell [{gx}, {gy}] is not on the {occ.cell} m grid of its own limits"
            )
        mask[j, i] = v == value
    return np.asarray(xs), np.asarray(ys), mask


def mask_to_occ(
    xs: Iterable[float],
    ys: Iterable[float],
    mask: np.ndarray,
    limits: tuple[tuple[float, float], tuple[float, float]],
    cell: float,
) -> Occupancy:
    """Inverse of :func:`occ_to_mask` with ``value=1`` (row-major: x fastest, then y)."""
    cells = {
        (float(x), float(y)): int(bool(mask[j, i]))
        for j, y in enumerate(ys)
        for i, x in enumerate(xs)
    }
    return Occupancy(limits, float(cell), cells)
