"""The file side of fingerprints and radio maps: finds and reads recordings, calls the pure stages
in annotator.core.fingerprints / annotator.core.radiomap, and writes .hst, .grd and heat-map PNGs."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.core import fingerprints as fp
from annotator.core import radiomap as rm
from annotator.errors import AnnotatorError, ConfigError, NoDataError
from bgt_core.formats.devices import Device, Devices, MapParams, read_dev, read_par
from bgt_core.formats.grd import RadioMapGrid, write_grd
from bgt_core.formats.hst import FingerprintHistograms, histograms_from_mapping, write_hst
from bgt_core.formats.occ import Occupancy, grid_corners
from bgt_core.formats.tables import hst_to_arrays, load_mbd, occ_to_mask
from bgt_core.sites import site_dir

log = logging.getLogger(__name__)

Progress = Callable[[int], None]  # called with the number of work items just finished
ALL_SENSORS_SUFFIX = "all_sensors.mbd"


def _noop(_: int) -> None:
    pass


# ---------------------------------------------------------------------------------------------
# Inputs


def _mbd_in(path: Path) -> list[Path]:
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.suffix == ".mbd" and p.is_file())
    if path.is_file():
        return [path]
    raise FileNotFoundError(f"no such file or directory: {path}")


def stationary_files(
    paths: Iterable[str | Path],
) -> list[tuple[Path, str, tuple[float, float, float]]]:
    """Every ``<alias>_<x>_<y>_<z>.mbd`` under ``paths`` (files or directories, not recursive),
    with its alias and position. A file whose name does not follow the pattern is an error."""
    out = []
    for p in paths:
        for f in _mbd_in(Path(p)):
            try:
                alias, pos = fp.parse_fingerprint_name(f.name)
            except ValueError:
                raise ConfigError(
                    f"{f}: fingerprint files must be named '<alias>_<x>_<y>_<z>.mbd'"
                ) from None
            out.append((f, alias, pos))
    if not out:
        raise NoDataError(f"no .mbd files in {', '.join(str(p) for p in paths)}")
    return out


def annotated_files(paths: Iterable[str | Path]) -> list[Path]:
    """Track .mbd files under ``paths``. In a directory the merged ``*all_sensors.mbd`` repeats the
    per-sensor files' rows, so it is read only when it is the directory's only file."""
    out: list[Path] = []
    for p in paths:
        files = _mbd_in(Path(p))
        if Path(p).is_dir():
            per_sensor = [f for f in files if not f.name.endswith(ALL_SENSORS_SUFFIX)]
            files = per_sensor or files
        out.extend(files)
    if not out:
        raise NoDataError(f"no .mbd files in {', '.join(str(p) for p in paths)}")
    return out


def builtin_devices(name: str = "tetam") -> Devices:
    return read_dev(site_dir(name) / f"{name}.dev")


def site_occupancy(name: str = "tetam", cell: float = 0.5) -> Occupancy:
    """The occupancy grid shipped with a built-in site (tetam: the published 0.5 m grid)."""
    from bgt_core.formats.occ import read_occ

    return read_occ(site_dir(name) / f"{name}_{cell:g}.occ")


def _complete_devices(
    given: Devices | None, seen_sensors: dict[str, str], seen_beacons: Iterable[str]
) -> Devices:
    """The devices written into the .hst: the given file's (or the built-in tetam site's when it
    knows every sensor seen, or every beacon seen as one of its sensors: receiver mode, with
    beacons at the sensors' places), plus anything seen in the data but not listed there. A
    beacon that the devices list as a sensor keeps that sensor's position and alias."""
    seen_beacons = set(seen_beacons)
    base = given
    if base is None:
        tetam = builtin_devices()
        known = set(tetam.dongles)
        base = tetam if set(seen_sensors) <= known or seen_beacons <= known else Devices({}, {})
    dongles = dict(base.dongles)
    for mac, alias in seen_sensors.items():
        if mac not in dongles:
            if given is not None:
                log.warning(
                    "sensor %s (%s) is not in the devices file; listed without a position",
                    mac,
                    alias,
                )
            dongles[mac] = Device(mac, (), 0, alias)
    beacons = dict(base.beacons)
    for i, mac in enumerate(sorted(seen_beacons - set(beacons)), len(beacons) + 1):
        fixed = base.dongles.get(mac)
        beacons[mac] = fixed if fixed is not None else Device(mac, (), 0, f"beacon{i}")
    return Devices(dongles, beacons)


