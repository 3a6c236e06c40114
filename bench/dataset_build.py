"""`annotator dataset build` on a 4-run campaign: build time with 1 and 2 Dask workers (their
ratio, in one run of this script), a rebuild with nothing changed (the per-run cache), whether
the files are identical, and the occupancy grids' agreement with published ones.

    python bench/dataset_build.py                          # 4 runs of 12 s
    python bench/dataset_build.py --runs 4 --duration 20 --published PATH/occ

Each run is `annotator simulate --rssi` of its own seed and path (loop, rectangle, zigzag, loop),
960x540, manual sync; the fingerprints are the bundled recordings. `--published` is a folder of
the site's published `tetam_<cell>.occ` grids to compare the built ones with (the occupancy
cells are 0.1, 0.2, 0.5 and 1.0 m).
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from annotator.core.occupancy import agreement
from bgt_core.formats.occ import read_occ
from bgt_core.sites import site_dir

REPO = Path(__file__).resolve().parents[1]
PATHS = ("loop", "rectangle", "zigzag", "loop")


def annotator(*args: str) -> str:
    res = subprocess.run(
        [sys.executable, "-c", "from annotator.cli import main; main()", *args],
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        raise SystemExit(f"annotator {' '.join(args[:2])} failed: {res.stdout}{res.stderr}")
    return res.stdout + res.stderr


def digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--published", type=Path, help="folder of published tetam_<cell>.occ grids")
    args = ap.parse_args()
    site = site_dir("tetam")
    with tempfile.TemporaryDirectory(prefix="dataset-bench-") as tmp:
        base = Path(tmp)
        runs = []
        t = time.perf_counter()
        for i in range(args.runs):
            name = f"run_{i}"
            annotator(
                "simulate", "--out", str(base / name), "--duration", str(args.duration),
                "--seed", str(i), "--path", PATHS[i % len(PATHS)], "--rssi-rate", "4",
                "--jobs", "2",
            )  # fmt: skip
            runs.append(f"  - {{name: {name}, experiment: {name}/experiment.yaml}}\n")
        print(
            f"rendered {args.runs} runs of {args.duration:g} s in {time.perf_counter() - t:.0f} s"
        )
        campaign = base / "campaign.yaml"
        campaign.write_text(
            "name: bench\n"
            f"site: {{devices: {site / 'tetam.dev'}, par: {site / 'tetam.par'}, "
            f"plan: {site / 'tetam.png'}, markers: {site / 'marker_positions.dat'}}}\n"
            "runs:\n" + "".join(runs)
            + f"fingerprints: {{recordings: {REPO / 'tests' / 'data' / 'dataset' / 'fpt'}}}\n"
            "radiomap_cells: [1.0]\n"
        )  # fmt: skip
        seconds, built = {}, {}
        for workers in (1, 2):
            out = base / f"out-{workers}"
            cache = base / f"cache-{workers}"
            t = time.perf_counter()
            annotator("dataset", "build", str(campaign), "--out", str(out),
                      "--workers", str(workers), "--cache", str(cache))  # fmt: skip
            seconds[workers] = time.perf_counter() - t
            built[workers] = digests(out)
            print(f"{workers} worker(s): {seconds[workers]:.1f} s", flush=True)
        print(f"ratio 1 / 2 workers: {seconds[1] / seconds[2]:.2f}x")
        print(
            f"identical files with 1 and 2 workers: {built[1] == built[2]} ({len(built[1])} files)"
        )
        t = time.perf_counter()
        text = annotator("dataset", "build", str(campaign), "--out", str(base / "out-2"),
                         "--workers", "2", "--cache", str(base / "cache-2"))  # fmt: skip
        again = time.perf_counter() - t
        last = [line for line in text.splitlines() if " runs (" in line]
        print(f"rebuild with nothing changed: {again:.1f} s; {last[-1] if last else text[-200:]}")
        print(f"same files as before: {digests(base / 'out-2') == built[2]}")
        if args.published is not None:
            for cell in (0.1, 0.2, 0.5, 1.0):
                theirs = args.published / f"tetam_{cell!r}.occ"
                ours = base / "out-2" / "occ" / f"tetam_{cell!r}.occ"
                if theirs.is_file() and ours.is_file():
                    share, n = agreement(read_occ(ours), read_occ(theirs))
                    print(f"occupancy {cell:g} m: {100 * share:.1f} % of {n} cells agree")
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
