"""Accuracy of `annotator track` under the real-world errors of a capture, one at a time and all together.

    python bench/field_accuracy.py                              # 30 s walks, every condition
    python bench/field_accuracy.py --duration 10 --conditions none,all
    python bench/field_accuracy.py --seeds 0,1,2 --keep runs/   # keep experiments and trajectories

Each condition renders the same walk through the tetam room (the default loop, 960x540, two
cameras) with `annotator.render.render_experiment`, gives `annotator track` the files a real
capture would have (the condition's errors; see docs/renderer.md) and scores the trajectory with
`annotator.core.evaluate.compare_to_truth` against the exact truth. Conditions:

    none        exact files, global shutter, no motion blur (exposure 0), the mild lens, no flicker
    survey      marker map off by 1.5 cm / 1 deg per axis (1-sigma per marker)
    rig         rig.yaml off by 3 mm / 1 deg per axis and camera
    intrinsics  focal length off by 0.4 % (1-sigma), principal point by 1 px per axis
    rolling     15 ms rolling-shutter readout (calibrations say 0)
    exposure    8 ms exposure: motion blur
    lens        a wide k1 = -0.28 lens (calibrated exactly)
    flicker     10 % lamp flicker at 100 Hz
    all         all of the above at once (`annotator simulate --errors field`)
    surveyed8   all of the above, and only 8 of the room's markers in the map (the rest skipped)
    fisheye     an OpenCV fisheye (equidistant) lens in place of the mild one (calibrated exactly)
    fisheye-all every error of `all`, with the fisheye lens in place of the wide one

When `annotator track --help` offers `--refine`, every condition is tracked twice: with
`--refine none` and with the default. Columns: posed share of rows; position error median and
95th percentile (cm); rotation error median (deg); the share of posed rows whose 3-D error is
within 2.8 x the row's sigma_m (a per-axis 1-sigma: ~95 % for an honest sigma); the median of
3-D error / sigma_m (~1.5 for an honest sigma); tracking time. A capture's errors are correlated
(the same map and rig errors move every row alike), so one seed's coverage is close to 0 or 100 %:
the pooled coverage over seeds, printed last, is the figure that judges sigma. With one datum
draw per seed it is coarse (an honest sigma leaves all of 14 seeds inside about half the time), so
the pooled line also gives rms z: the root mean square over every compared row of 3-D error /
sigma_m / sqrt(3), 1.0 for an honest per-axis sigma, below 1 when it is cautious.

'floor' (cm, median over the walk): the error the written survey alone leaves. The video fixes the
map's shape but not where it sits in the room: that comes from the surveyed markers, so a perfect
video map fitted (rotation and shift) to the written positions of the surveyed markers the walk
saw (`markers_seen` of the refinement's report) is off by their mean survey error. Likewise the
beacon sits where the rig file puts the cameras around it: a shift common to every camera of the
rig moves no camera (the gauge), so the bundle's origin is off by the rig's mean position error,
turned with the bundle. The floor is the sum of the two. 'rot fl' (deg, median over the walk)
is the same for the orientation: the bundle's is the cameras' (which the video measures, in the
frame the survey gives the map) times the written rig's inverse, off by the rig's mean turn. No estimator can do better than this on
average (one capture may land a little below it when the map's own errors cancel part of it, or
the markers' orientation priors turn the frame the other way); a seed whose floor exceeds a target
is not expected to meet it. 'datum z' says how unlucky the survey draw was: the mean survey error
of the surveyed markers the walk saw, over the sigma the experiment states for that mean
(survey sigma / sqrt(count)), as a 3-D length. For an honest survey it is distributed as chi(3):
median 1.54, 95 % below 2.8, so a seed above ~3 drew a datum that sigma_m cannot cover.

Videos are cached under --cache keyed by everything that shapes them (render arguments and the
renderer's source), so a re-run or a new file-error condition on an existing video is quick.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import annotator.render as render_pkg
from annotator.core.evaluate import compare_to_truth
from annotator.io.experiment import load_experiment, load_rig
from annotator.io.trajectory import read_trajectory
from annotator.render import LoopTrajectory, default_cameras, render_experiment
from annotator.render.conditions import ERROR_PRESETS
from annotator.render.errors import FileErrors
from annotator.render.experiment import write_experiment_files
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir

T0 = 1_700_000_000.0
START_OFFSET = 0.41
COVERAGE_K = 2.8  # 3-D error within 2.8 sigma_m (per-axis sigma): ~95 % for a Gaussian

FIELD = ERROR_PRESETS["field"]
VIDEO_KEYS = ("lens", "readout", "exposure", "flicker")
FILE_KEYS = (
    "survey_m",
    "survey_deg",
    "rig_m",
    "rig_deg",
    "focal_rel",
    "principal_px",
    "distortion",
)


@dataclass(frozen=True)
class Condition:
    name: str
    video: dict[str, object] = field(default_factory=dict)  # overrides of the clean video
    files: dict[str, float | int] = field(default_factory=dict)  # FileErrors magnitudes


CLEAN_VIDEO: dict[str, object] = {"lens": "mild", "readout": 0.0, "exposure": 0.0, "flicker": 0.0}
CONDITIONS = {
    c.name: c
    for c in (
        Condition("none"),
        Condition(
            "survey", files={"survey_m": FIELD["survey_m"], "survey_deg": FIELD["survey_deg"]}
        ),
        Condition("rig", files={"rig_m": FIELD["rig_m"], "rig_deg": FIELD["rig_deg"]}),
        Condition(
            "intrinsics",
            files={"focal_rel": FIELD["focal_rel"], "principal_px": FIELD["principal_px"]},
        ),
        Condition("rolling", video={"readout": FIELD["readout"]}),
        Condition("exposure", video={"exposure": FIELD["exposure"]}),
        Condition("lens", video={"lens": FIELD["lens"]}),
        Condition("flicker", video={"flicker": FIELD["flicker"]}),
        Condition(
            "all",
            video={k: FIELD[k] for k in VIDEO_KEYS},
            files={k: float(FIELD[k]) for k in FILE_KEYS},
        ),
        Condition(
            "surveyed8",
            video={k: FIELD[k] for k in VIDEO_KEYS},
            files={**{k: float(FIELD[k]) for k in FILE_KEYS}, "surveyed": 8},
        ),
        Condition("fisheye", video={"lens": "fisheye"}),
        Condition(
            "fisheye-all",
            video={**{k: FIELD[k] for k in VIDEO_KEYS}, "lens": "fisheye"},
            files={k: float(FIELD[k]) for k in FILE_KEYS},
        ),
    )
}


def renderer_digest() -> str:
    """Hash of the renderer's source: a changed renderer never reuses a stale cached video."""
    h = hashlib.sha256()
    for p in sorted(Path(render_pkg.__file__).parent.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def video_key(args: dict[str, object]) -> str:
    return hashlib.sha256(json.dumps(args, sort_keys=True).encode()).hexdigest()[:16]


def render_once(
    cache: Path, args: dict[str, object], render: Callable[[Path], None], what: str
) -> Path:
    """Folder keyed by `args`: `render(folder)` fills it once (into a .part folder, renamed when
    complete), later calls find it done."""
    folder = cache / video_key(args)
    if (folder / "done.json").is_file():
        return folder
    tmp = folder.with_name(folder.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    t = time.perf_counter()
    render(tmp)
    (tmp / "done.json").write_text(json.dumps(args, indent=1), encoding="utf-8")
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    print(f"rendered {what} in {time.perf_counter() - t:.0f} s", flush=True)
    return folder


def cached_video(
    cache: Path,
    video: dict[str, object],
    duration: float,
    seed: int,
    width: int,
    height: int,
    jobs: int,
) -> Path:
    """Folder holding front.mp4, back.mp4 and truth.csv of this video, rendered if not cached."""
    args = {
        **CLEAN_VIDEO,
        **video,
        "duration": duration,
        "seed": seed,
        "width": width,
        "height": height,
        "t0": T0,
        "start_offset": START_OFFSET,
        "renderer": renderer_digest(),
    }

    def render(tmp: Path) -> None:
        render_experiment(
            tmp,
            LoopTrajectory(t0=T0),
            (T0, T0 + duration),
            width=width,
            height=height,
            start_offset=START_OFFSET,
            seed=seed,
            exposure=float(video.get("exposure", 0.0)),
            lens=str(video.get("lens", "mild")),
            readout=float(video.get("readout", 0.0)),
            flicker=float(video.get("flicker", 0.0)),
            jobs=jobs,
        )

    what = ", ".join(f"{k}={v}" for k, v in video.items()) or "clean"
    return render_once(cache, args, render, f"{duration:g} s ({what}, seed {seed})")


def link(src: Path, dst: Path) -> None:
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def make_experiment(
    folder: Path,
    video_dir: Path,
    cond: Condition,
    seed: int,
    width: int,
    height: int,
    slate: float = 0.0,
) -> Path:
    """The condition's experiment: the cached videos plus files carrying its errors. ``slate``:
    seconds of clock slate the videos start with (their true start, in true/experiment.yaml)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("front.mp4", "back.mp4", "truth.csv"):
        link(video_dir / name, folder / name)
    video = {**CLEAN_VIDEO, **cond.video}
    write_experiment_files(
        folder,
        default_cameras(width, height, str(video["lens"])),
        read_marker_map(site_dir("tetam") / "marker_positions.dat"),
        {"front": T0 - slate, "back": T0 + START_OFFSET - slate},
        readout=float(video["readout"]),
        exposure=float(video["exposure"]),
        errors=FileErrors(**cond.files, seed=seed),
        settings={"condition": cond.name, **video},
    )
    return folder / "experiment.yaml"


def annotator_cmd() -> list[str]:
    return [sys.executable, "-c", "from annotator.cli import main; main()"]


def refine_modes() -> list[str | None]:
    """[None] (today's default) or ['none', None] when `annotator track` knows --refine."""
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    res = subprocess.run(
        [*annotator_cmd(), "track", "--help"], capture_output=True, text=True, env=env, check=False
    )
    return ["none", None] if "--refine" in res.stdout else [None]


@dataclass
class Row:
    condition: str
    seed: int
    refine: str
    posed: float
    median_cm: float
    p95_cm: float
    rot_median_deg: float
    within: float  # share of compared rows with 3-D error < 2.8 sigma_m; NaN without sigma
    seconds: float
    n_compared: int = 0
    n_within: int = 0
    z_median: float = float(
        "nan"
    )  # median of 3-D error / sigma_m (~1.5 for an honest per-axis sigma)
    floor_cm: float = float(
        "nan"
    )  # median error of the survey's datum alone (see the module's doc)
    rot_floor_deg: float = float("nan")  # the same for the bundle's orientation
    datum_z: float = float("nan")  # the surveyed markers' mean survey error / its sigma (3-D)
    z2_sum: float = 0.0  # sum over the compared rows of (3-D error / sigma_m)^2 / 3


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |R a_i + t - b_i|^2 (Kabsch); a shift alone for fewer than 3 points."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    if len(a) < 3:
        return np.eye(3), cb - ca
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))])
    R = vt.T @ d @ u.T
    return R, cb - R @ ca


