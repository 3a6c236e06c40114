"""The baseline localizers on every published track: CE50 / CE75 / CE95 per track and method.

    python bench/baseline_table.py --dataset DATASET_DIR [--cell 0.5] [--maps hst,fpt]

DATASET_DIR is the public "Position Annotated BLE RSSI Dataset" (CC0, Daniş et al.), laid out as
published: trk/ (annotated tracks), fpt/ (stationary recordings), hst/set_1/tetam_multi_rssi.hst,
occ/ and cnf/. Without --dataset the bundled subset (tests/data/dataset: one track) is used.

Radio maps: ``fpt`` builds fingerprints from the stationary recordings in fpt/ with
`annotator fingerprints`, ``hst`` takes the published histograms (81 positions); each goes
through `annotator radiomap` on the occupancy grid's free cells. Then, for every track and map,
`annotator localize` (knn, grid-hmm) and `annotator score` against the track's annotation (the
same code, called in-process). Prints a Markdown table and the medians over tracks.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from annotator.core.scoring import score
from annotator.io.localize import localize_run
from annotator.io.scoring import read_truth

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "tests" / "data" / "dataset"
METHODS = ("knn", "grid-hmm")


def annotator(*args: str) -> None:
    exe = Path(sys.executable).parent / "annotator"
    cmd = (
        [str(exe)]
        if exe.is_file()
        else [sys.executable, "-c", "from annotator.cli import main; main()"]
    )
    res = subprocess.run([*cmd, *args], capture_output=True, text=True, check=False)
    if res.returncode:
        raise SystemExit(f"annotator {args[0]} failed: {res.stderr.strip()}")


def build_maps(dataset: Path, work: Path, cell: float, which: list[str]) -> dict[str, Path]:
    occ = dataset / "occ" / f"tetam_{cell:g}.occ"
    maps = {}
    for name in which:
        if name == "fpt":
            hst = work / "fpt.hst"
            annotator(
                "fingerprints",
                str(dataset / "fpt"),
                "--devices",
                str(dataset / "cnf" / "tetam.dev"),
                "--out",
                str(hst),
            )
        elif name == "hst":
            hst = dataset / "hst" / "set_1" / "tetam_multi_rssi.hst"
        else:
            raise SystemExit(f"unknown map source {name!r} (fpt, hst)")
        out = work / f"radiomap_{name}"
        annotator("radiomap", str(hst), "--occupancy", str(occ), "--out", str(out), "--no-plots")
        maps[name] = out
    return maps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=BUNDLED)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--maps", default="hst,fpt", help="radio maps to build: hst, fpt or both")
    args = ap.parse_args()
    tracks = sorted((args.dataset / "trk").glob("*_all_sensors.mbd"))
    if not tracks:
        raise SystemExit(f"{args.dataset}/trk: no *_all_sensors.mbd tracks")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        maps = build_maps(args.dataset, Path(tmp), args.cell, args.maps.split(","))
        print(
            f"radio maps ({', '.join(maps)}; {args.cell:g} m cells) built in "
            f"{time.perf_counter() - t0:.1f} s",
            file=sys.stderr,
        )
        for track in tracks:
            name = track.name.removesuffix("_all_sensors.mbd")
            truth = read_truth(track)
            for map_name, folder in maps.items():
                for method in METHODS:
                    t1 = time.perf_counter()
                    est, _ = localize_run(track, folder, method)
                    pos = np.column_stack([est.xy, np.full(len(est.t), np.nan)])
                    s = score(est.t, pos, truth).summary_2d
                    rows.append((name, map_name, method, s, time.perf_counter() - t1))
    print(f"\n2-D error (m) against the published annotation, {args.cell:g} m radio-map cells\n")
    print("| track | radio map | method | CE50 | CE75 | CE95 | estimates |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: |")
    for name, map_name, method, s, _ in rows:
        print(
            f"| {name} | {map_name} | {method} | {s.ce50:.2f} | {s.ce75:.2f} | {s.ce95:.2f} | {s.n} |"
        )
    print(f"\nmedian over {len(tracks)} track(s)\n")
    print("| radio map | method | CE50 | CE75 | CE95 |")
    print("| --- | --- | ---: | ---: | ---: |")
    for map_name in maps:
        for method in METHODS:
            sel = [r[3] for r in rows if r[1] == map_name and r[2] == method]
            med = [float(np.median([getattr(s, k) for s in sel])) for k in ("ce50", "ce75", "ce95")]
            print(f"| {map_name} | {method} | {med[0]:.2f} | {med[1]:.2f} | {med[2]:.2f} |")
    print(
        f"\nlocalize + score: {sum(r[4] for r in rows):.1f} s for {len(rows)} runs", file=sys.stderr
    )


if __name__ == "__main__":
    main()
