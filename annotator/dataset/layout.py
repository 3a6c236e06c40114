"""The published layout of a dataset, written from a campaign and its runs' results.

    cnf/<site>.dev, cnf/<site>.par          the site files, as given
    map/<plan>.png                          the floor plan
    vid/marker_positions.dat                the marker map as the first run refined it
    trk/<run>/<alias>_0.00_0.00_0.00.mbd    each sensor's labelled readings of the run
    trk/<run>_all_sensors.mbd, trk/<run>.png
    runs/<run>/                             report.json, trajectory.csv and the run's plots
    fpt/                                    the stationary recordings, as given
    hst/set_1/<site>_multi_rssi.hst         their fingerprint histograms
    grd/<site>_<sensor>_<cell>.grd          radio maps, one per sensor and cell size
    occ/<site>_<cell>.occ, .png             occupancy grids from the floor plan
    parquet/readings|trajectories|fingerprints.parquet
    README.md                               the datasheet
    SHA256SUMS                              every file's SHA-256

Everything here is a function of the campaign and the runs' results, in a fixed order, so the
same inputs give the same bytes whatever the cluster did.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.campaign import Campaign
from annotator.dataset.runs import RunDone
from annotator.io.report_records import read_report
from bgt_core.formats.devices import Devices, MapParams

TRACK_POSITION = "0.00_0.00_0.00"  # a moving track's files carry no fixed position
VOLATILE_REPORT_KEYS = (("refinement", "seconds"), ("refinement", "timing"))


def copy(src: Path, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return dst


def clean_report(report: Mapping[str, Any], name: str) -> dict[str, Any]:
    """A run's report.json for publication: the experiment named by the run, not by a path of
    the machine that built it, and no timings (they differ from build to build)."""
    out = json.loads(json.dumps(report))
    out["experiment"] = name
    for section, key in VOLATILE_REPORT_KEYS:
        if isinstance(out.get(section), dict):
            out[section].pop(key, None)
    return out


def write_tracks(out: Path, run: RunDone, devices: Devices) -> dict[str, Any]:
    """trk/ and runs/ of one run; returns its cleaned report."""
    res = run.results
    annotated = res / "annotated"
    trk = out / "trk" / run.name
    for f in sorted(annotated.glob("*.mbd")):
        if f.name == "all_sensors.mbd":
            copy(f, out / "trk" / f"{run.name}_all_sensors.mbd")
            continue
        dongle = devices.dongles.get(f.stem)
        alias = dongle.alias if dongle is not None and dongle.alias else f.stem
        copy(f, trk / f"{alias}_{TRACK_POSITION}.mbd")
    if (res / "trajectory_map.png").is_file():
        copy(res / "trajectory_map.png", out / "trk" / f"{run.name}.png")
    report = clean_report(read_report(res / "report.json"), run.name)
    dest = out / "runs" / run.name
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "report.json").write_text(json.dumps(report, indent=1, sort_keys=True), "utf-8")
    for f in sorted(res.glob("*.png")) + [res / "trajectory.csv"]:
        if f.is_file():
            copy(f, dest / f.name)
    return report


def write_occupancy(
    out: Path, plan: np.ndarray, params: MapParams, site: str, cells: tuple[float, ...]
) -> dict[float, Any]:
    """occ/<site>_<cell>.occ and a picture of each (occupied dark red, free white)."""
    import cv2

    from annotator.core.occupancy import occupancy_from_plan
    from bgt_core.formats.occ import grid_corners, write_occ

    grids = {}
    (out / "occ").mkdir(parents=True, exist_ok=True)
    for cell in cells:
        occ = occupancy_from_plan(plan, params, cell)
        write_occ(occ, out / "occ" / f"{site}_{float(cell)!r}.occ")
        xs, ys = grid_corners(occ.limits, cell)
        row = {x: i for i, x in enumerate(xs)}
        col = {y: j for j, y in enumerate(ys)}
        px = max(4, int(round(cell / params.parity)))
        img = np.full((len(xs) * px, len(ys) * px, 3), 255, np.uint8)
        for (gx, gy), v in occ.cells.items():
            i, j = row[gx], col[gy]
            if v:
                img[i * px : (i + 1) * px, j * px : (j + 1) * px] = (40, 40, 190)
        img[::px, :] = 200
        img[:, ::px] = 200
        cv2.imwrite(str(out / "occ" / f"{site}_occ_{float(cell)!r}.png"), img)
        grids[cell] = occ
    return grids


def write_parquet_tables(out: Path, runs: list[RunDone], hst: Any | None) -> dict[str, int]:
    """parquet/: every run's labelled readings and trajectory rows (with a `run` column and the
    quality columns), and the fingerprint histograms in long form."""
    import pandas as pd

    from annotator.io.trajectory import read_trajectory

    folder = out / "parquet"
    folder.mkdir(parents=True, exist_ok=True)
    readings, trajectories = [], []
    for run in runs:
        df = pd.read_parquet(run.results / "annotated.parquet")
        df.insert(0, "run", run.name)
        readings.append(df)
        traj = read_trajectory(run.results / "trajectory.csv")
        t = pd.DataFrame(
            {
                "run": run.name,
                "t": traj.t,
                "x": traj.position[:, 0],
                "y": traj.position[:, 1],
                "z": traj.position[:, 2],
                "valid": traj.valid,
            }
        )
        for k, v in traj.quality.items():
            v = np.asarray(v)
            if v.ndim == 1 and len(v) == len(traj.t):
                t[k] = v
        trajectories.append(t)
    counts = {}
    for name, frames in (("readings", readings), ("trajectories", trajectories)):
        table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
        table.to_parquet(folder / f"{name}.parquet", index=False)
        counts[name] = len(table)
    if hst is not None:
        rows = []
        edges = list(hst.bins)
        for pos, per_sensor in hst.fingerprints.items():
            for sensor, per_beacon in per_sensor.items():
                for beacon, probs in per_beacon.items():
                    for b, p in enumerate(probs):
                        if p:
                            rows.append((*pos, sensor, beacon, edges[b], float(p)))
        cols = ["x", "y", "z", "sensor", "beacon", "rssi_bin", "probability"]
        fp = pd.DataFrame(rows, columns=cols)
        fp.to_parquet(folder / "fingerprints.parquet", index=False)
        counts["fingerprints"] = len(fp)
    return counts


def write_manifest(out: Path) -> Path:
    """SHA256SUMS: one `<hex>  <path>` line per file, sorted by path (sha256sum -c reads it)."""
    lines = []
    for f in sorted(p for p in out.rglob("*") if p.is_file() and p.name != "SHA256SUMS"):
        digest = hashlib.sha256(f.read_bytes()).hexdigest()
        lines.append(f"{digest}  {f.relative_to(out).as_posix()}\n")
    path = out / "SHA256SUMS"
    path.write_text("".join(lines), "utf-8")
    return path


def site_files(out: Path, campaign: Campaign) -> None:
    site = campaign.site
    copy(site.devices, out / "cnf" / site.devices.name)
    copy(site.par, out / "cnf" / site.par.name)
    copy(site.plan, out / "map" / site.plan.name)