@dataclass(frozen=True)
class DatumFloor:
    position_cm: float  # median over the walk
    rotation_deg: float
    # |mean survey error of the surveyed markers seen| / (stated survey sigma / sqrt(count)):
    # chi(3) for an honest survey (median 1.54, 95 % below 2.8); a seed far above drew a datum
    # that sigma_m (which states the survey's sigma) cannot be expected to cover.
    datum_z: float = float("nan")


def datum_floor(exp: Path, refined: Path) -> DatumFloor:
    """The error a perfect video map fitted to the written survey of the surveyed markers the
    refinement saw, and the written rig's mean camera pose, would leave: position (median over
    the true walk) and orientation (NaN without a refinement record)."""
    nan = DatumFloor(float("nan"), float("nan"))
    record = refined / "refinement.json"
    if not record.is_file():
        return nan
    seen = set(json.loads(record.read_text(encoding="utf-8")).get("markers_seen", []))
    written = read_marker_map(exp.parent / "marker_positions.dat")
    true = read_marker_map(exp.parent / "true" / "marker_positions.dat")
    ids = sorted(i for i in written if i in seen and i in true)
    if not ids:
        return nan
    R, t = _rigid_fit(
        np.array([true[i].position for i in ids], float),
        np.array([written[i].position for i in ids], float),
    )
    truth = read_trajectory(exp.parent / "truth.csv")
    p = truth.position
    written_rig, true_rig = (
        load_rig(exp.parent / "rig.yaml").cameras,
        load_rig(exp.parent / "true" / "rig.yaml").cameras,
    )
    d_rig = np.mean(
        [written_rig[n].t_bundle_camera - true_rig[n].t_bundle_camera for n in true_rig], axis=0
    )
    err = p @ R.T + t - p - truth.rotation @ d_rig
    # Orientation: the video measures the cameras' world orientation (in the frame the survey
    # gives the map); the bundle's is that times the written rig's inverse, whose mean turn over
    # the cameras no image can tell (the gauge). Bundle error = R_map . R_wb (R_bc R_bc'^T) R_wb^T.
    rig_turn = Rotation.concatenate(
        [
            Rotation.from_matrix(true_rig[n].R_bundle_camera @ written_rig[n].R_bundle_camera.T)
            for n in true_rig
        ]
    ).mean()
    body = Rotation.from_matrix(truth.rotation)
    turn = Rotation.from_matrix(R) * body * rig_turn * body.inv()
    priors = load_experiment(exp).priors
    mean_error = np.mean([np.subtract(written[i].position, true[i].position) for i in ids], axis=0)
    stated = np.sqrt(np.mean([priors.marker(i).sigma_m ** 2 for i in ids]) / len(ids))
    return DatumFloor(
        100 * float(np.median(np.linalg.norm(err, axis=1))),
        float(np.degrees(np.median(turn.magnitude()))),
        float(np.linalg.norm(mean_error) / stated) if stated > 0 else float("nan"),
    )


