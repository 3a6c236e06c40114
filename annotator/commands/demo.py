"""`annotator demo`: the README's first command; capture, render, annotate and score with no hardware."""

from __future__ import annotations

import datetime as dt
import signal
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import Progress
from rich.table import Table

from annotator.commands._common import console, one_line_errors, stage_columns, stage_progress

out_console = Console(emoji=False)


def _utc(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    return dt.datetime.fromtimestamp(t_ns / 1e9, tz=dt.UTC).strftime("%H:%M:%S.%f")[:-3]


def capture_table(cap: Any) -> Table:
    table = Table(title=f"capture: {sum(f.rows for f in cap.files)} readings in {cap.run_dir}")
    for col, right in (
        ("file (rssi/)", False),
        ("rows", True),
        ("first (UTC)", False),
        ("last (UTC)", False),
    ):
        table.add_column(col, justify="right" if right else "left", overflow="fold")
    for f in cap.files:
        table.add_row(f.path.name, str(f.rows), _utc(f.first_ns), _utc(f.last_ns))
    return table


def result_table(summary: dict[str, Any]) -> Table:
    from annotator.core.labeling import describe_counts

    e, c = summary["error_cm"], summary["coverage"]
    table = Table(title="annotation against the known truth", show_header=False)
    table.add_column("what")
    table.add_column("value", overflow="fold")

    def cm(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f} cm"

    table.add_row(
        "position error (labelled readings)",
        f"median {cm(e['median'])}, p95 {cm(e['p95'])}, max {cm(e['max'])} (n = {e['n']})",
    )
    whose = "taken by the receiver" if summary.get("mode") == "receiver" else "of the beacon"
    table.add_row(
        f"readings {whose} ({c['readings_of_beacon']})",
        escape(describe_counts(summary["counts"])),
    )
    for name, s in summary["sync"].items():
        sigma = "" if s["sigma_ms"] is None else f" ± {s['sigma_ms']:.1f} ms"
        end = s.get("error_end_ms")
        at_end = (
            ""
            if end is None or abs(end - s["error_ms"]) < 0.05
            else f", {end:+.1f} ms at the last frame"
        )
        table.add_row(
            f"{name} video start",
            f"found {s['found']:.4f}, true {s['true']:.4f}: error "
            f"{s['error_ms']:+.1f} ms{sigma}{at_end} ({s['method']})",
        )
    return table


def demo(
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            help="Folder for everything the demo writes (created; must not hold an earlier demo).",
        ),
    ] = Path("demo-output"),
    duration: Annotated[
        float,
        typer.Option(
            help="Seconds of video (the capture runs ~6 s longer). Render and tracking time grow with it."
        ),
    ] = 30.0,
    end_cover: Annotated[
        bool,
        typer.Option(
            "--end-cover/--no-end-cover",
            help="A second hands-cover event 3 s before the end (lets the "
            "annotator fit clock drift when the two are >= 10 s apart).",
        ),
    ] = True,
    jobs: Annotated[
        int, typer.Option(help="Processes for rendering and tracking (one per camera).")
    ] = 2,
    seed: Annotated[
        int, typer.Option(help="Seed of the simulated radio and the render noise.")
    ] = 0,
    receiver: Annotated[
        bool,
        typer.Option(
            "--receiver",
            help="The other direction: beacons at the site's 12 sensor positions, a receiver on "
            "the bundle. The readings are simulated (no collector or agents), the walk rendered, "
            "and `annotator run` in receiver mode labels every reading the receiver took.",
        ),
    ] = False,
) -> None:
    """Run the whole pipeline on this machine with no hardware, then score it.

    1. a collector and three simulated sensor agents (pi-1..pi-3, 4 tetam sensors each) record a run
       over loopback Zenoh while a beacon walks a loop, with hands over it 2 s after the start;
    2. the same walk is rendered as front/back camera video (the back camera starts 0.35 s later);
    3. `annotator run` (sync.mode auto: it is not told when the videos started) labels the readings;
    4. the labels are compared with the true path: position error, coverage, sync error.

    Writes OUT/capture (the run), OUT/experiment (videos, experiment.yaml), OUT/results (annotated
    files, report.json, plots), OUT/logs and OUT/demo_summary.json.

    With --receiver the same walk runs the other way (fixed beacons, a receiver on the bundle).
    """
    with one_line_errors():
        from annotator.demo import DemoError, DemoSettings, run_demo

        if jobs < 1:
            raise DemoError("--jobs must be >= 1")
        # SIGTERM (a closed terminal, `kill`) takes the same way out as Ctrl-C, so the
        # collector and agents are stopped too.
        signal.signal(signal.SIGTERM, signal.default_int_handler)
        settings = DemoSettings(
            out=out.absolute(), duration_s=duration, end_cover=end_cover, jobs=jobs, seed=seed
        )
        with Progress(*stage_columns(), console=console) as bar:
            progress = stage_progress(bar)

            def note(text: str) -> None:
                bar.console.print(escape(text), highlight=False, soft_wrap=True)

            def on_capture(cap: Any) -> None:
                bar.console.print(capture_table(cap))

            try:
                if receiver:
                    from annotator.demo_receiver import run_receiver_demo

                    result = run_receiver_demo(settings, progress)
                    on_capture(result.capture)
                else:
                    result = run_demo(settings, progress, note, on_capture)
            except KeyboardInterrupt:
                # The child processes are already stopped (annotator.demo cleans up on any exit).
                raise DemoError("interrupted; the collector and agents were stopped") from None
        s = result.summary
        out_console.print(result_table(s))
        out_console.print(
            f"results:  {result.results}  (report.json, annotated/, annotated.parquet)",
            highlight=False,
            soft_wrap=True,
        )
        for p in s["plots"]:
            out_console.print(f"plot:     {p}", highlight=False, soft_wrap=True)
        out_console.print(
            f"summary:  {result.summary_path}   (demo took {s['wall_time_s']:.0f} s)",
            highlight=False,
            soft_wrap=True,
        )


def register(app: typer.Typer) -> None:
    app.command("demo")(demo)