def _beacon_filter(devices: Devices | None) -> set[str] | None:
    # An explicit devices file that lists beacons restricts the fingerprints to them (a capture
    # also hears phones and other people's tags); without one every beacon is kept. Its sensors
    # count too: in receiver mode the site's fixed devices are the beacons heard.
    if devices is not None and devices.beacons:
        return set(devices.beacons) | set(devices.dongles)
    return None


# ---------------------------------------------------------------------------------------------
# Fingerprints


@dataclass(frozen=True, slots=True)
class FingerprintResult:
    histograms: FingerprintHistograms
    files: int
    readings: int  # rows read
    used: int  # readings inside the bin range that went into a histogram


def stationary_fingerprints(
    paths: Sequence[str | Path],
    edges: np.ndarray,
    devices: Devices | None = None,
    progress: Progress = _noop,
) -> FingerprintResult:
    """Normalised per-position, per-sensor, per-beacon histograms of stationary recordings.
    Files for the same position and sensor (e.g. two sessions) are pooled before normalising."""
    files = stationary_files(paths)
    wanted = _beacon_filter(devices)
    counts: dict[tuple[float, float, float], dict[str, dict[str, np.ndarray]]] = {}
    seen_sensors: dict[str, str] = {}
    seen_beacons: set[str] = set()
    rows = 0
    for f, alias, pos in files:
        df = load_mbd(f)
        if "x" in df.columns:
            raise ConfigError(
                f"{f}: rows carry positions, so this is an annotated track, not a "
                "stationary recording; use --from-annotated"
            )
        rows += len(df)
        for (s, b), g in df.groupby(["sensor", "beacon"], sort=True):
            if wanted is not None and b not in wanted:
                continue
            seen_sensors.setdefault(s, alias)
            seen_beacons.add(b)
            per = counts.setdefault(pos, {}).setdefault(s, {})
            per[b] = per.get(b, 0) + fp.counts(g["rssi"].to_numpy(), edges)
        progress(1)
    table, used = _normalised(counts)
    if not table:
        raise NoDataError(
            f"no readings inside {edges[0]:g}..{edges[-1]:g} dBm in {len(files)} files"
        )
    h = histograms_from_mapping(
        edges, _complete_devices(devices, seen_sensors, seen_beacons), table
    )
    return FingerprintResult(h, len(files), rows, used)


def _normalised(counts: dict) -> tuple[dict, int]:
    table: dict = {}
    used = 0
    for pos in sorted(counts):
        for s in sorted(counts[pos]):
            for b in sorted(counts[pos][s]):
                c = counts[pos][s][b]
                if c.sum() == 0:
                    log.info("%s %s %s: no readings in the bin range; left out", pos, s, b)
                    continue
                used += int(c.sum())
                table.setdefault(pos, {}).setdefault(s, {})[b] = fp.normalise(c)
    return table, used


def annotated_fingerprints(
    paths: Sequence[str | Path],
    edges: np.ndarray,
    cell: float,
    devices: Devices | None = None,
    *,
    min_readings: int = 1,
    origin: tuple[float, float] = (0.0, 0.0),
    progress: Progress = _noop,
) -> FingerprintResult:
    """Fingerprints from moving, position-annotated captures: readings binned into grid cells of
    ``cell`` metres (anchored at ``origin``); each occupied cell becomes a reference position at
    its centre (height: median of the readings' z there). A (cell, sensor, beacon) histogram
    needs at least ``min_readings`` in-range readings."""
    files = annotated_files(paths)
    frames = []
    for f in files:
        frames.append(load_mbd(f))
        progress(1)
    import pandas as pd

    df = pd.concat(frames, ignore_index=True)
    if "x" not in df.columns:
        raise NoDataError(
            f"{files[0]}: rows carry no positions; --from-annotated needs "
            "annotated track files (ts,sensor,beacon,rssi,x,y,z,...)"
        )
    wanted = _beacon_filter(devices)
    if wanted is not None:
        df = df[df["beacon"].isin(wanted)]
    bins = fp.bin_to_cells(df[["x", "y"]].to_numpy(), cell, origin)
    if not len(bins.keys):
        raise NoDataError("no annotated readings with a position")
    z = df["z"].to_numpy()
    heights = np.array([np.nanmedian(z[bins.inverse == i]) for i in range(len(bins.keys))])
    centres = (np.asarray(origin) + (bins.keys + 0.5) * cell).round(6)
    counts: dict = {}
    for (s, b), g in df.groupby(["sensor", "beacon"], sort=True):
        idx = g.index.to_numpy()
        c = fp.cell_counts(g["rssi"].to_numpy(), bins.inverse[idx], len(bins.keys), edges)
        for i in np.flatnonzero(c.sum(axis=1) >= max(min_readings, 1)):
            pos = (float(centres[i, 0]), float(centres[i, 1]), float(round(heights[i], 2)))
            counts.setdefault(pos, {}).setdefault(s, {})[b] = c[i]
    table, used = _normalised(counts)
    if not table:
        raise NoDataError(f"no cell has {min_readings} or more readings inside the bin range")
    seen_sensors = {s: s for s in df["sensor"].unique()}
    h = histograms_from_mapping(
        edges, _complete_devices(devices, seen_sensors, df["beacon"].unique()), table
    )
    return FingerprintResult(h, len(files), len(df), used)