def track_and_score(
    exp: Path, out: Path, refine: str | None, jobs: int, cond: str, seed: int
) -> Row:
    cmd = [*annotator_cmd(), "track", str(exp), "--out", str(out), "--jobs", str(jobs)]
    if refine is not None:
        cmd += ["--refine", refine]
    t = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - t
    label = refine or "default"
    if res.returncode != 0:
        print(
            f"{cond} seed {seed} refine {label}: annotator track failed:\n{res.stderr[-2000:]}",
            flush=True,
        )
        nan = float("nan")
        return Row(cond, seed, label, nan, nan, nan, nan, nan, seconds)
    traj = read_trajectory(out / "trajectory.csv")
    truth = read_trajectory(exp.parent / "truth.csv")
    cmp = compare_to_truth(
        traj.t, traj.position, traj.rotation, truth.t, truth.position, truth.rotation
    )
    ok = np.isfinite(cmp.position_error)
    err = cmp.position_error[ok]
    sigma = traj.quality.get("sigma_m")
    within = (
        float(np.mean(err < COVERAGE_K * sigma[ok]))
        if sigma is not None and ok.any()
        else float("nan")
    )
    if not ok.any():
        return Row(cond, seed, label, 0.0, *(4 * [float("nan")]), seconds)
    n_within = int(np.sum(err < COVERAGE_K * sigma[ok])) if sigma is not None else 0
    z_median = float(np.median(err / sigma[ok])) if sigma is not None else float("nan")
    z2_sum = float(np.sum((err / sigma[ok]) ** 2) / 3) if sigma is not None else float("nan")
    return Row(
        cond,
        seed,
        label,
        float(traj.valid.mean()),
        100 * float(np.median(err)),
        100 * float(np.percentile(err, 95)),
        float(np.median(cmp.rotation_error_deg[ok])),
        within,
        seconds,
        int(ok.sum()),
        n_within,
        z_median,
        z2_sum=z2_sum,
    )


