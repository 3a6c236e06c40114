"""Accuracy of the labelled RSSI readings of `annotator run` (automatic sync) under real-world errors.

    python bench/field_labels.py                          # 30 s, conditions none and all, seeds 0,1,2
    python bench/field_labels.py --duration 12 --conditions all --seeds 0

The scenario is `annotator demo`'s without its processes: the demo's rounded loop through the
tetam room, two hands-cover events (2 s after the start and 3 s before the end), the simulated
agents' readings (three agents x four sensors, 10 adverts/s, -20 dB and 60 % loss while covered)
generated in-process with `sensor_agent.scanning.simulated.Simulation` and written as a collector
run's .mbd files. The two videos are rendered with `annotator.render.render_experiment` and the
files handed to the annotator carry the condition's errors; experiment.yaml says `sync: auto` (no
video start times). `annotator.pipeline.run_experiment` (what `annotator run` calls) tracks with the
default self-calibration, finds each camera's start from the cover events and labels every
reading. Each labelled reading is scored against the true path at the reading's own timestamp
(`annotator.demo.score`). Conditions:

    none   exact files, global shutter, the demo's 1/120 s exposure, the mild lens, no flicker
    all    `annotator simulate --errors field`: survey 1.5 cm / 1 deg, rig 3 mm / 1 deg, focal
           0.4 %, principal point 1 px, distortion error, k1 = -0.28 lens, 15 ms rolling-shutter
           readout, 8 ms exposure, 10 % flicker

Columns: labelled readings; position error median / p95 / max (cm); share of labelled readings
whose 3-D error is within 2.8 x the label's sigma (~95 % for an honest per-axis sigma); each
camera's video-start error (ms) beside its reported sigma. Videos are cached under --cache (the
same default folder as bench/field_accuracy.py, keyed by everything that shapes them).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from field_accuracy import FIELD, FILE_KEYS, VIDEO_KEYS, link, render_once, renderer_digest  # noqa: E402

from annotator import demo  # noqa: E402
from annotator.render import default_cameras, render_experiment  # noqa: E402
from annotator.render.errors import FileErrors  # noqa: E402
from annotator.render.experiment import write_experiment_files  # noqa: E402
from bgt_core import safe_yaml  # noqa: E402
from bgt_core.formats.markers import read_marker_map  # noqa: E402
from bgt_core.formats.mbd import format_row  # noqa: E402
from bgt_core.sites import site_dir  # noqa: E402

T0 = 1_700_000_000.0
START_OFFSET = 0.35  # the demo's
COVERAGE_K = 2.8
CLEAN_VIDEO: dict[str, object] = {
    "lens": "mild",
    "readout": 0.0,
    "exposure": 1 / 120,
    "flicker": 0.0,
}
CONDITIONS: dict[str, tuple[dict[str, object], dict[str, float]]] = {
    "none": ({}, {}),
    "all": ({k: FIELD[k] for k in VIDEO_KEYS}, {k: float(FIELD[k]) for k in FILE_KEYS}),
}


def cached_video(
    cache: Path, video: dict[str, object], settings: demo.DemoSettings, jobs: int
) -> Path:
    """Folder holding front.mp4 and back.mp4 of the demo walk with these video errors."""
    args = {
        **CLEAN_VIDEO,
        **video,
        "scenario": "demo-walk",
        "duration": settings.duration_s,
        "seed": settings.seed,
        "covers": settings.covers(),
        "t0": T0,
        "start_offset": START_OFFSET,
        "renderer": renderer_digest(),
    }

    def render(tmp: Path) -> None:
        render_experiment(
            tmp,
            demo.bundle_pose_at(demo.demo_path(settings.speed_mps), T0),
            (T0, T0 + settings.duration_s),
            width=960,
            height=540,
            start_offset=START_OFFSET,
            covers=settings.covers(),
            seed=settings.seed,
            exposure=float(args["exposure"]),
            lens=str(args["lens"]),
            readout=float(args["readout"]),
            flicker=float(args["flicker"]),
            jobs=jobs,
        )

    what = "clean" if not video else ", ".join(f"{k}={v}" for k, v in video.items())
    return render_once(
        cache, args, render, f"{settings.duration_s:g} s (seed {settings.seed}, {what})"
    )


def write_readings(run_dir: Path, settings: demo.DemoSettings) -> int:
    """The three simulated agents' readings as a collector run: rssi/<agent>/<sensor>.mbd."""
    from sensor_agent.scanning.simulated import simulate_fleet

    path = demo.demo_path(settings.speed_mps)
    events = demo.rssi_events(settings)
    fleet = simulate_fleet(
        "tetam", demo.split_sensors(), path, round(T0 * 1e9), seed=settings.seed, events=events
    )
    n = 0
    for agent, sim in zip(demo.AGENTS, fleet, strict=True):
        rows: dict[str, list[str]] = {}
        for mac, r in sim.generate(settings.duration_s + 1.0):
            rows.setdefault(mac, []).append(format_row(r.t_ns, mac, r.beacon, r.rssi))
        (run_dir / "rssi" / agent).mkdir(parents=True, exist_ok=True)
        for mac, lines in rows.items():
            (run_dir / "rssi" / agent / f"{mac.replace(':', '')}.mbd").write_text(
                "".join(lines), encoding="utf-8"
            )
            n += len(lines)
    return n


