"""Accuracy of `annotator track` (methods rig and paper) on a rendered experiment with known truth.

    python bench/track_accuracy.py                      # renders 60 s at 960x540 into a temp dir
    python bench/track_accuracy.py --experiment DIR     # an existing `annotator simulate` folder
Prints position error (cm) and rotation error (deg) per method, over rows that have a pose.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from annotator.experiment import load_experiment
from annotator.pipeline import TrackSettings, track_experiment
from annotator.trajectory_io import Trajectory, read_trajectory


def errors(traj: Trajectory, truth: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    ok = traj.valid & (traj.t >= truth.t[0]) & (traj.t <= truth.t[-1])
    t = traj.t[ok]
    p_true = np.stack([np.interp(t, truth.t, truth.position[:, i]) for i in range(3)], 1)
    r_true = Slerp(truth.t, Rotation.from_matrix(truth.rotation))(t)
    pos = np.linalg.norm(traj.position[ok] - p_true, axis=1)
    rot = np.degrees((r_true.inv() * Rotation.from_matrix(traj.rotation[ok])).magnitude())
    return pos, rot


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


def render(out: Path, duration: float, seed: int) -> None:
    from typer.testing import CliRunner

    from annotator.cli import app

    res = CliRunner().invoke(app, ["simulate", "--out", str(out), "--duration", str(duration),
                                   "--seed", str(seed), "--jobs", "2"])
    if res.exit_code != 0:
        raise SystemExit(f"render failed: {res.output}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiment", type=Path, help="folder with experiment.yaml and truth.csv")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.experiment
        if folder is None:
            folder = Path(tmp)
            t0 = time.perf_counter()
            render(folder, args.duration, args.seed)
            print(f"rendered {args.duration:.0f} s in {time.perf_counter() - t0:.0f} s")
        exp = load_experiment(folder / "experiment.yaml")
        truth = read_trajectory(folder / "truth.csv")
        print(f"{'method':8} {'rows':>6} {'posed':>6} {'median':>7} {'mean':>7} {'p75':>7} {'p95':>7} {'max':>7}"
              f"   {'rot med':>7} {'rot p95':>7}  {'path dev med':>12} {'p95':>6}  (cm, deg)  time")
        for method in ("rig", "paper"):
            t0 = time.perf_counter()
            traj = track_experiment(exp, TrackSettings(method=method, jobs=args.jobs))
            el = time.perf_counter() - t0
            pos, rot = errors(traj, truth)
            cm = 100 * pos
            dev = 100 * path_deviation(traj, truth)
            print(f"{method:8} {len(traj):6d} {int(traj.valid.sum()):6d} {np.median(cm):7.2f} {cm.mean():7.2f} "
                  f"{np.percentile(cm, 75):7.2f} {np.percentile(cm, 95):7.2f} {cm.max():7.2f}   "
                  f"{np.median(rot):7.3f} {np.percentile(rot, 95):7.3f}  {np.median(dev):12.2f} "
                  f"{np.percentile(dev, 95):6.2f}  {el:9.1f} s")
        print("position errors compare with truth at the same time; 'path dev' is the distance to the "
              "true path as a curve, whatever the time (how the paper scored itself). 'posed' rows exclude "
              "NaN rows (no trustworthy pose); rig has a row per frame of both cameras, paper one per batch.")


if __name__ == "__main__":
    main()