def save_fingerprints(result: FingerprintResult, out: str | Path) -> Path:
    out = Path(out)
    if not out.parent.is_dir():
        raise AnnotatorError(f"{out}: the folder {out.parent} does not exist")
    write_hst(result.histograms, out)
    return out


# ---------------------------------------------------------------------------------------------
# Radio maps


@dataclass(frozen=True, slots=True)
class Grid:
    limits: tuple[tuple[float, float], tuple[float, float]]
    cell: float
    xs: np.ndarray  # lower-left corners
    ys: np.ndarray
    mask: np.ndarray  # [iy, ix] True = compute this cell


@dataclass(frozen=True, slots=True)
class Site:
    """Floor plan and its pixel geometry, when the fingerprints come from a known built-in site."""

    name: str
    params: MapParams
    floor_plan: Path


def detect_site(devices: Devices) -> Site | None:
    """The built-in tetam site when the .hst lists exactly its sensors."""
    tetam = builtin_devices()
    if devices.dongles and set(devices.dongles) == set(tetam.dongles):
        d = site_dir("tetam")
        return Site("tetam", read_par(d / "tetam.par"), d / "tetam.png")
    return None


def make_grid(
    h: FingerprintHistograms,
    cell: float | None,
    occupancy: Occupancy | None,
    site: Site | None,
    *,
    free_value: int = 0,
) -> Grid:
    """The cells to compute: an occupancy grid's cells whose value is ``free_value`` (0 in the
    published files, see bgt_core.formats.occ), or every cell of the site's / the data's
    extent in ``cell`` metre steps."""
    if occupancy is not None:
        if cell is not None and abs(cell - occupancy.cell) > 1e-9:
            raise ConfigError(
                f"--cell {cell} does not match the occupancy grid's {occupancy.cell} m cells"
            )
        try:
            xs, ys, mask = occ_to_mask(occupancy, free_value)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        return Grid(occupancy.limits, occupancy.cell, xs, ys, mask)
    if cell is None or not cell > 0:
        raise ConfigError("give --cell (metres) or an --occupancy grid")
    if site is not None:
        x0, y0, x1, y1 = site.params.limits
        limits = ((x0, y0), (x1, y1))
    else:
        pts: list[Sequence[float]] = [p[:2] for p in h.fingerprints]
        pts += [d.position[:2] for d in h.devices.dongles.values() if len(d.position) >= 2]
        if not pts:
            raise NoDataError("the fingerprint file holds no fingerprints")
        a = np.asarray(pts, dtype=float)
        lo = np.floor(a.min(axis=0) / cell) * cell
        hi = a.max(axis=0)
        hi = np.where(hi > lo, hi, lo + cell)
        limits = ((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
    x_lo, y_lo = grid_corners(limits, cell)
    return Grid(
        limits,
        float(cell),
        np.asarray(x_lo),
        np.asarray(y_lo),
        np.ones((len(y_lo), len(x_lo)), dtype=bool),
    )


@dataclass(frozen=True, slots=True)
class SensorMap:
    grid: RadioMapGrid
    mean: np.ndarray  # [iy, ix] mean RSSI over beacons (NaN outside the mask)
    # [iy, ix] mean RSSI of each beacon on its own (a receiver hearing wall beacons: one map each)
    beacon_means: dict[str, np.ndarray] = field(default_factory=dict)


def radio_maps(
    h: FingerprintHistograms,
    grid: Grid,
    *,
    neighbours: int = 4,
    power: float = 2.0,
    progress: Progress = _noop,
) -> list[SensorMap]:
    """One radio map per sensor in the .hst: every masked cell's histogram per beacon."""
    positions, sensors, beacons, p = hst_to_arrays(h)
    if not len(positions):
        raise NoDataError("the fingerprint file holds no fingerprints")
    edges = np.asarray(h.bins)
    iy, ix = np.nonzero(grid.mask)  # row-major: y outer, x inner
    targets = np.column_stack([grid.xs[ix] + grid.cell / 2, grid.ys[iy] + grid.cell / 2])
    out = []
    for si, s in enumerate(sensors):
        per_beacon = {}
        for bi, b in enumerate(beacons):
            hist = rm.interpolate(
                positions[:, :2], p[:, si, bi], targets, edges, neighbours=neighbours, power=power
            )
            if np.isfinite(hist).all(axis=1).any():
                per_beacon[b] = hist
        cells: dict = {}
        for m in range(len(targets)):
            key = (float(grid.xs[ix[m]]), float(grid.ys[iy[m]]))
            for b, hist in per_beacon.items():
                if np.isfinite(hist[m]).all():
                    cells.setdefault(key, {})[b] = tuple(float(v) for v in hist[m])
        mean = np.full(grid.mask.shape, np.nan)
        beacon_means = {}
        if per_beacon:
            means = np.stack([rm.mean_rssi(hh, edges) for hh in per_beacon.values()])
            ok = np.isfinite(means)
            n = ok.sum(axis=0)
            mean[iy, ix] = np.where(
                n > 0, np.where(ok, means, 0.0).sum(axis=0) / np.maximum(n, 1), np.nan
            )
            for b, row in zip(per_beacon, means, strict=True):
                beacon_means[b] = np.full(grid.mask.shape, np.nan)
                beacon_means[b][iy, ix] = row
        out.append(
            SensorMap(
                RadioMapGrid(s, grid.limits, grid.cell, tuple(h.bins), cells), mean, beacon_means
            )
        )
        progress(1)
    return out


def cell_label(cell: float) -> str:
    return repr(float(cell))


def write_radio_maps(
    maps: Sequence[SensorMap],
    h: FingerprintHistograms,
    grid: Grid,
    out_dir: str | Path,
    stem: str,
    *,
    plots: bool = True,
    site: Site | None = None,
    progress: Progress = _noop,
) -> list[Path]:
    """``<stem>_<sensor>_<cell>.grd`` (and ``.png`` heat map) per sensor in ``out_dir``; for a
    sensor that hears several beacons (a receiver on the bundle) also ``..._beacons.png``, one
    panel per beacon."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    sensors_xy = {
        m: (d.position[0], d.position[1])
        for m, d in h.devices.dongles.items()
        if len(d.position) >= 2
    }
    fps = np.array([p[:2] for p in h.fingerprints], dtype=float)
    for m in maps:
        # not Path.with_suffix: the cell size ("0.5") already contains a dot
        base = f"{stem}_{m.grid.sensor}_{cell_label(grid.cell)}"
        grd_path, png_path = out_dir / f"{base}.grd", out_dir / f"{base}.png"
        write_grd(m.grid, grd_path)
        written.append(grd_path)
        if plots:
            from annotator.plots.radiomap import plot_mean_rssi

            alias = h.devices.dongles.get(m.grid.sensor)
            name = alias.alias if alias is not None else m.grid.sensor
            plot_mean_rssi(
                png_path,
                grid.xs,
                grid.ys,
                grid.cell,
                m.mean,
                title=f"{name} ({m.grid.sensor}): mean RSSI, {grid.cell:g} m cells",
                sensors=sensors_xy,
                highlight=m.grid.sensor,
                fingerprints=fps,
                floor_plan=site.floor_plan if site else None,
                params=site.params if site else None,
            )
            written.append(png_path)
            if len(m.beacon_means) > 1:  # a receiver hearing several beacons: a map of each
                from annotator.plots.radiomap import plot_beacon_maps

                where = {
                    mac: (d.position[0], d.position[1])
                    for mac, d in [*h.devices.dongles.items(), *h.devices.beacons.items()]
                    if len(d.position) >= 2
                }
                names = {mac: d.alias for mac, d in h.devices.dongles.items()}
                beacons_png = out_dir / f"{base}_beacons.png"
                plot_beacon_maps(
                    beacons_png,
                    grid.xs,
                    grid.ys,
                    grid.cell,
                    m.beacon_means,
                    title=f"{name}: mean RSSI of each beacon heard, {grid.cell:g} m cells",
                    positions=where,
                    names=names,
                )
                written.append(beacons_png)
        progress(1)
    return written
