"""Accuracy of `annotator track` across a matrix of captures: how the bundle moves, what the
camera adds to the picture and how the markers were printed, each with every field error on.

    python bench/field_matrix.py                                  # every cell, seeds 0-4, 30 s
    python bench/field_matrix.py --cells walk,print --seeds 0,1 --duration 20
    python bench/field_matrix.py --json matrix.json               # rows for later comparison
    python bench/field_matrix.py --sync slate                     # the clock slate, not the hands

Every cell renders its walk through the tetam room with `annotator.render.render_experiment`
and the field errors of `annotator simulate --errors field` in the files (survey 1.5 cm / 1 deg,
rig 3 mm / 1 deg, focal 0.4 %, principal point 1 px, wide k1 = -0.28 lens, 15 ms readout written
as 0, 8 ms exposure, 10 % flicker), with hands over the bundle at 2 s and 3 s before the end
and the RSSI the walk gives at the site's 12 sensors (`annotator.render.rssi`, 2 adverts/s).
`annotator run` (today's defaults, `sync.mode: auto`: it is not told when the videos started)
tracks, synchronises and labels it; the trajectory and every labelled reading are scored against
the exact truth. Cells:

    walk        the default loop, held in front while walking (the renderer's own habit)
    push        a level cart pushed along the rectangle, stopping at each corner and turning
                in place (up to 56 deg/s), like the paper's "with rotation" tracks
    hand        the loop, carried in one hand: more wobble, a 2 cm bounce, jolts at each step
    fast        the loop walked at 1.2 m/s
    print       the loop, markers printed 0.7 % larger than experiment.yaml's length (0.300 m
                for 0.298) with 0.2 % scatter from marker to marker
    real        the loop at 1920x1080 with what a real camera adds (`--imaging real`: defocus
                1.5 px, JPEG quality 60, 40 % vignetting, uneven and drifting light, exposure
                steps, noise 5) and the 0.7 % print
    push-real   the cart pushes of `push` with the imaging and print of `real`, at 1920x1080

With `--sync slate` every camera also films the clock slate (`collector slate`, a 60 Hz screen
with a random refresh phase) for a second before and after the walk, and `annotator run` uses
`sync.mode: slate` (the covers stay: readings under them are not labelled). With `--receiver`
the radio runs the other way: the bundle carries a receiver 10 cm above its beacon, a beacon
advertises at each of the site's 12 sensor positions, and every reading the receiver took is
labelled with its antenna's position and scored against where that antenna truly was.

Columns per row: posed share of the frames outside the covers; trajectory error median and p95
(cm); rotation error median (deg); share of posed rows within 2.8 sigma_m (~95 % for an honest
per-axis sigma); the labelled readings' error median and p95 (cm) and share within 2.8 x their
sigma; the automatic sync's error (ms, mean over the cameras of |found - true| video start);
readout found by the refinement (ms, true 15) and printed scale found (the print cells' truth
1.007); run time. Per cell: the mean over seeds and the worst seed; last, the mean over cells
and the worst cell. Videos are cached like bench/field_accuracy.py's.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import field_accuracy as fa  # noqa: E402  (the bench beside this one)

from annotator.core.evaluate import compare_to_truth  # noqa: E402
from annotator.io.trajectory import read_trajectory  # noqa: E402
from annotator.render import render_experiment  # noqa: E402
from annotator.render.conditions import IMAGING_NOISE, IMAGING_PRESETS, path_trajectory  # noqa: E402
from annotator.render.rssi import (  # noqa: E402
    COVER_RAMP_S,
    RECEIVER_ANTENNA,
    RECEIVER_MAC,
    add_receiver,
    write_simulated_run,
)
from bgt_core import safe_yaml  # noqa: E402

TRUE_READOUT_S = float(fa.FIELD["readout"])
COVER_S = 1.5  # hands over the bundle at 2 s and 3 s before the end, this long
SLATE = {"s": 0.0}  # seconds of clock slate at each end (--sync slate: 1)
RECEIVER = {"on": False}  # --receiver: the bundle carries a receiver; the site's sensors beacon
PROFILE = {"on": False}  # --profile-corners: the detector's profile model (off by default)


def covers(duration: float) -> list[tuple[float, float]]:
    return [(2.0, COVER_S), (duration - 3.0, COVER_S)]


@dataclass(frozen=True)
class Cell:
    name: str
    path: str = "loop"
    motion: str = "walk"
    speed: float = 0.4
    dwell: float = 2.5
    imaging: str = "clean"
    print_scale: float = 1.0
    print_scatter: float = 0.0
    width: int = 960
    height: int = 540

    def render_args(self) -> dict[str, object]:
        return asdict(self)


PRINT = {"print_scale": 1.007, "print_scatter": 0.002}
REAL = {"imaging": "real", **PRINT, "width": 1920, "height": 1080}
CELLS = {
    c.name: c
    for c in (
        Cell("walk"),
        Cell("push", path="rectangle", motion="cart"),
        Cell("hand", motion="hand"),
        Cell("fast", speed=1.2),
        Cell("print", **PRINT),  # type: ignore[arg-type]
        Cell("real", **REAL),  # type: ignore[arg-type]
        Cell("push-real", path="rectangle", motion="cart", **REAL),  # type: ignore[arg-type]
    )
}


def cell_video(cache: Path, cell: Cell, duration: float, seed: int, jobs: int) -> Path:
    """front.mp4, back.mp4 and truth.csv of the cell's capture (every field error of the video:
    wide lens, 15 ms readout, 8 ms exposure, flicker), rendered once and cached."""
    video = {k: fa.FIELD[k] for k in fa.VIDEO_KEYS}
    args = {
        **cell.render_args(),
        **video,
        "duration": duration,
        "seed": seed,
        "t0": fa.T0,
        "start_offset": fa.START_OFFSET,
        "renderer": fa.renderer_digest(),
    }

    args["covers"] = covers(duration)
    if SLATE["s"]:
        args["slate"] = SLATE["s"]

    def render(tmp: Path) -> None:
        render_experiment(
            tmp,
            cell_walk(cell),
            (fa.T0, fa.T0 + duration),
            covers=covers(duration),
            width=cell.width,
            height=cell.height,
            start_offset=fa.START_OFFSET,
            seed=seed,
            noise_sigma=IMAGING_NOISE[cell.imaging],
            exposure=float(video["exposure"]),
            lens=str(video["lens"]),
            readout=float(video["readout"]),
            flicker=float(video["flicker"]),
            jobs=jobs,
            imaging=IMAGING_PRESETS[cell.imaging],
            print_scale=cell.print_scale,
            print_scatter=cell.print_scatter,
            slate=SLATE["s"],
        )

    return fa.render_once(cache, args, render, f"{cell.name} {duration:g} s (seed {seed})")


def cell_walk(cell: Cell):  # noqa: ANN201 - a render trajectory
    return path_trajectory(cell.path, fa.T0, cell.speed, cell.dwell, True, cell.motion)


def make_experiment(
    folder: Path, vdir: Path, cell: Cell, duration: float, seed: int, rssi_rate: float
) -> Path:
    """The cell's capture as a user hands it over: the field errors in the files, the simulated
    readings in run/, `sync: {mode: auto}`."""
    exp = fa.make_experiment(
        folder, vdir, fa.CONDITIONS["all"], seed, cell.width, cell.height, SLATE["s"]
    )
    write_simulated_run(
        folder / "run",
        cell_walk(cell),
        (fa.T0, fa.T0 + duration),
        covers=covers(duration),
        seed=seed,
        rate_hz=rssi_rate,
        receiver=RECEIVER_MAC if RECEIVER["on"] else None,
    )
    doc = safe_yaml.load_file(exp)
    doc["rssi"] = "run"
    doc["sync"] = {"mode": "slate" if SLATE["s"] else "auto"}
    exp.write_text(safe_yaml.dump(doc, sort_keys=False), encoding="utf-8")
    if RECEIVER["on"]:
        add_receiver(exp)
    return exp


@dataclass
class MatrixRow:
    cell: str
    seed: int
    posed: float
    median_cm: float
    p95_cm: float
    rot_median_deg: float
    within: float
    label_median_cm: float = float("nan")
    label_p95_cm: float = float("nan")
    label_within: float = float("nan")
    sync_error_ms: float = float("nan")
    readout_ms: list[float] = field(default_factory=list)
    printed_scale: float = float("nan")
    seconds: float = 0.0
    n_compared: int = 0
    n_within: int = 0
    n_labels: int = 0
    n_labels_within: int = 0


def run_and_score(exp: Path, cell: Cell, duration: float, seed: int, jobs: int) -> MatrixRow:
    """`annotator run` in this process, scored against the render's exact walk."""
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment
    from annotator.vision.detection import DetectorSettings

    t = time.perf_counter()
    experiment = load_experiment(exp)
    try:
        detector = DetectorSettings(profile_corners=PROFILE["on"])
        track = TrackSettings(jobs=jobs, detector=detector)
        run = run_experiment(experiment, RunSettings(track=track))
    except Exception as e:  # noqa: BLE001 - a failed cell is a row, not the end of the bench
        print(f"{cell.name} seed {seed}: annotator run failed: {e}", flush=True)
        nan = float("nan")
        return MatrixRow(cell.name, seed, 0.0, nan, nan, nan, nan)
    write_run_outputs(exp.parent / "results", experiment, run, plots=False)
    return score(exp.parent / "results", exp.parent, cell, duration, seed, time.perf_counter() - t)


