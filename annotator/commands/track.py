"""`annotator track`: camera videos of an experiment -> DIR/trajectory.csv (thin; see pipeline.py)."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TaskID, TextColumn, TimeRemainingColumn

from annotator.commands._common import (
    LazyProgress,
    default_jobs,
    one_line_errors,
    print_sigma_budget,
)

if TYPE_CHECKING:
    from annotator.core.refine import Refinement


class Method(StrEnum):
    rig = "rig"
    paper = "paper"


class Refine(StrEnum):
    none = "none"
    map = "map"
    all = "all"


REFINE_HELP = (
    "rig: self-calibration from the video after a first pass (bundle adjustment over keyframes, "
    "priors from experiment.yaml's refine: section). map: the marker map (and markers the survey "
    "skipped); all: also the rig, the intrinsics and distortion, the rolling-shutter readout. "
    "none: the files as given."
)


class CornerRefine(StrEnum):
    subpix = "subpix"
    contour = "contour"
    apriltag = "apriltag"
    none = "none"


def track(
    experiment: Annotated[
        Path, typer.Argument(help="experiment.yaml (markers, rig, videos, sync).")
    ],
    out: Annotated[Path, typer.Option("--out", help="Folder for trajectory.csv (created).")],
    method: Annotated[
        Method,
        typer.Option(
            help="rig: joint multi-marker PnP over both cameras + RTS/SO(3) smoother (accurate). "
            "paper: the per-marker averaging + Kalman filter of Daniş et al. 2022, for comparison."
        ),
    ] = Method.rig,
    jobs: Annotated[
        int | None,
        typer.Option(
            help="Worker processes: the videos are decoded and detected in parallel, then the joint "
            "solves share them.",
            show_default="one per core",
        ),
    ] = None,
    downscale: Annotated[
        float | None,
        typer.Option(
            help="Detect markers on frames scaled by this factor, then refine the corners at full "
            "resolution. 1 = detect at full resolution.",
            show_default="halve while wider than 1280 px, so 0.5 for 1080p",
        ),
    ] = None,
    corner_refine: Annotated[
        CornerRefine, typer.Option(help="ArUco corner refinement.")
    ] = CornerRefine.subpix,
    board_refine: Annotated[
        bool,
        typer.Option(
            help="Recover missed markers by projecting the known room (refineDetectedMarkers)."
        ),
    ] = True,
    thorough_detect: Annotated[
        bool,
        typer.Option(
            help="Threshold every frame at three window sizes (OpenCV's default) instead of one. By "
            "default only frames where one window finds fewer than two markers get the three; "
            "this is ~2x slower detection for ~1-2 % more markers."
        ),
    ] = False,
    edge_corners: Annotated[
        bool | None,
        typer.Option(
            help="Place each corner where the fitted outer edges of the marker's black square meet "
            "(unbiased for small and large markers; see docs/annotator.md, 'Corners'). Default: "
            "on where detection runs on a downscaled copy (frames wider than 1280 px) or with "
            "--profile-corners, off otherwise.",
            show_default=False,
        ),
    ] = None,
    profile_corners: Annotated[
        bool,
        typer.Option(
            help="Finish the edge corners of small markers with a model of the blurred image "
            "across each side, the marker's own bits included: unbiased on small and blurred "
            "markers, where the edge fit is pulled 0.1-0.4 px inward. It finds the printed size "
            "and helps fast walks, costs ~3x the detection time, and on slow walks it has not "
            "yet beaten the default (docs/annotator.md, 'Corners').",
        ),
    ] = False,
    joint: Annotated[
        bool,
        typer.Option(
            help="rig: solve near-simultaneous frames of all cameras jointly (motion-compensated)."
        ),
    ] = True,
    refine: Annotated[
        Refine | None,
        typer.Option(help=REFINE_HELP, show_default="experiment.yaml's refine.mode, else all"),
    ] = None,
    max_frames: Annotated[
        int | None, typer.Option(help="Stop each video after this many frames.")
    ] = None,
    batch_frames: Annotated[
        int,
        typer.Option(
            help="paper: F, frames per batch, counted over all cameras in time order "
            "(15 at two 30 fps cameras = 0.25 s)."
        ),
    ] = 15,
    close: Annotated[int, typer.Option(help="paper: C, poses kept from the closest markers.")] = 20,
    keep: Annotated[int, typer.Option(help="paper: U, poses left after outlier elimination.")] = 10,
    q: Annotated[float, typer.Option(help="paper: Kalman measurement noise (q I).")] = 0.15,
    process_noise: Annotated[
        float, typer.Option(help="paper: Kalman process noise (random walk).")
    ] = 0.01,
) -> None:
    """Track the camera-beacon bundle through the marker room; writes DIR/trajectory.csv.

    Columns: t (Unix s), x, y, z (beacon, m), r11..r33 (R_world_bundle, row-major), then
    quality columns (markers, rms_px, sigma_m). Rows without a trustworthy pose are NaN.
    """
    from annotator.errors import ConfigError
    from annotator.io.experiment import load_experiment
    from annotator.io.trajectory import write_trajectory
    from annotator.pipeline import TrackSettings, track
    from annotator.vision.detection import DetectorSettings
    from annotator.vision.paper import PaperSettings

    console = Console(stderr=True, emoji=False)
    with one_line_errors():
        jobs = default_jobs() if jobs is None else jobs
        if jobs < 1:
            raise ConfigError("--jobs must be at least 1")
        if downscale is not None and not 0 < downscale <= 1:
            raise ConfigError("--downscale must be in (0, 1]")
        if not (
            batch_frames >= 1 and close >= 1 and 1 <= keep <= close and q > 0 and process_noise >= 0
        ):
            raise ConfigError(
                "paper parameters: need --batch-frames >= 1, 1 <= --keep <= --close, --q > 0 "
                "and --process-noise >= 0"
            )
        exp = load_experiment(experiment)
        settings = TrackSettings(
            method=method.value,
            jobs=jobs,
            joint=joint,
            max_frames=max_frames,
            refine=refine.value if refine is not None else exp.priors.mode,
            detector=DetectorSettings(
                dictionary=exp.markers.dictionary,
                corner_refine=corner_refine.value,
                downscale=downscale,
                board_refine=board_refine,
                threshold_windows=(3, 23, 10) if thorough_detect else (7, 7, 10),
                edge_corners=edge_corners,
                profile_corners=profile_corners,
            ),
            paper=PaperSettings(
                frames=batch_frames, close=close, keep=keep, q=q, process=process_noise
            ),
        )
        # Lazy: no bars until a video reports its first frames.
        with LazyProgress(
            TextColumn("{task.description:>8}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            console=console,
        ) as bar:
            tasks: dict[str, TaskID] = {}

            def report(name: str, done: int, total: int) -> None:
                if not tasks:
                    tasks.update({n: bar.add_task(n, total=None) for n in exp.videos})
                bar.update(tasks[name], completed=done, total=max(total, done))

            result = track(exp, settings, report)
        traj = result.trajectory
        out.mkdir(parents=True, exist_ok=True)
        path = out / "trajectory.csv"
        write_trajectory(path, traj)
        if result.refinement is not None:
            _report_refinement(out, result.refinement, console)
        n_ok = int(traj.valid.sum())
        console.print(
            f"wrote {path}: {len(traj)} rows, {n_ok} with a pose "
            f"({100 * n_ok / max(len(traj), 1):.0f} %), method {method.value}",
            highlight=False,
        )
        print_sigma_budget(
            console,
            traj.quality,
            refined=result.refinement is not None,
            jig=exp.priors.jig is not None,
        )


def _report_refinement(out: Path, refinement: Refinement, console: Console) -> None:
    """refined/ (map, rig, calibrations, refinement.json) and a few lines on the console."""
    import json
    import math

    from annotator.io.refined import write_refined

    write_refined(out / "refined", refinement)
    rep = refinement.report
    (out / "refined" / "refinement.json").write_text(json.dumps(rep, indent=1), encoding="utf-8")
    for name, cam in rep["cameras"].items():
        console.print(
            f"refine {name}: reprojection {cam['rms_px_before']:.2f} -> {cam['rms_px_after']:.2f} px, "
            f"focal {100 * cam['focal_change_rel'][0]:+.2f} %, readout {1000 * cam['readout_s']:.1f} ms",
            highlight=False,
        )
        for note in cam.get("notes", []):
            console.print(f"  {name}: {note}", highlight=False, markup=False)
    printed = rep.get("printed_length", {})
    if printed.get("estimated"):
        console.print(
            f"refine: markers printed {printed['found_m']:.4f} m "
            f"({printed['scale']:.4f} +- {printed['scale_sigma']:.4f} x the stated "
            f"{printed['stated_m']} m): {printed['note']}",
            highlight=False,
            markup=False,
        )
    if rep["markers_mapped"]:
        console.print(
            f"refine: mapped markers {rep['markers_mapped']} from the video", highlight=False
        )
    for m in rep["markers_moved"]:
        console.print(
            f"refine: marker {m['id']} is {100 * math.hypot(*m['offset_m']):.1f} cm from its "
            f"survey: moved since the survey?",
            style="yellow",
            highlight=False,
        )
    jig = rep.get("jig")
    if jig is not None:
        shift_mm = 1000 * math.hypot(*jig["shift_m"])
        console.print(
            f"jig: {jig['rows']} rows at rest; the rig turned by {jig['rotation_deg']:.2f} deg and "
            f"shifted by {jig['rig_shift_share'] * shift_mm:.1f} mm, the map by "
            f"{1000 * math.hypot(*jig['map_shift_m']):.1f} mm",
            highlight=False,
        )


def register(app: typer.Typer) -> None:
    app.command("track")(track)