def fmt(v: float, spec: str) -> str:
    return "-" if not np.isfinite(v) else format(v, spec)


HEADER = (
    f"{'condition':11} {'seed':>4} {'refine':8} {'posed':>6} {'median':>7} {'p95':>7} {'rot med':>8} "
    f"{'<2.8sig':>8} {'err/sig':>7} {'time':>6} {'floor':>6} {'rot fl':>6} {'datum z':>7}"
)


def row_text(r: Row) -> str:
    return (
        f"{r.condition:11} {r.seed:4d} {r.refine:8} {fmt(100 * r.posed, '5.1f')}% {fmt(r.median_cm, '7.2f')} "
        f"{fmt(r.p95_cm, '7.2f')} {fmt(r.rot_median_deg, '8.3f')} {fmt(100 * r.within, '7.1f')}% "
        f"{fmt(r.z_median, '7.2f')} {r.seconds:5.0f}s {fmt(r.floor_cm, '6.2f')} "
        f"{fmt(r.rot_floor_deg, '6.3f')} {fmt(r.datum_z, '7.2f')}"
    )


def pooled_text(rows: list[Row]) -> list[str]:
    """Per condition and refine mode over all seeds: rows within 2.8 sigma of all compared rows."""
    out = []
    keys = list(dict.fromkeys((r.condition, r.refine) for r in rows))
    for cond, refine in keys:
        mine = [r for r in rows if (r.condition, r.refine) == (cond, refine) and r.n_compared]
        n, k = sum(r.n_compared for r in mine), sum(r.n_within for r in mine)
        if n:
            seeds = ",".join(str(r.seed) for r in mine)
            rms_z = float(np.sqrt(sum(r.z2_sum for r in mine) / n))
            out.append(
                f"{cond:11} {refine:8} seeds {seeds:12} {100 * k / n:6.1f}% of {n} rows within "
                f"{COVERAGE_K} sigma; per seed {', '.join(fmt(100 * r.within, '.1f') for r in mine)} %; "
                f"rms z {fmt(rms_z, '.2f')}"
            )
    return out


