"""`annotator simulate`: render a synthetic two-camera experiment with known truth."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import Progress

from annotator.commands._common import console, one_line_errors, stage_columns, stage_progress
from annotator.errors import ConfigError

if TYPE_CHECKING:
    from annotator.render.trajectory import LoopTrajectory, PolylineTrajectory, RestFirst


def parse_cover(text: str) -> tuple[float, float]:
    """'START_S:DURATION_S' -> (start, duration); ConfigError names the bad value."""
    try:
        start, duration = (float(v) for v in text.split(":"))
    except ValueError:
        raise ConfigError(f"--cover {text!r}: expected START_S:DURATION_S, e.g. 1.0:1.5") from None
    if start < 0 or duration <= 0:
        raise ConfigError(f"--cover {text!r}: start must be >= 0 and duration > 0")
    return start, duration


def simulate(
    out: Annotated[
        Path, typer.Option("--out", help="Folder to write the experiment into (created).")
    ],
    duration: Annotated[float, typer.Option(help="Length of the front video, seconds.")] = 20.0,
    path: Annotated[
        str,
        typer.Option(
            help="loop (rounded rectangle), rectangle or zigzag (the paper's kind of planned path, "
            "walked with a stop at each corner), or FILE.yaml with 'waypoints: [[x, y], ...]' in "
            "room metres. Polyline paths also write path.yaml for `annotator evaluate --path`."
        ),
    ] = "loop",
    speed: Annotated[float, typer.Option(help="Bundle walking speed along the path, m/s.")] = 0.4,
    motion: Annotated[
        str,
        typer.Option(
            help="How the bundle is carried: walk (held in front, slow wobble, height 1.3-1.8 m), "
            "cart (a level cart: no wobble, 1.2 m; with --path rectangle: straight pushes and "
            "in-place turns at the corners) or hand (carried in one hand: more wobble, a 2 cm "
            "bounce and jolts at every step)."
        ),
    ] = "walk",
    dwell: Annotated[
        float,
        typer.Option(
            help="Polyline paths: seconds standing at each corner, turning to the new heading."
        ),
    ] = 2.0,
    turn: Annotated[
        bool,
        typer.Option(
            help="Polyline paths: face along each segment; --no-turn keeps the first heading throughout."
        ),
    ] = True,
    width: Annotated[int, typer.Option(help="Frame width, px.")] = 960,
    height: Annotated[int, typer.Option(help="Frame height, px.")] = 540,
    fps: Annotated[float, typer.Option(help="Frames per second of both videos.")] = 30.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise and textures.")] = 0,
    start_offset: Annotated[
        float, typer.Option(help="The back camera starts this many seconds after the front one.")
    ] = 0.41,
    cover: Annotated[
        list[str] | None,
        typer.Option(
            help="Hands over both lenses at START_S:DURATION_S after the start (repeatable)."
        ),
    ] = None,
    t0: Annotated[
        float, typer.Option(help="Wall-clock Unix time of the first front frame.")
    ] = 1_700_000_000.0,
    noise: Annotated[
        float | None,
        typer.Option(
            help="Sensor noise standard deviation, gray levels. Default 2 (5 with --imaging real).",
            show_default=False,
        ),
    ] = None,
    exposure: Annotated[
        float | None,
        typer.Option(
            help="Exposure time, s: the image integrates the motion over it (motion blur); 0 = none. "
            "Default 1/120 (0.008 with --errors field).",
            show_default=False,
        ),
    ] = None,
    jobs: Annotated[int, typer.Option(help="Render the two cameras in this many processes.")] = 1,
    jig: Annotated[
        float,
        typer.Option(
            help="Seconds the bundle first rests on a jig at the path's start pose; the jig's pose "
            "goes into experiment.yaml (refine: jig:), off by its 1 mm / 0.1 deg sigma when the "
            "files carry errors. `track` then takes the rig's gauge from the rest. 0 = no jig.",
            min=0.0,
        ),
    ] = 0.0,
    errors: Annotated[
        str,
        typer.Option(
            "--errors",
            help="Preset of real-world errors: none, or field (survey 1.5 cm / 1 deg, rig 3 mm / "
            "1 deg, focal 0.4 %, principal point 1 px, wide k1=-0.28 lens, 15 ms readout, "
            "8 ms exposure, 10 % flicker). The options below override single values.",
            rich_help_panel="Real-world errors",
        ),
    ] = "none",
    survey_m: Annotated[
        float | None,
        typer.Option(
            "--survey-m",
            help="Marker map written with this 1-sigma position error per axis, m.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    survey_deg: Annotated[
        float | None,
        typer.Option(
            "--survey-deg",
            help="Marker map written with this 1-sigma orientation error per axis, deg.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    rig_m: Annotated[
        float | None,
        typer.Option(
            "--rig-m",
            help="rig.yaml: each camera's position in the bundle off by this 1-sigma per axis, m.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    rig_deg: Annotated[
        float | None,
        typer.Option(
            "--rig-deg",
            help="rig.yaml: each camera's orientation in the bundle off by this 1-sigma per axis, deg.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    focal_error: Annotated[
        float | None,
        typer.Option(
            "--focal-error",
            help="Calibrations: fx and fy off by this relative 1-sigma (one factor for both), "
            "e.g. 0.004.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    principal_error: Annotated[
        float | None,
        typer.Option(
            "--principal-error",
            help="Calibrations: cx and cy each off by this 1-sigma, px.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    distortion_error: Annotated[
        float | None,
        typer.Option(
            "--distortion-error",
            help="Calibrations: k1 and k2 each off by this 1-sigma.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    lens: Annotated[
        str | None,
        typer.Option(
            help="Lens rendered (and written): mild (k1 ~ -0.08), wide (radial-tangential, k1 = -0.28) or "
            "fisheye (OpenCV's fisheye model). Default mild (wide with --errors field).",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    k1: Annotated[
        float | None,
        typer.Option(
            help="Replace the lens' first radial coefficient.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    readout: Annotated[
        float | None,
        typer.Option(
            help="Rolling-shutter readout, s: row v of a frame stamped t is seen at t + readout*v/height; "
            "0 = global shutter (default; 0.015 with --errors field).",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    write_readout: Annotated[
        bool,
        typer.Option(
            help="Write the true readout into the calibrations (by default they say 0, as users rarely know it).",
            rich_help_panel="Real-world errors",
        ),
    ] = False,
    flicker: Annotated[
        float | None,
        typer.Option(
            help="Brightness flicker seen in the picture, relative amplitude (0.1 = +-10 %); 0 = none "
            "(default; 0.1 with --errors field).",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    surveyed: Annotated[
        int | None,
        typer.Option(
            help="Write only this many markers (a random choice by --seed) into the marker map, as if the "
            "surveyor skipped the rest; default all.",
            rich_help_panel="Real-world errors",
            show_default=False,
        ),
    ] = None,
    flicker_hz: Annotated[
        float,
        typer.Option(
            help="Flicker frequency, Hz (lamps on 50 Hz mains: 100).",
            rich_help_panel="Real-world errors",
        ),
    ] = 100.0,
    imaging: Annotated[
        str,
        typer.Option(
            help="What the camera adds to the picture: clean, or real (defocus 1.5 px, JPEG "
            "quality 60, 40 % vignetting, light uneven by 20 % and drifting 10 %, auto-exposure "
            "steps of 8 %, noise 5). The options below override single values.",
            rich_help_panel="Imaging and printing",
        ),
    ] = "clean",
    defocus: Annotated[
        float | None,
        typer.Option(
            help="Lens out of focus: Gaussian blur sigma, px.",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    jpeg_quality: Annotated[
        int | None,
        typer.Option(
            "--jpeg-quality",
            help="Every frame through JPEG at this quality (1-100); 0 = none.",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    vignetting: Annotated[
        float | None,
        typer.Option(
            help="The picture's corners this much darker than its centre (0.4 = 40 %).",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    uneven_light: Annotated[
        float | None,
        typer.Option(
            "--uneven-light",
            help="Brightness gradient of +- this across the picture, turning slowly.",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    light_change: Annotated[
        float | None,
        typer.Option(
            "--light-change",
            help="The light level drifts by +- this (relative) over a 10 s period.",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    exposure_steps: Annotated[
        float | None,
        typer.Option(
            "--exposure-steps",
            help="Auto-exposure: a new gain within +- this (relative) every 3 s.",
            rich_help_panel="Imaging and printing",
            show_default=False,
        ),
    ] = None,
    print_scale: Annotated[
        float,
        typer.Option(
            "--print-scale",
            help="Markers printed this many times the markers.length experiment.yaml says "
            "(1.007: a printer's rounding makes 0.298 m squares 0.300 m).",
            rich_help_panel="Imaging and printing",
        ),
    ] = 1.0,
    print_scatter: Annotated[
        float,
        typer.Option(
            "--print-scatter",
            help="Each marker's printed side off by a further N(0, this) relative.",
            rich_help_panel="Imaging and printing",
        ),
    ] = 0.0,
    slate: Annotated[
        float,
        typer.Option(
            help="Seconds each camera films the clock slate (`collector slate`, a 60 Hz screen) "
            "before the walk and after it; experiment.yaml then says `sync: {mode: slate}`. "
            "0: no slate.",
            rich_help_panel="Radio",
            min=0.0,
            max=10.0,
        ),
    ] = 0.0,
    rssi: Annotated[
        bool,
        typer.Option(
            "--rssi/--no-rssi",
            help="Also write the RSSI the bundle's beacon gives at the site's 12 sensors along the "
            "walk into run/ (a collector run; experiment.yaml's rssi: names it), so `annotator run` "
            "works on the render. --no-rssi leaves an empty rssi/ folder for readings of your own.",
            rich_help_panel="Radio",
        ),
    ] = True,
    rssi_rate: Annotated[
        float,
        typer.Option(
            "--rssi-rate",
            help="Adverts per second of the simulated beacon; each sensor hears ~95 % of them "
            "(the published dataset has about 2 readings/s per sensor).",
            rich_help_panel="Radio",
            min=0.1,
            max=100.0,
        ),
    ] = 2.0,
    receiver: Annotated[
        bool,
        typer.Option(
            "--receiver",
            help="The other direction: beacons at the site's 12 sensor positions, heard by a "
            "receiver on the bundle (10 cm above its beacon). Writes run/rssi/simulated/"
            "<receiver>.mbd, `receiver:` into experiment.yaml and `antennas:` into rig.yaml, so "
            "`annotator run` labels every reading the receiver took.",
            rich_help_panel="Radio",
        ),
    ] = False,
) -> None:
    """Render the tetam marker room along a path into front.mp4/back.mp4 plus experiment.yaml,
    rig.yaml, front.yaml/back.yaml (calibrations), marker_positions.dat, truth.csv, the RSSI
    the walk gives (run/: run.yaml and rssi/simulated/<sensor>.mbd, from 2 s before the first
    frame to 2 s after the last, hands-cover drops included) and, for polyline paths, path.yaml.
    `annotator run OUT/experiment.yaml` then tracks, synchronises and labels it.

    The videos are always rendered with the exact room, rig and lenses; real-world errors
    (--errors field, --survey-m, ...) only go into the files handed to the annotator. The exact
    files are kept under true/ (true/experiment.yaml tracks the same videos) and
    perturbation.yaml lists true and written values per marker and per camera."""
    with one_line_errors():
        from annotator.render import render_experiment
        from annotator.render.conditions import path_trajectory, resolve_errors
        from annotator.render.errors import FileErrors
        from annotator.render.trajectory import RestFirst

        covers = [parse_cover(c) for c in cover or []]
        e = resolve_errors(
            errors,
            survey_m=survey_m,
            survey_deg=survey_deg,
            rig_m=rig_m,
            rig_deg=rig_deg,
            focal_rel=focal_error,
            principal_px=principal_error,
            distortion=distortion_error,
            lens=lens,
            readout=readout,
            exposure=exposure,
            flicker=flicker,
        )
        exposure_s, readout_s, flicker_a = (
            float(e["exposure"]),
            float(e["readout"]),
            float(e["flicker"]),
        )
        if (
            duration <= start_offset
            or fps <= 0
            or width < 64
            or height < 64
            or speed < 0
            or dwell < 0
            or not 0 <= exposure_s < 1 / fps
        ):
            raise ConfigError(
                "need duration > start-offset, fps > 0, speed >= 0, dwell >= 0, "
                "0 <= exposure < 1/fps and a frame of at least 64x64"
            )
        if not 0 <= readout_s < 1 / fps:
            raise ConfigError(
                f"--readout {readout_s}: must be >= 0 and shorter than a frame (1/fps)"
            )
        if not 0 <= flicker_a < 1 or flicker_hz <= 0:
            raise ConfigError("--flicker must be in [0, 1) and --flicker-hz > 0")
        from annotator.render.camera import LENSES

        if e["lens"] not in LENSES:
            raise ConfigError(f"--lens {e['lens']!r}: expected one of {', '.join(LENSES)}")
        try:
            file_errors = FileErrors(
                float(e["survey_m"]),
                float(e["survey_deg"]),
                float(e["rig_m"]),
                float(e["rig_deg"]),
                float(e["focal_rel"]),
                float(e["principal_px"]),
                float(e["distortion"]),
                write_readout,
                surveyed,
                seed,
            )
        except ValueError as err:
            raise ConfigError(f"error magnitudes: {err}") from None
        from annotator.render.conditions import IMAGING_NOISE, resolve_imaging

        try:
            camera_imaging = resolve_imaging(
                imaging,
                defocus_px=defocus,
                jpeg_quality=jpeg_quality,
                vignetting=vignetting,
                uneven_light=uneven_light,
                light_change=light_change,
                exposure_steps=exposure_steps,
            )
        except ValueError as err:
            raise ConfigError(f"--imaging: {err}") from None
        noise_sigma = IMAGING_NOISE[imaging] if noise is None else noise
        if not (noise_sigma >= 0 and 0.5 < print_scale < 2.0 and 0 <= print_scatter < 0.1):
            raise ConfigError(
                "need --noise >= 0, --print-scale in (0.5, 2) and --print-scatter in [0, 0.1)"
            )
        walk = path_trajectory(path, t0, speed, dwell, turn, motion)
        trajectory = RestFirst(walk, jig) if jig > 0 else walk
        if jig > 0 and jig >= duration - start_offset:
            raise ConfigError(f"--jig {jig}: the rest must end before the video (--duration)")
        if receiver and not rssi:
            raise ConfigError("--receiver simulates readings: it needs --rssi")
        with Progress(*stage_columns(6), console=console) as bar:
            progress = stage_progress(bar)

            result = render_experiment(
                out,
                trajectory,
                (t0, t0 + duration),
                width=width,
                height=height,
                fps=fps,
                start_offset=start_offset,
                covers=covers,
                seed=seed,
                noise_sigma=noise_sigma,
                exposure=exposure_s,
                jobs=jobs,
                lens=str(e["lens"]),
                k1=k1,
                readout=readout_s,
                flicker=flicker_a,
                flicker_hz=flicker_hz,
                errors=file_errors,
                progress=progress,
                rssi_dir="run" if rssi else "rssi",
                imaging=camera_imaging,
                print_scale=print_scale,
                print_scatter=print_scatter,
                slate=slate,
            )
        if slate > 0:
            text = result.experiment.read_text(encoding="utf-8")
            result.experiment.write_text(
                text.replace("  mode: manual\n", "  mode: slate\n", 1), encoding="utf-8"
            )
        if jig > 0:
            write_jig(result.experiment, trajectory, t0, t0 + jig, seed, file_errors.perturbs)
        frames = ", ".join(f"{k} {v} frames" for k, v in result.frames.items())
        extra = [result.truth.name]
        if rssi:
            from annotator.render.rssi import RECEIVER_MAC, add_receiver, write_simulated_run

            run = write_simulated_run(
                out / "run",
                trajectory,
                (t0, t0 + duration),
                covers=covers,
                seed=seed,
                rate_hz=rssi_rate,
                receiver=RECEIVER_MAC if receiver else None,
            )
            if receiver:
                add_receiver(result.experiment)
                extra.append(
                    f"run/ ({run.readings} readings of {len(run.beacons)} fixed beacons at "
                    f"receiver {run.receiver})"
                )
            else:
                extra.append(
                    f"run/ ({run.readings} readings of beacon {run.beacon} at "
                    f"{len(run.files)} sensors)"
                )
        if (result.out_dir / "path.yaml").exists():
            extra.append("path.yaml")
        console.print(
            f"wrote {result.experiment} ({frames}), {', '.join(extra)}",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def write_jig(
    experiment: Path,
    trajectory: LoopTrajectory | PolylineTrajectory | RestFirst,
    start: float,
    end: float,
    seed: int,
    perturbed: bool,
) -> None:
    """Add the rest's jig to experiment.yaml (``refine: jig:``) and its written error to
    perturbation.yaml; the true experiment under true/ gets the exact jig."""
    import numpy as np
    import yaml

    from annotator.core.priors import JIG_SIGMA_DEG, JIG_SIGMA_M
    from annotator.render.errors import jig_entry

    pos, rot = trajectory(np.array([start]))
    for path, off in (
        (experiment, perturbed),
        (experiment.parent / "true" / experiment.name, False),
    ):
        if not path.is_file():
            continue
        entry, error = jig_entry(pos[0], rot[0], start, end, JIG_SIGMA_M, JIG_SIGMA_DEG, seed, off)
        text = path.read_text(encoding="utf-8")
        path.write_text(
            text
            + yaml.safe_dump({"refine": {"jig": entry}}, default_flow_style=None, sort_keys=False),
            encoding="utf-8",
        )
        if path == experiment:
            with (path.parent / "perturbation.yaml").open("a", encoding="utf-8") as f:
                f.write(yaml.safe_dump({"jig": error}, default_flow_style=None))


def register(app: typer.Typer) -> None:
    app.command(
        "simulate", short_help="Render a capture of the marker room with known truth (no hardware)."
    )(simulate)
