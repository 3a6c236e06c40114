"""What a rest on a jig buys: the bundle's orientation and position with and without it.

    python bench/rig_jig.py                          # 12 s walks, seeds 0-5, all field errors
    python bench/rig_jig.py --duration 30 --seeds 0,1 --jig 2
    python bench/rig_jig.py --surveyed 8 --seeds 0,1,2      # only 8 markers in the map

Each seed renders `annotator simulate --errors field --jig S` (the loop through the tetam room,
960x540, two cameras; the bundle first rests S seconds at the walk's start pose, and the jig's
pose is written into experiment.yaml off by the jig's 1 mm / 0.1 deg sigma) and tracks it twice
with the default `annotator track`: with the experiment as written, and with the same experiment
minus its `refine: jig:` entry (the rig's gauge from rig.yaml alone, today's field case).
Columns per run: position error median and p95 (cm), rotation error median (deg), share of rows
whose 3-D error is within 2.8 sigma_m, median 3-D error / sigma_m; and, for the jig run, the
correction the jig made (deg, mm) as report.json's refinement.jig records it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from annotator.core.evaluate import compare_to_truth
from annotator.io.trajectory import read_trajectory


def annotator(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "annotator.cli", *args], check=True, capture_output=True)


def score(render: Path, track: Path) -> tuple[float, ...]:
    traj = read_trajectory(track / "trajectory.csv")
    truth = read_trajectory(render / "truth.csv")
    cmp = compare_to_truth(
        traj.t, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    ok = np.isfinite(cmp.position_error)
    if not ok.any():  # nothing posed (e.g. no surveyed marker in view): NaN figures
        return (np.nan,) * 5
    err = cmp.position_error[ok]
    z = err / traj.quality["sigma_m"][ok]
    return (
        100 * float(np.median(err)),
        100 * float(np.percentile(err, 95)),
        float(np.nanmedian(cmp.rotation_error_deg)),
        100 * float(np.mean(z < 2.8)),
        float(np.median(z)),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--seeds", default="0,1,2,3,4,5")
    ap.add_argument("--jig", type=float, default=2.0, help="seconds resting on the jig")
    ap.add_argument(
        "--surveyed", type=int, default=None, help="only this many markers in the written map"
    )
    ap.add_argument("--keep", type=Path, default=None, help="keep renders and tracks here")
    a = ap.parse_args()
    root = a.keep or Path(tempfile.mkdtemp(prefix="bgt-rig-jig-"))
    print(
        f"{'seed':>4} {'run':<7} {'median':>7} {'p95':>6} {'rot med':>8} {'<2.8sig':>8} "
        f"{'err/sig':>7}  jig correction"
    )
    rows: dict[str, list[tuple[float, ...]]] = {"no jig": [], "jig": []}
    for seed in (int(s) for s in a.seeds.split(",")):
        render = root / f"s{seed}"
        if not (render / "experiment.yaml").is_file():
            annotator(
                "simulate", "--out", str(render), "--duration", str(a.duration), "--seed",
                str(seed), "--errors", "field", "--jig", str(a.jig), "--jobs", "2",
                *(["--surveyed", str(a.surveyed)] if a.surveyed else []),
            )  # fmt: skip
        text = (render / "experiment.yaml").read_text(encoding="utf-8")
        (render / "nojig.yaml").write_text(text[: text.index("refine:")], encoding="utf-8")
        for run, exp in (("no jig", "nojig.yaml"), ("jig", "experiment.yaml")):
            out = render / ("track-" + run.replace(" ", ""))
            annotator("track", str(render / exp), "--out", str(out), "--jobs", "2")
            figures = score(render, out)
            rows[run].append(figures)
            note = ""
            if run == "jig" and np.isfinite(figures[0]):
                rec = json.loads((out / "refined" / "refinement.json").read_text())["jig"]
                note = (
                    f"turn {rec['rotation_deg']:.2f} deg, shift {1000 * np.linalg.norm(rec['shift_m']):.1f} mm "
                    f"({rec['rig_shift_share']:.0%} to the rig), {rec['rows']} rows"
                )
            med, p95, rot, cov, zm = figures
            print(
                f"{seed:>4} {run:<7} {med:7.2f} {p95:6.2f} {rot:8.3f} {cov:7.1f}% {zm:7.2f}  {note}",
                flush=True,
            )
    for run, r in rows.items():
        m = np.array(r)
        m = m[np.isfinite(m[:, 0])]
        if not len(m):
            continue
        print(
            f"{run:<7} over seeds: median of medians {np.median(m[:, 0]):.2f} cm, worst p95 "
            f"{m[:, 1].max():.2f} cm, rotation median {np.median(m[:, 2]):.3f} deg (worst "
            f"{m[:, 2].max():.3f}), within 2.8 sigma {m[:, 3].mean():.1f} % (mean over seeds)"
        )
    print(
        f"conditions: `annotator simulate --errors field --jig {a.jig:g}"
        f"{f' --surveyed {a.surveyed}' if a.surveyed else ''}` {a.duration:g} s, 960x540, "
        f"two cameras, default `annotator track`; renders in {root}"
    )


if __name__ == "__main__":
    main()
