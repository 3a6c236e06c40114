"""Speed of the dataset readers, fingerprinting and radio-map interpolation; prints figures.

    python bench/bench_radiomap.py [--cell 0.5] [--positions 81] [--sensors 12]

Reads the bundled dataset subset (tests/data/dataset) and synthesises a published-size
fingerprint set (81 positions x 12 sensors on the tetam floor) for the radio map.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from annotator.core import radiomap as rm
from annotator.core.fingerprints import rssi_edges
from annotator.io import radio_data
from bgt_core.formats import hst, tables
from bgt_core.formats.occ import read_occ

ROOT = Path(__file__).resolve().parents[1]
DATASET = ROOT / "tests" / "data" / "dataset"


def timed(fn, *args, repeat: int = 3, **kw):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--positions", type=int, default=81)
    ap.add_argument("--sensors", type=int, default=12)
    args = ap.parse_args()

    fpt = sorted((DATASET / "fpt").glob("*.mbd"))
    t, df = timed(tables.load_mbd, fpt)
    print(
        f"load_mbd: {len(df)} rows from {len(fpt)} files in {t:.3f} s "
        f"({len(df) / t / 1e3:.0f} k rows/s)"
    )
    trk = DATASET / "trk" / "straight_01_all_sensors.mbd"
    t, tr = timed(tables.load_mbd, trk)
    print(
        f"load_mbd (track, 16 columns): {len(tr)} rows in {t:.3f} s ({len(tr) / t / 1e3:.0f} k rows/s)"
    )

    edges = rssi_edges()
    t, res = timed(radio_data.stationary_fingerprints, [DATASET / "fpt"], edges)
    print(f"stationary fingerprints: {res.files} files, {res.readings} readings in {t:.3f} s")
    t, res = timed(radio_data.annotated_fingerprints, [DATASET / "trk" / "straight_01"], edges, 0.5)
    print(
        f"annotated fingerprints (0.5 m): {len(res.histograms.fingerprints)} cells from "
        f"{res.readings} readings in {t:.3f} s"
    )

    rng = np.random.default_rng(0)
    centres = 0.5 * (edges[:-1] + edges[1:])
    xy = rng.uniform([0, 0], [20.6, 17.6], size=(args.positions, 2))
    sensors = [f"{i:012x}" for i in range(1, args.sensors + 1)]
    table = {}
    for x, y in xy:
        per = {}
        for s in sensors:
            # two-peaked histograms, like the published ones
            mu = rng.uniform(-90, -55)
            p = np.exp(-0.5 * ((centres - mu) / 1.5) ** 2) + 0.6 * np.exp(
                -0.5 * ((centres - mu - rng.uniform(4, 9)) / 1.0) ** 2
            )
            per[s] = {"e78f135624ce": p / p.sum()}
        table[(round(float(x), 2), round(float(y), 2), 1.85)] = per
    h = hst.histograms_from_mapping(edges, radio_data.builtin_devices(), table)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "b.hst"
        t, _ = timed(hst.write_hst, h, path)
        size = path.stat().st_size
        t2, _ = timed(hst.read_hst, path)
        print(
            f".hst of {args.positions} x {args.sensors}: write {t:.3f} s, read {t2:.3f} s, "
            f"{size / 1e6:.2f} MB"
        )

        hists = np.stack([table[k][sensors[0]]["e78f135624ce"] for k in list(table)[:4]])
        t, _ = timed(rm.wasserstein_mix, hists, [0.4, 0.3, 0.2, 0.1], edges, repeat=200)
        print(f"wasserstein_mix of 4 histograms: {t * 1e6:.0f} us")

        occ_file = DATASET / "occ" / f"tetam_{args.cell}.occ"
        occ = read_occ(occ_file) if occ_file.exists() else None
        grid = radio_data.make_grid(h, None if occ else args.cell, occ, None)
        t, maps = timed(radio_data.radio_maps, h, grid, repeat=1)
        cells = int(grid.mask.sum())
        print(
            f"radio maps: {args.sensors} sensors x {cells} cells ({grid.cell:g} m) in {t:.2f} s "
            f"({t / args.sensors / cells * 1e6:.0f} us per cell and sensor)"
        )
        t, _ = timed(
            radio_data.write_radio_maps,
            maps,
            h,
            grid,
            Path(tmp) / "grd",
            "b",
            plots=False,
            repeat=1,
        )
        print(f"write {len(maps)} .grd files: {t:.2f} s")
        t, _ = timed(
            radio_data.write_radio_maps,
            maps[:1],
            h,
            grid,
            Path(tmp) / "png",
            "b",
            plots=True,
            site=radio_data.detect_site(h.devices),
            repeat=1,
        )
        print(f"one .grd + heat map over the floor plan: {t:.2f} s")


if __name__ == "__main__":
    main()
