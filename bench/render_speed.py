"""How fast the renderer makes a two-camera experiment (`annotator simulate`), in frames/s.

Usage: python bench/render_speed.py [--duration 10] [--width 960 --height 540] [--jobs 1 2]
Prints one line per run: wall time, frames rendered (both cameras) and frames per second,
plus the one-off cost of the lens-distortion map.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from annotator.render import LoopTrajectory, default_cameras, render_experiment
from annotator.render.camera import build_distortion_map


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()

    cam = default_cameras(args.width, args.height)["front"]
    t = time.perf_counter()
    build_distortion_map(cam)
    print(
        f"distortion map {args.width}x{args.height}: {time.perf_counter() - t:.2f} s (once per camera)"
    )

    traj = LoopTrajectory()
    for jobs in args.jobs:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            res = render_experiment(
                tmp,
                traj,
                (traj.t0, traj.t0 + args.duration),
                width=args.width,
                height=args.height,
                jobs=jobs,
            )
            wall = time.perf_counter() - t
        n = sum(res.frames.values())
        print(
            f"{args.duration:g} s two-camera render {args.width}x{args.height}, jobs={jobs}: "
            f"{wall:.1f} s wall, {n} frames, {n / wall:.1f} frames/s"
        )


if __name__ == "__main__":
    main()
