"""Accuracy of `annotator track` (methods rig and paper) on rendered experiments with known truth.

    python bench/track_accuracy.py                      # renders 60 s of each path at 960x540 into a temp dir
    python bench/track_accuracy.py --paths rectangle    # only some paths (loop, rectangle, zigzag)
    python bench/track_accuracy.py --experiment DIR     # an existing `annotator simulate` folder
Prints, per path and method, position error (cm, against the truth at the same time), rotation
error (deg) and the deviation from the path whatever the time (cm): for polyline paths the
paper's measure against the planned polyline (path.yaml), for the loop the distance to the true
curve. Statistics are over rows that have a pose.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from annotator.core.evaluate import compare_to_path, compare_to_truth
from annotator.core.trajectory import Trajectory
from annotator.io.experiment import load_experiment
from annotator.io.trajectory import read_trajectory
from annotator.io.waypoints import load_waypoints
from annotator.pipeline import TrackSettings, track_experiment


def errors(traj: Trajectory, truth: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (deg) errors of the posed rows inside truth's span."""
    cmp = compare_to_truth(
        traj.t, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    ok = np.isfinite(cmp.position_error)
    return cmp.position_error[ok], cmp.rotation_error_deg[ok]


def path_deviation(traj: Trajectory, truth: Trajectory) -> np.ndarray:
    """Distance of each posed row to the true path as a curve, ignoring time (the paper's measure)."""
    from scipy.spatial import cKDTree

    # Densify the true path to ~1 mm steps so nearest-point distance is the distance to the curve.
    seg = np.linalg.norm(np.diff(truth.position, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    dense_s = np.arange(0, s[-1], 0.001)
    dense = np.stack([np.interp(dense_s, s, truth.position[:, i]) for i in range(3)], 1)
    d, _ = cKDTree(dense).query(traj.position[traj.valid])
    return d


def render(out: Path, duration: float, seed: int, path: str) -> None:
    from typer.testing import CliRunner

    from annotator.cli import app

    res = CliRunner().invoke(
        app,
        [
            "simulate",
            "--out",
            str(out),
            "--duration",
            str(duration),
            "--seed",
            str(seed),
            "--jobs",
            "2",
            "--path",
            path,
        ],
    )
    if res.exit_code != 0:
        raise SystemExit(f"render failed: {res.output}")


def deviation(
    traj: Trajectory, truth: Trajectory, folder: Path
) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-posed-row deviation (m) and, against a planned polyline, the drag at each segment end."""
    if (folder / "path.yaml").exists():
        cmp = compare_to_path(traj.position, load_waypoints(folder / "path.yaml"))
        dev = cmp.deviation
        return dev[np.isfinite(dev)], cmp.drag
    return path_deviation(traj, truth), None


def evaluate_folder(name: str, folder: Path, jobs: int) -> None:
    exp = load_experiment(folder / "experiment.yaml")
    truth = read_trajectory(folder / "truth.csv")
    for method in ("rig", "paper"):
        t0 = time.perf_counter()
        traj = track_experiment(exp, TrackSettings(method=method, jobs=jobs))
        el = time.perf_counter() - t0
        pos, rot = errors(traj, truth)
        cm = 100 * pos
        dev, drag = deviation(traj, truth, folder)
        dev = 100 * dev
        drag_txt = (
            ""
            if drag is None
            else "  drag " + " ".join("-" if not np.isfinite(v) else f"{100 * v:.0f}" for v in drag)
        )
        print(
            f"{name:10} {method:6} {len(traj):6d} {int(traj.valid.sum()):6d} {np.median(cm):7.2f} {cm.mean():7.2f} "
            f"{np.percentile(cm, 75):7.2f} {np.percentile(cm, 95):7.2f} {cm.max():7.2f}   "
            f"{np.median(rot):7.3f} {np.percentile(rot, 95):7.3f}  {np.median(dev):8.2f} "
            f"{np.percentile(dev, 95):6.2f}  {el:7.1f} s{drag_txt}",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--experiment", type=Path, help="folder with experiment.yaml and truth.csv (and path.yaml)"
    )
    ap.add_argument(
        "--paths",
        default="loop,rectangle",
        help="comma-separated `annotator simulate --path` values to render (default loop,rectangle)",
    )
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    header = (
        f"{'path':10} {'method':6} {'rows':>6} {'posed':>6} {'median':>7} {'mean':>7} {'p75':>7} {'p95':>7} "
        f"{'max':>7}   {'rot med':>7} {'rot p95':>7}  {'dev med':>8} {'p95':>6}  (cm, deg)  time"
    )
    with tempfile.TemporaryDirectory() as tmp:
        if args.experiment is not None:
            print(header)
            evaluate_folder(args.experiment.name, args.experiment, args.jobs)
        else:
            paths = [p.strip() for p in args.paths.split(",") if p.strip()]
            folders = {}
            for path in paths:  # all renders first, so the table comes out in one piece
                folders[path] = Path(tmp) / path.replace("/", "_")
                t0 = time.perf_counter()
                render(folders[path], args.duration, args.seed, path)
                print(
                    f"rendered {args.duration:.0f} s of {path} in {time.perf_counter() - t0:.0f} s",
                    flush=True,
                )
            print(header)
            for path, folder in folders.items():
                evaluate_folder(path, folder, args.jobs)
        print(
            "position errors compare with truth at the same time; 'dev' ignores time: for a polyline path the "
            "distance to the planned polyline (how the paper scored itself; 'drag' per segment end, cm), for "
            "the loop the distance to the true curve. 'posed' rows exclude NaN rows (no trustworthy pose); "
            "rig has a row per frame of both cameras, paper one per batch of F frames of both cameras."
        )


if __name__ == "__main__":
    main()
