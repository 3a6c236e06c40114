"""The file side of the baseline localizers: radio maps (.grd folders) and RSSI readings in,
estimates CSV (the input of `annotator score`) out. The algorithms live in annotator.core.localize."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from annotator.core.localize import Estimates2D, RadioMapArrays, Readings, grid_hmm, knn
from annotator.errors import AnnotatorError, ConfigError, NoDataError

METHODS = ("knn", "grid-hmm")


def radiomap_beacons(grids: list) -> Counter:
    return Counter(b for g in grids for beacons in g.cells.values() for b in beacons)


def read_radiomap_grids(folder: str | Path) -> list:
    from bgt_core.formats.grd import read_grd
    from bgt_core.formats.occ import GridFormatError

    folder = Path(folder)
    if not folder.is_dir():
        raise AnnotatorError(f"radio map {folder}: not a folder of .grd files")
    files = sorted(folder.glob("*.grd"))
    if not files:
        raise NoDataError(f"radio map {folder}: no .grd files in it")
    try:
        grids = [read_grd(f) for f in files]
    except GridFormatError as e:
        raise AnnotatorError(str(e)) from None
    cells = {g.cell for g in grids}
    if len(cells) != 1 or len({g.bins for g in grids}) != 1:
        raise ConfigError(f"radio map {folder}: the .grd files mix cell sizes or bins")
    if len({g.sensor for g in grids}) != len(grids):
        raise ConfigError(f"radio map {folder}: two .grd files for the same sensor")
    return grids


def radiomap_arrays(
    grids: list, beacon: str, occupancy: str | Path | None = None, free_value: int = 0
) -> RadioMapArrays:
    """Stack the per-sensor grids for ``beacon`` into (C, S, K) over the cells any sensor maps,
    restricted to the free cells of ``occupancy`` when given."""
    keys = sorted(
        {c for g in grids for c, b in g.cells.items() if beacon in b}, key=lambda c: (c[1], c[0])
    )
    if not keys:
        raise NoDataError(f"the radio map has no cell for beacon {beacon}")
    cell = grids[0].cell
    if occupancy is not None:
        from bgt_core.formats.occ import GridFormatError, read_occ

        try:
            occ = read_occ(occupancy)
        except GridFormatError as e:
            raise AnnotatorError(str(e)) from None
        if abs(occ.cell - cell) > 1e-9:
            raise ConfigError(f"{occupancy}: {occ.cell} m cells, the radio map has {cell} m")
        free = {(round(x, 6), round(y, 6)) for (x, y), v in occ.cells.items() if v == free_value}
        keys = [c for c in keys if (round(c[0], 6), round(c[1], 6)) in free]
        if not keys:
            raise NoDataError(f"{occupancy}: no free cell of it is in the radio map")
    edges = np.asarray(grids[0].bins, dtype=float)
    k = len(edges) - 1
    hist = np.full((len(keys), len(grids), k), np.nan)
    for si, g in enumerate(grids):
        for ci, c in enumerate(keys):
            h = g.cells.get(c, {}).get(beacon)
            if h is not None:
                hist[ci, si] = h[:k]
    centres = np.asarray(keys, dtype=float) + cell / 2
    return RadioMapArrays(centres, tuple(g.sensor for g in grids), edges, hist, float(cell))


def reading_files(run: str | Path) -> list[Path]:
    """RSSI files of: a .mbd file; a collector run (rssi/*.mbd); an annotated run (annotated/);
    a published track folder (its per-sensor files) or any folder of .mbd files."""
    from annotator.io.radio_data import annotated_files

    run = Path(run)
    if run.is_dir():
        for sub in (run / "rssi", run / "annotated"):
            if sub.is_dir() and any(sub.glob("*.mbd")):
                return annotated_files([sub])
    if not run.exists():
        raise AnnotatorError(f"cannot read {run}: no such file or directory")
    return annotated_files([run])


def read_readings(
    run: str | Path, sensors: tuple[str, ...], beacon: str | None, map_beacons: Counter
) -> tuple[Readings, str]:
    from bgt_core.formats.tables import load_mbd

    df = load_mbd(reading_files(run))
    if beacon is None:
        heard = Counter(df["beacon"])
        both = [b for b, _ in heard.most_common() if b in map_beacons]
        if not both:
            raise NoDataError(f"{run}: no beacon of the readings is in the radio map")
        beacon = both[0]
    df = df[df["beacon"] == beacon].sort_values("t_ns", kind="stable")
    if not len(df):
        raise NoDataError(f"{run}: no readings of beacon {beacon}")
    index = {s: i for i, s in enumerate(sensors)}
    sensor = np.array([index.get(s, -1) for s in df["sensor"]], dtype=np.int64)
    if (sensor < 0).all():
        raise NoDataError(f"{run}: none of the sensors heard is in the radio map")
    return Readings(df["t_ns"].to_numpy() / 1e9, sensor, df["rssi"].to_numpy()), beacon


def localize_run(
    run: str | Path,
    radiomap: str | Path,
    method: str,
    *,
    beacon: str | None = None,
    occupancy: str | Path | None = None,
    k: int = 4,
    window_s: float = 2.0,
    step_s: float = 0.5,
    speed_mps: float = 1.0,
) -> tuple[Estimates2D, str]:
    if method not in METHODS:
        raise ConfigError(f"--method must be one of {', '.join(METHODS)}, not {method!r}")
    from bgt_core.wire import WireError, normalize_mac

    if beacon is not None:
        try:
            beacon = normalize_mac(beacon)
        except WireError as e:
            raise ConfigError(f"--beacon: {e}") from None
    grids = read_radiomap_grids(radiomap)
    map_beacons = radiomap_beacons(grids)
    sensors = tuple(g.sensor for g in grids)
    readings, beacon = read_readings(run, sensors, beacon, map_beacons)
    m = radiomap_arrays(grids, beacon, occupancy)
    if method == "knn":
        est = knn(m, readings, k=k, window_s=window_s, step_s=step_s)
    else:
        est = grid_hmm(m, readings, step_s=step_s, speed_mps=speed_mps)
    return est, beacon