def score(
    results: Path, render: Path, cell: Cell, duration: float, seed: int, seconds: float
) -> MatrixRow:
    """A run's written results (report.json, trajectory.csv, annotated.parquet) against the
    render's exact walk (truth.csv and the walk itself at every reading's time)."""
    import pandas as pd

    nan = float("nan")
    report = json.loads((results / "report.json").read_text(encoding="utf-8"))
    traj = read_trajectory(results / "trajectory.csv")
    truth = read_trajectory(render / "truth.csv")
    starts = {"front": fa.T0 - SLATE["s"], "back": fa.T0 + fa.START_OFFSET - SLATE["s"]}
    cams = report["sync"]["cameras"]
    found = {n: float(c["video_start"]) for n, c in cams.items()}
    sync = [abs(found[n] - starts[n]) * 1000 for n in found]
    # The trajectory's times are the videos' clock mapped onto the RSSI clock by the sync
    # (t = start + pts (1 + drift)): score it on the video clock through the front camera's map
    # (the sync's error is scored on its own, and in the labels). Row by row against truth.csv
    # this gives the same figures.
    drift = float(cams["front"].get("drift") or 0.0)
    t_video = starts["front"] + (traj.t - found["front"]) / (1.0 + drift)
    cmp = compare_to_truth(
        t_video, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    outside = np.ones(len(traj.t), bool)
    for start, length in covers(duration):
        outside &= ~(
            (t_video >= fa.T0 + start) & (t_video <= fa.T0 + start + length + COVER_RAMP_S)
        )
    ok = np.isfinite(cmp.position_error)
    err = cmp.position_error[ok]
    sigma = traj.quality["sigma_m"][ok]
    # labelled readings against the walk at their own time: where the bundle's beacon was, or
    # in receiver mode its receiver's antenna
    labels = pd.read_parquet(results / "annotated.parquet")
    true_pos, true_rot = cell_walk(cell)(labels["t_ns"].to_numpy() / 1e9)
    if RECEIVER["on"]:
        true_pos = true_pos + true_rot.apply(np.asarray(RECEIVER_ANTENNA, float))
    lerr = np.linalg.norm(labels[["x", "y", "z"]].to_numpy() - true_pos, axis=1)
    lsig = labels["pos_sigma"].to_numpy()
    refined = report.get("refinement", {})
    printed = refined.get("printed_length", {})
    return MatrixRow(
        cell.name,
        seed,
        float(np.mean(traj.valid[outside])),
        100 * float(np.median(err)) if err.size else nan,
        100 * float(np.percentile(err, 95)) if err.size else nan,
        float(np.median(cmp.rotation_error_deg[ok])) if err.size else nan,
        float(np.mean(err < fa.COVERAGE_K * sigma)) if err.size else nan,
        100 * float(np.median(lerr)) if lerr.size else nan,
        100 * float(np.percentile(lerr, 95)) if lerr.size else nan,
        float(np.mean(lerr < fa.COVERAGE_K * lsig)) if lerr.size else nan,
        float(np.mean(sync)),
        [1000 * float(c.get("readout_s") or 0.0) for c in refined.get("cameras", {}).values()],
        float(printed.get("scale", nan)),
        seconds,
        int(err.size),
        int(np.sum(err < fa.COVERAGE_K * sigma)),
        int(lerr.size),
        int(np.sum(lerr < fa.COVERAGE_K * lsig)),
    )


def fmt(v: float, spec: str) -> str:
    return fa.fmt(v, spec)


def row_text(r: MatrixRow) -> str:
    ro = "/".join(fmt(v, ".1f") for v in r.readout_ms) or "-"
    return (
        f"{r.cell:10} {r.seed:4d} {fmt(100 * r.posed, '5.1f')}% {fmt(r.median_cm, '7.2f')} "
        f"{fmt(r.p95_cm, '7.2f')} {fmt(r.rot_median_deg, '8.3f')} {fmt(100 * r.within, '7.1f')}% "
        f"{fmt(r.label_median_cm, '7.2f')} {fmt(r.label_p95_cm, '7.2f')} "
        f"{fmt(100 * r.label_within, '7.1f')}% {fmt(r.sync_error_ms, '6.1f')} {ro:>11} "
        f"{fmt(r.printed_scale, '7.4f')} {r.seconds:5.0f}s"
    )


HEADER = (
    f"{'cell':10} {'seed':>4} {'posed':>6} {'median':>7} {'p95':>7} {'rot med':>8} {'<2.8sig':>8} "
    f"{'lab med':>7} {'lab p95':>7} {'lab<2.8':>8} {'sync':>6} {'readout ms':>11} {'printed':>7} "
    f"{'time':>6}"
)


def cell_summary(rows: list[MatrixRow]) -> list[str]:
    """Per cell: mean over seeds and the worst seed; then the mean over cells and the worst."""
    out, means = [], {}
    for name in dict.fromkeys(r.cell for r in rows):
        mine = [r for r in rows if r.cell == name]
        med = np.array([r.median_cm for r in mine])
        n, k = sum(r.n_compared for r in mine), sum(r.n_within for r in mine)
        within = k / n if n else float("nan")
        nl, kl = sum(r.n_labels for r in mine), sum(r.n_labels_within for r in mine)
        readout = [v for r in mine for v in r.readout_ms]
        means[name] = (
            float(np.mean([r.posed for r in mine])),
            float(np.nanmean(med)),
            float(np.nanmean([r.p95_cm for r in mine])),
            within,
        )
        worst = mine[int(np.nanargmax(med))] if np.isfinite(med).any() else mine[0]
        out.append(
            f"{name:10} seeds {len(mine)}: posed {100 * means[name][0]:5.1f} %, median "
            f"{fmt(means[name][1], '.2f')} cm, p95 {fmt(means[name][2], '.2f')} cm, within 2.8 "
            f"sigma {fmt(100 * within, '.1f')} % pooled; worst seed {worst.seed}: median "
            f"{fmt(worst.median_cm, '.2f')} cm, posed {100 * worst.posed:.1f} %; labels median "
            f"{fmt(float(np.nanmean([r.label_median_cm for r in mine])), '.2f')} cm, p95 "
            f"{fmt(float(np.nanmean([r.label_p95_cm for r in mine])), '.2f')} cm, within "
            f"{fmt(100 * kl / nl if nl else float('nan'), '.1f')} %; sync error median "
            f"{fmt(float(np.nanmedian([r.sync_error_ms for r in mine])), '.1f')} ms; readout "
            f"{fmt(float(np.mean(readout)) if readout else float('nan'), '.1f')} ms "
            f"(true {1000 * TRUE_READOUT_S:.0f})"
        )
    if means:
        worst_cell = max(means, key=lambda c: means[c][1] if np.isfinite(means[c][1]) else np.inf)
        out.append(
            f"{'all cells':10} mean median {fmt(float(np.nanmean([m[1] for m in means.values()])), '.2f')} cm, "
            f"mean posed {100 * float(np.mean([m[0] for m in means.values()])):.1f} %; worst cell "
            f"{worst_cell} (median {fmt(means[worst_cell][1], '.2f')} cm, posed "
            f"{100 * means[worst_cell][0]:.1f} %, within {fmt(100 * means[worst_cell][3], '.1f')} %)"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--duration", type=float, default=30.0, help="walk length, s (default 30)")
    ap.add_argument("--cells", default=",".join(CELLS), help=f"subset of {', '.join(CELLS)}")
    ap.add_argument("--seeds", default="0,1,2,3,4", help="comma-separated seeds (default 0-4)")
    ap.add_argument("--jobs", type=int, default=2, help="processes for rendering and tracking")
    ap.add_argument("--keep", type=Path, help="keep every experiment and trajectory here")
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "ble-groundtruth-field-videos",
        help="rendered videos, keyed by their render arguments",
    )
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="score the runs already under --keep again (no render, no run)",
    )
    ap.add_argument(
        "--rssi-rate",
        type=float,
        default=2.0,
        help="adverts/s of the simulated beacon (2: about the published dataset's readings per "
        "sensor; the hands-cover sync's error shrinks as it grows)",
    )
    ap.add_argument(
        "--sync",
        choices=("cover", "slate"),
        default="cover",
        help="how the videos are put on the RSSI clock: the hands cover (sync.mode: auto) or the "
        "clock slate filmed for 1 s at each end (sync.mode: slate)",
    )
    ap.add_argument(
        "--receiver",
        action="store_true",
        help="receiver mode: the bundle carries a receiver (10 cm above its beacon) and a beacon "
        "sits at each of the site's 12 sensor positions; every reading the receiver took is "
        "labelled with its antenna's position",
    )
    ap.add_argument(
        "--profile-corners",
        action="store_true",
        help="track with the detector's profile model (annotator track --profile-corners)",
    )
    args = ap.parse_args()
    SLATE["s"] = 1.0 if args.sync == "slate" else 0.0
    RECEIVER["on"] = args.receiver
    PROFILE["on"] = args.profile_corners
    names = [c.strip() for c in args.cells.split(",") if c.strip()]
    unknown = [n for n in names if n not in CELLS]
    if unknown:
        raise SystemExit(f"--cells: unknown {', '.join(unknown)} (known: {', '.join(CELLS)})")
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    args.cache.mkdir(parents=True, exist_ok=True)
    work = args.keep or Path(tempfile.mkdtemp(prefix="field-matrix-"))
    rows: list[MatrixRow] = []
    print(
        f"walks of {args.duration:g} s, every field error on, RSSI {args.rssi_rate:g} adverts/s, "
        f"sync by the {args.sync}{', receiver mode' if args.receiver else ''}"
        f"{', profile corners' if args.profile_corners else ''}; cells "
        f"{', '.join(names)}"
    )
    print(HEADER, flush=True)
    try:
        for seed in seeds:
            for name in names:
                cell = CELLS[name]
                if args.rescore:
                    folder = work / f"{name}-s{seed}"
                    if not (folder / "results" / "report.json").is_file():
                        continue
                    row = score(folder / "results", folder, cell, args.duration, seed, float("nan"))
                    rows.append(row)
                    print(row_text(row), flush=True)
                    continue
                vdir = cell_video(args.cache, cell, args.duration, seed, args.jobs)
                exp = make_experiment(
                    work / f"{name}-s{seed}", vdir, cell, args.duration, seed, args.rssi_rate
                )
                row = run_and_score(exp, cell, args.duration, seed, args.jobs)
                rows.append(row)
                print(row_text(row), flush=True)
    finally:
        if args.keep is None and not args.rescore:
            shutil.rmtree(work, ignore_errors=True)
    print()
    for line in cell_summary(rows):
        print(line)
    if args.json is not None:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
