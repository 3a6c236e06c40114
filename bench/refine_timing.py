"""What the self-calibration costs on a long capture: refinement time against tracking time.

    python bench/refine_timing.py                          # one 600 s two-camera 1080p capture
    python bench/refine_timing.py --durations 20,120,300   # how the costs grow with the capture
    python bench/refine_timing.py --durations 20 --also-none   # plus a --refine none run to compare
    python bench/refine_timing.py --prefixes 20,120,300    # the first 20/120/300 s of the 600 s render

Each duration renders the default loop walk through the tetam room with `annotator simulate
--errors field` (every real-world error on: survey, rig, intrinsics, wide lens, rolling shutter,
motion blur, flicker), two cameras at --width x --height, and caches the render under --cache
(outside the repository; keyed by the render arguments and the renderer's source). Then
`annotator track --refine all` runs on it in a child process and the bench prints:

    track s      wall time of the whole `annotator track` process (decode, detect, solve, refine, write)
    refine s     the bundle adjustment alone (keyframe choice + solve, every round), from
                 refined/refinement.json's "timing" record
    +retrack s   the extra joint-solve pass over every frame with the refined map, rig and lenses
    ratio        refine s / track s (issue 10's target: <= 25 % on 10 min of 1080p);
                 ratio+   (refine s + retrack s) / track s, everything the refinement adds
    keyframes    keyframes the adjustment used (capped by RefineSettings.max_keyframes, spread over
                 the whole capture), and its rounds
    fps          frames of both cameras per wall second of tracking
    cpu s        CPU time of the tracking process tree (less sensitive to other work on the machine)
    peak MB      peak resident memory of the largest process of the tree (wait4's ru_maxrss)
    median/p95   position error against the rendered truth, cm; posed: share of rows with a pose

The load average is printed before and after each run: on a shared machine wall times move with it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from field_accuracy import render_once, renderer_digest  # noqa: E402

from annotator.core.evaluate import compare_to_truth  # noqa: E402
from annotator.io.trajectory import read_trajectory  # noqa: E402
from annotator.io.video import video_info  # noqa: E402

CLI = [sys.executable, "-m", "annotator.cli"]


def cached_capture(
    cache: Path,
    duration: float,
    width: int,
    height: int,
    fps: float,
    seed: int,
    jobs: int,
    log: Path,
) -> Path:
    """An `annotator simulate --errors field` experiment folder, rendered once per argument set."""
    args = {
        "duration": duration,
        "width": width,
        "height": height,
        "fps": fps,
        "seed": seed,
        "errors": "field",
        "renderer": renderer_digest(),
    }

    def render(tmp: Path) -> None:
        cmd = [
            *CLI,
            "simulate",
            "--out",
            str(tmp),
            "--duration",
            str(duration),
            "--width",
            str(width),
            "--height",
            str(height),
            "--fps",
            str(fps),
            "--seed",
            str(seed),
            "--errors",
            "field",
            "--jobs",
            str(jobs),
        ]
        with log.open("a", encoding="utf-8") as f:
            f.write("$ " + " ".join(cmd) + "\n")
            f.flush()
            subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=True)

    print(
        f"[{time.strftime('%H:%M:%S')}] capture {duration:g} s at {width}x{height} (cached or rendering) ...",
        flush=True,
    )
    return render_once(
        cache, args, render, f"{duration:g} s at {width}x{height}, errors field, seed {seed}"
    )


def timed(cmd: list[str], log: Path) -> tuple[float, float, float, int]:
    """Run ``cmd``; (wall s, CPU s of its process tree, peak RSS MB of its largest process, exit code)."""
    with log.open("a", encoding="utf-8") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        # wait4: this child's own rusage (its waited-for children included), not every child so far.
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
    return wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024, proc.returncode


def track_once(
    folder: Path, out: Path, refine: str, jobs: int, log: Path, max_frames: int | None = None
) -> dict[str, object]:
    cmd = [
        *CLI,
        "track",
        str(folder / "experiment.yaml"),
        "--out",
        str(out),
        "--refine",
        refine,
        "--jobs",
        str(jobs),
    ] + ([] if max_frames is None else ["--max-frames", str(max_frames)])
    load0 = os.getloadavg()[0]
    wall, cpu, peak_mb, code = timed(cmd, log)
    if code != 0:
        raise SystemExit(f"annotator track failed (exit {code}); see {log}")
    n_frames = sum(
        min(video_info(folder / f"{cam}.mp4").frame_count, max_frames or 1 << 62)
        for cam in ("front", "back")
    )
    traj = read_trajectory(out / "trajectory.csv")
    truth = read_trajectory(folder / "truth.csv")
    cmp = compare_to_truth(
        traj.t, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    e = 100 * cmp.position_error[np.isfinite(cmp.position_error)]
    row: dict[str, object] = {
        "refine": refine,
        "track_s": wall,
        "cpu_s": cpu,
        "peak_mb": peak_mb,
        "frames": n_frames,
        "fps": n_frames / wall,
        "posed": float(traj.valid.mean()),
        "median_cm": float(np.median(e)) if len(e) else float("nan"),
        "p95_cm": float(np.percentile(e, 95)) if len(e) else float("nan"),
        "load_before": load0,
        "load_after": os.getloadavg()[0],
    }
    rep_path = out / "refined" / "refinement.json"
    if refine != "none" and rep_path.is_file():
        rep = json.loads(rep_path.read_text(encoding="utf-8"))
        timing = rep.get("timing", {})
        row.update(
            keyframes=rep["keyframes"],
            corners=rep["corners"],
            iterations=rep["iterations"],
            rounds=timing.get("rounds", 1),
            refine_s=timing.get("solve", rep["seconds"]),
            retrack_s=timing.get("retrack", float("nan")),
        )
        row["ratio"] = row["refine_s"] / wall
        row["ratio_plus"] = (row["refine_s"] + row["retrack_s"]) / wall
    return row


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--durations", default="600", help="comma-separated capture lengths, s (default 600)"
    )
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--jobs", type=int, default=2, help="worker processes of the render and the tracking"
    )
    ap.add_argument(
        "--also-none", action="store_true", help="also track with --refine none, for comparison"
    )
    ap.add_argument(
        "--prefixes",
        help="comma-separated lengths, s: track only the first this many seconds of "
        "each capture (annotator track --max-frames) instead of the whole",
    )
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "bgt-refine-timing",
        help="render cache and track outputs (outside the repository: 10 min of 1080p is GBs)",
    )
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args()
    durations = [float(d) for d in args.durations.split(",")]
    args.cache.mkdir(parents=True, exist_ok=True)
    log = args.cache / "commands.log"
    print(
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; {args.width}x{args.height} at "
        f"{args.fps:g} fps, two cameras, --errors field, seed {args.seed}, jobs {args.jobs}; log {log}",
        flush=True,
    )
    rows = []
    for d in durations:
        folder = cached_capture(
            args.cache / "renders", d, args.width, args.height, args.fps, args.seed, args.jobs, log
        )
        lengths = [float(p) for p in args.prefixes.split(",")] if args.prefixes else [d]
        for length, refine in [
            (n, r) for n in lengths for r in (("all", "none") if args.also_none else ("all",))
        ]:
            cut = None if length >= d else round(length * args.fps)
            print(
                f"[{time.strftime('%H:%M:%S')}] track {length:g} s"
                + (f" (of {d:g} s)" if cut else "")
                + f" --refine {refine} ...",
                flush=True,
            )
            row = track_once(
                folder,
                args.cache / "tracks" / f"{folder.name}-{refine}-{length:g}",
                refine,
                args.jobs,
                log,
                cut,
            )
            row["duration_s"] = length
            rows.append(row)
            print(
                "  "
                + json.dumps(
                    {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}
                ),
                flush=True,
            )
    print(
        f"\n{'capture':>8} {'refine':>6} {'track s':>8} {'refine s':>9} {'+retrack s':>10} {'ratio':>6} "
        f"{'ratio+':>6} {'keyfr':>6} {'rounds':>6} {'fps':>6} {'cpu s':>7} {'peak MB':>8} {'median cm':>9} "
        f"{'p95 cm':>7} {'posed':>6} {'load':>9}"
    )
    for r in rows:
        ref = "refine_s" in r
        print(
            f"{r['duration_s']:7g}s {r['refine']:>6} {r['track_s']:8.1f} "
            + (
                f"{r['refine_s']:9.1f} {r['retrack_s']:10.1f} {100 * r['ratio']:5.1f}% {100 * r['ratio_plus']:5.1f}% "
                f"{r['keyframes']:6d} {r['rounds']:6d} "
                if ref
                else f"{'-':>9} {'-':>10} {'-':>6} {'-':>6} {'-':>6} {'-':>6} "
            )
            + f"{r['fps']:6.1f} {r['cpu_s']:7.0f} {r['peak_mb']:8.0f} {r['median_cm']:9.2f} {r['p95_cm']:7.2f} "
            f"{100 * r['posed']:5.1f}% {r['load_before']:4.1f}>{r['load_after']:<4.1f}"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
