"""`annotator fingerprints`: stationary recordings (or annotated moving captures) -> .hst."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import LazyProgress, console, one_line_errors
from annotator.commands._format_errors import format_errors
from annotator.errors import ConfigError

HELP = (
    "Build fingerprint histograms (.hst) from RSSI recordings.\n\n"
    "Stationary mode (default): PATHS are .mbd files, or folders of them, named "
    "<alias>_<x>_<y>_<z>.mbd (one sensor, beacon standing still at x, y, z), as in the "
    "published dataset's fpt/ folder. Each (position, sensor, beacon) gets a histogram of its "
    "readings over the --bins range, one bin per dBm, normalised to sum to 1; readings outside "
    "the range are dropped first. The output matches the published .hst files.\n\n"
    "Moving mode (--from-annotated DIR): annotated track .mbd files "
    "(ts,sensor,beacon,rssi,x,y,z,...) are binned into --cell metre grid cells; each cell "
    "visited becomes a reference position.\n\n"
    "Examples:\n\n"
    "  annotator fingerprints fpt/ --out tetam.hst --devices cnf/tetam.dev\n\n"
    "  annotator fingerprints --from-annotated run1/annotated --cell 0.5 --out auto.hst\n"
)


def fingerprints(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="The .hst file to write.", show_default=False)
    ],
    paths: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Stationary .mbd files or folders of them.", metavar="PATHS", show_default=False
        ),
    ] = None,
    devices: Annotated[
        Path | None,
        typer.Option(
            help="Site devices file (.dev) copied into the .hst; when it lists beacons only those are "
            "kept. Default: the built-in tetam site if it knows every sensor, else the MACs seen."
        ),
    ] = None,
    bins: Annotated[
        str, typer.Option(help="RSSI range LO:HI in dBm, one bin per dBm.")
    ] = "-100:-20",
    from_annotated: Annotated[
        list[Path] | None,
        typer.Option(
            "--from-annotated",
            help="Annotated track .mbd files or folders (moving mode); repeatable.",
        ),
    ] = None,
    cell: Annotated[float, typer.Option(help="Grid cell size in metres (moving mode).")] = 0.5,
    min_readings: Annotated[
        int,
        typer.Option(
            help="Moving mode: least in-range readings for a (cell, sensor, beacon) histogram."
        ),
    ] = 1,
) -> None:
    from annotator.core import fingerprints as fp
    from annotator.io import radio_data
    from bgt_core.formats.devices import read_dev

    with one_line_errors(), format_errors():
        if bool(paths) == bool(from_annotated):
            raise ConfigError("give either stationary PATHS or --from-annotated DIR (not both)")
        try:
            edges = fp.rssi_edges(*fp.parse_range(bins))
        except ValueError as e:
            raise ConfigError(f"--bins: {e}") from None
        if from_annotated and not cell > 0:
            raise ConfigError(f"--cell must be positive, got {cell}")
        devs = read_dev(devices) if devices is not None else None
        sources = list(from_annotated or paths or [])
        files = (
            radio_data.annotated_files(sources)
            if from_annotated
            else [f for f, _, _ in radio_data.stationary_files(sources)]
        )
        with LazyProgress(console=console, transient=True) as bar:
            task = bar.add_task("reading recordings", total=len(files))

            def advance(n: int) -> None:
                bar.advance(task, n)

            if from_annotated:
                result = radio_data.annotated_fingerprints(
                    sources, edges, cell, devs, min_readings=min_readings, progress=advance
                )
            else:
                result = radio_data.stationary_fingerprints(sources, edges, devs, progress=advance)
        radio_data.save_fingerprints(result, out)
        h = result.histograms
        n_hist = sum(len(b) for s in h.fingerprints.values() for b in s.values())
        console.print(
            f"wrote {out}: {len(h.fingerprints)} positions, {n_hist} histograms from "
            f"{result.files} files ({result.used} of {result.readings} readings in range)",
            highlight=False,
        )


def register(app: typer.Typer) -> None:
    app.command("fingerprints", help=HELP)(fingerprints)
