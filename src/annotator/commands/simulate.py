"""`annotator simulate`: render a synthetic two-camera experiment with known truth."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

if TYPE_CHECKING:
    from annotator.render.trajectory import LoopTrajectory, PolylineTrajectory


def parse_cover(text: str) -> tuple[float, float]:
    """'START_S:DURATION_S' -> (start, duration); ConfigError names the bad value."""
    try:
        start, duration = (float(v) for v in text.split(":"))
    except ValueError:
        raise ConfigError(f"--cover {text!r}: expected START_S:DURATION_S, e.g. 1.0:1.5") from None
    if start < 0 or duration <= 0:
        raise ConfigError(f"--cover {text!r}: start must be >= 0 and duration > 0")
    return start, duration


def path_trajectory(path: str, t0: float, speed: float, dwell: float,
                    turn: bool) -> LoopTrajectory | PolylineTrajectory:
    """--path value -> the trajectory to render: `loop`, a preset polyline or a waypoints YAML."""
    from annotator.commands.evaluate import load_waypoints
    from annotator.render.trajectory import PRESET_PATHS, LoopTrajectory, PolylineTrajectory

    if path == "loop":
        return LoopTrajectory(t0=t0, speed=speed)
    if path in PRESET_PATHS:
        waypoints = PRESET_PATHS[path]
    elif path.endswith((".yaml", ".yml")):
        waypoints = tuple((float(x), float(y)) for x, y in load_waypoints(Path(path)))
    else:
        raise ConfigError(f"--path {path!r}: expected loop, {', '.join(PRESET_PATHS)} or a FILE.yaml with "
                          "'waypoints: [[x, y], ...]'")
    return PolylineTrajectory(waypoints, t0=t0, speed=speed, dwell=dwell, turn=turn)


def simulate(
    out: Annotated[Path, typer.Option("--out", help="Folder to write the experiment into (created).")],
    duration: Annotated[float, typer.Option(help="Length of the front video, seconds.")] = 20.0,
    path: Annotated[str, typer.Option(
        help="loop (rounded rectangle), rectangle or zigzag (the paper's kind of planned path, "
             "walked with a stop at each corner), or FILE.yaml with 'waypoints: \\[\\[x, y], ...]' in "
             "room metres. Polyline paths also write path.yaml for `annotator evaluate --path`.")] = "loop",
    speed: Annotated[float, typer.Option(help="Bundle walking speed along the path, m/s.")] = 0.4,
    dwell: Annotated[float, typer.Option(
        help="Polyline paths: seconds standing at each corner, turning to the new heading.")] = 2.0,
    turn: Annotated[bool, typer.Option(
        help="Polyline paths: face along each segment; --no-turn keeps the first heading throughout.")] = True,
    width: Annotated[int, typer.Option(help="Frame width, px.")] = 960,
    height: Annotated[int, typer.Option(help="Frame height, px.")] = 540,
    fps: Annotated[float, typer.Option(help="Frames per second of both videos.")] = 30.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise and textures.")] = 0,
    start_offset: Annotated[float, typer.Option(
        help="The back camera starts this many seconds after the front one.")] = 0.41,
    cover: Annotated[list[str] | None, typer.Option(
        help="Hands over both lenses at START_S:DURATION_S after the start (repeatable).")] = None,
    t0: Annotated[float, typer.Option(help="Wall-clock Unix time of the first front frame.")] = 1_700_000_000.0,
    noise: Annotated[float, typer.Option(help="Sensor noise standard deviation, gray levels.")] = 2.0,
    exposure: Annotated[float, typer.Option(
        help="Exposure time, s: the image integrates the motion over it (motion blur); 0 = none.")] = 1 / 120,
    jobs: Annotated[int, typer.Option(help="Render the two cameras in this many processes.")] = 1,
) -> None:
    """Render the tetam marker room along a path into front.mp4/back.mp4 plus experiment.yaml,
    rig.yaml, front.yaml/back.yaml (calibrations), marker_positions.dat, truth.csv and, for
    polyline paths, path.yaml."""
    with one_line_errors():
        from annotator.render import render_experiment

        covers = [parse_cover(c) for c in cover or []]
        if duration <= start_offset or fps <= 0 or width < 64 or height < 64 or speed < 0 or dwell < 0 \
                or not 0 <= exposure < 1 / fps:
            raise ConfigError("need duration > start-offset, fps > 0, speed >= 0, dwell >= 0, "
                              "0 <= exposure < 1/fps and a frame of at least 64x64")
        trajectory = path_trajectory(path, t0, speed, dwell, turn)
        with Progress(TextColumn("{task.description:>6}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                      TimeRemainingColumn(), console=console) as bar:
            tasks: dict[str, int] = {}

            def progress(name: str, done: int, total: int) -> None:
                if name not in tasks:
                    tasks[name] = bar.add_task(name, total=total)
                bar.update(tasks[name], completed=done)

            result = render_experiment(out, trajectory, (t0, t0 + duration),
                                       width=width, height=height, fps=fps, start_offset=start_offset,
                                       covers=covers, seed=seed, noise_sigma=noise, exposure=exposure,
                                       jobs=jobs, progress=progress)
        frames = ", ".join(f"{k} {v} frames" for k, v in result.frames.items())
        extra = " and path.yaml" if (result.out_dir / "path.yaml").exists() else ""
        console.print(f"wrote {result.experiment} ({frames}), {result.truth.name}{extra}", highlight=False,
                      soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate)