def side_by_side(rows: list[Row]) -> str:
    """Per condition and seed: `--refine none` beside the default (median / p95 cm, rotation deg)."""
    by = {(r.condition, r.seed, r.refine): r for r in rows}
    lines = [
        f"{'condition':11} {'seed':>4} | {'refine none: med / p95 / rot':>30} | {'default: med / p95 / rot':>30} | "
        f"{'refine s':>8}"
    ]
    for cond, seed in dict.fromkeys((r.condition, r.seed) for r in rows):
        a, b = by.get((cond, seed, "none")), by.get((cond, seed, "default"))
        if a is None or b is None:
            continue

        def cell(r: Row) -> str:
            return f"{fmt(r.median_cm, '6.2f')} / {fmt(r.p95_cm, '6.2f')} cm / {fmt(r.rot_median_deg, '5.2f')} deg"

        lines.append(
            f"{cond:11} {seed:4d} | {cell(a):>30} | {cell(b):>30} | {b.seconds - a.seconds:7.0f}s"
        )
    lines.append(
        "refine s: the default's time minus refine none's (the refinement and the second pass)."
    )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--duration", type=float, default=30.0, help="length of the walk, s (default 30)"
    )
    ap.add_argument(
        "--conditions",
        default=",".join(CONDITIONS),
        help=f"comma-separated subset of {', '.join(CONDITIONS)} (default all of them)",
    )
    ap.add_argument(
        "--seeds",
        default="0",
        help="comma-separated seeds (render noise and error draws), default 0",
    )
    ap.add_argument(
        "--jobs", type=int, default=2, help="processes for rendering and for `annotator track`"
    )
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    ap.add_argument(
        "--keep",
        type=Path,
        help="keep each condition's experiment and trajectory under this folder",
    )
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "ble-groundtruth-field-videos",
        help="rendered videos, keyed by their render arguments (default: in the temp folder)",
    )
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument(
        "--default-only", action="store_true", help="track with the default refinement only"
    )
    args = ap.parse_args()
    names = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [n for n in names if n not in CONDITIONS]
    if unknown:
        raise SystemExit(
            f"--conditions: unknown {', '.join(unknown)} (known: {', '.join(CONDITIONS)})"
        )
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    modes = [None] if args.default_only else refine_modes()
    print(
        f"walk {args.duration:g} s, {args.width}x{args.height}, two cameras; refine modes: "
        f"{', '.join(m or 'default' for m in modes)}",
        flush=True,
    )
    args.cache.mkdir(parents=True, exist_ok=True)
    work = args.keep or Path(tempfile.mkdtemp(prefix="field-accuracy-"))
    rows: list[Row] = []
    try:
        for seed in seeds:
            for name in names:
                cond = CONDITIONS[name]
                vdir = cached_video(
                    args.cache, cond.video, args.duration, seed, args.width, args.height, args.jobs
                )
                exp = make_experiment(
                    work / f"{name}-s{seed}", vdir, cond, seed, args.width, args.height
                )
                mine = []
                for mode in modes:
                    out = exp.parent / f"track-{mode or 'default'}"
                    mine.append(track_and_score(exp, out, mode, args.jobs, name, seed))
                floor = datum_floor(exp, exp.parent / "track-default" / "refined")
                for r in mine:
                    r.floor_cm, r.rot_floor_deg = floor.position_cm, floor.rotation_deg
                    r.datum_z = floor.datum_z
                    print(row_text(r), flush=True)
                rows += mine
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(HEADER)
    for r in rows:
        print(row_text(r))
    if len(modes) > 1:
        print()
        print(side_by_side(rows))
    print(
        f"conditions: {', '.join(names)} (see --help); errors in cm against the exact truth at the same time; "
        f"'<2.8sig' = share of posed rows with 3-D error < {COVERAGE_K} x sigma_m (~95 % if sigma is honest); "
        f"'err/sig' = median of 3-D error / sigma_m (~1.5 if honest); 'floor' = median error the survey's datum and the "
        f"rig's mean position error leave (cm, see --help); 'rot fl' = the same for the orientation (deg); "
        f"'datum z' = the surveyed markers' mean survey error over its stated sigma (chi(3): 95 % below 2.8)."
    )
    print()
    print("pooled over seeds (errors of one capture are correlated: judge sigma over many seeds):")
    for line in pooled_text(rows):
        print(line)
    if args.json is not None:
        args.json.write_text(json.dumps([r.__dict__ for r in rows], indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