def make_experiment(folder: Path, video_dir: Path, cond: str, settings: demo.DemoSettings) -> Path:
    video, files = CONDITIONS[cond]
    video = {**CLEAN_VIDEO, **video}
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("front.mp4", "back.mp4"):
        link(video_dir / name, folder / name)
    write_experiment_files(
        folder,
        default_cameras(960, 540, str(video["lens"])),
        read_marker_map(site_dir("tetam") / "marker_positions.dat"),
        {"front": T0, "back": T0 + START_OFFSET},
        readout=float(video["readout"]),
        errors=FileErrors(**files, seed=settings.seed),
        settings={"condition": cond, **video},
    )
    shutil.rmtree(folder / "rssi", ignore_errors=True)
    write_readings(folder / "run", settings)
    doc = {
        "markers": {"file": "marker_positions.dat", "dictionary": "DICT_6X6_50", "length": 0.298},
        "rig": "rig.yaml",
        "videos": {"front": "front.mp4", "back": "back.mp4"},
        "rssi": "run",
        "sync": {"mode": "auto"},
    }
    exp = folder / "experiment.yaml"
    exp.write_text(safe_yaml.dump(doc, sort_keys=False), encoding="utf-8")
    return exp


def run_and_score(exp: Path, settings: demo.DemoSettings, jobs: int) -> dict[str, object]:
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment

    t = time.perf_counter()
    experiment = load_experiment(exp)
    run = run_experiment(experiment, RunSettings(track=TrackSettings(jobs=jobs)))
    write_run_outputs(exp.parent / "results", experiment, run, plots=False)
    seconds = time.perf_counter() - t
    path = demo.demo_path(settings.speed_mps)
    s = demo.score(run, path, T0, {"front": T0, "back": T0 + START_OFFSET}, settings.duration_s)
    lab = np.asarray(run.labels.labelled, bool)
    t_s = (np.asarray(run.rssi.t_ns, np.int64)[lab] - round(T0 * 1e9)) / 1e9
    truth = np.array([path.position_at(float(x)) for x in t_s]).reshape(-1, 3)
    err = np.linalg.norm(np.asarray(run.labels.positions)[lab] - truth, axis=1)
    sigma = np.asarray(run.labels.sigma)[lab]
    ok = np.isfinite(sigma)
    s["within"] = float(np.mean(err[ok] < COVERAGE_K * sigma[ok])) if ok.any() else float("nan")
    s["n_within"], s["n_sigma"] = int(np.sum(err[ok] < COVERAGE_K * sigma[ok])), int(ok.sum())
    s["seconds"] = seconds
    return s


def row_text(cond: str, seed: int, s: dict) -> str:
    e = s["error_cm"]
    cams = "  ".join(
        f"{n} {c['error_ms']:+6.1f} ms (sigma {c['sigma_ms'] or float('nan'):5.1f})"
        for n, c in s["sync"].items()
    )
    return (
        f"{cond:5} {seed:4d} {e['n']:6d} {e['median']:7.2f} {e['p95']:7.2f} {e['max']:7.2f} "
        f"{100 * s['within']:7.1f}%  {cams}  {s['seconds']:4.0f}s"
    )


HEADER = (
    f"{'cond':5} {'seed':>4} {'labels':>6} {'median':>7} {'p95':>7} {'max':>7} {'<2.8sig':>8}  "
    "video start error per camera (reported sigma)  time"
)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of video (default 30)")
    ap.add_argument("--conditions", default="none,all", help="comma-separated subset of none, all")
    ap.add_argument(
        "--seeds", default="0,1,2", help="comma-separated seeds (render, radio and error draws)"
    )
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument(
        "--keep", type=Path, help="keep each experiment and its results under this folder"
    )
    ap.add_argument(
        "--cache", type=Path, default=Path(tempfile.gettempdir()) / "ble-groundtruth-field-videos"
    )
    ap.add_argument("--json", type=Path, help="also write the summaries as JSON here")
    args = ap.parse_args()
    conds = [c.strip() for c in args.conditions.split(",") if c.strip()]
    bad = [c for c in conds if c not in CONDITIONS]
    if bad:
        raise SystemExit(f"--conditions: unknown {', '.join(bad)} (known: {', '.join(CONDITIONS)})")
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    args.cache.mkdir(parents=True, exist_ok=True)
    work = args.keep or Path(tempfile.mkdtemp(prefix="field-labels-"))
    rows: list[tuple[str, int, dict]] = []
    print(
        f"demo walk {args.duration:g} s, 960x540, two cameras, sync auto, refine default",
        flush=True,
    )
    try:
        for seed in seeds:
            settings = demo.DemoSettings(
                out=work,
                duration_s=args.duration,
                seed=seed,
                start_offset_s=START_OFFSET,
                jobs=args.jobs,
            )
            for cond in conds:
                vdir = cached_video(args.cache, CONDITIONS[cond][0], settings, args.jobs)
                exp = make_experiment(work / f"{cond}-s{seed}", vdir, cond, settings)
                rows.append((cond, seed, run_and_score(exp, settings, args.jobs)))
                print(row_text(*rows[-1]), flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(HEADER)
    for r in rows:
        print(row_text(*r))
    print(
        "errors in cm: labelled reading's position against the true path at the reading's timestamp"
    )
    for cond in conds:
        mine = [s for c, _, s in rows if c == cond]
        n, k = sum(s["n_sigma"] for s in mine), sum(s["n_within"] for s in mine)
        if n:
            print(
                f"{cond}: pooled over seeds {100 * k / n:.1f} % of {n} labels within {COVERAGE_K} sigma"
            )
    if args.json is not None:
        args.json.write_text(
            json.dumps([{"condition": c, "seed": s, **v} for c, s, v in rows], indent=1),
            encoding="utf-8",
        )


if __name__ == "__main__":
    main()
