"""`annotator radiomap`: fingerprint histograms (.hst) -> per-sensor .grd radio maps + heat maps."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import LazyProgress, console, one_line_errors
from annotator.commands._format_errors import format_errors
from annotator.errors import ConfigError

HELP = (
    "Interpolate fingerprint histograms to every grid cell (a radio map per sensor).\n\n"
    "For each cell centre and each sensor/beacon, the k nearest fingerprints (--neighbours) are"
    " combined with inverse-distance weights (1/d^power) by averaging their quantile functions "
    "(1-D Wasserstein interpolation), so a peak moves between fingerprints instead of "
    "splitting. A fingerprint exactly at a cell centre is used unchanged.\n\n"
    "Writes <hst name>_<sensor>_<cell>.grd per sensor into --out, and a heat map of the mean "
    "RSSI (.png, over the floor plan for the built-in tetam site). With --occupancy the grid is"
    " the occupancy file's and only free cells are computed (value 0 in the published .occ "
    "files, where 1 marks desks and other occupied cells; see --free-value).\n\n"
    "Example:\n\n"
    "  annotator radiomap tetam.hst --cell 0.5 --occupancy occ/tetam_0.5.occ --out radiomap/\n"
)


def radiomap(
    hst: Annotated[
        Path,
        typer.Argument(help="Fingerprint histograms (.hst).", metavar="HST", show_default=False),
    ],
    out: Annotated[
        Path,
        typer.Option("--out", "-o", help="Folder for the .grd and .png files.", show_default=False),
    ],
    cell: Annotated[
        float | None,
        typer.Option(
            help="Cell size in metres (default: the occupancy grid's; required without one)."
        ),
    ] = None,
    occupancy: Annotated[
        Path | None,
        typer.Option(
            help="Occupancy grid (.occ): its limits and cells are used; only free cells (see "
            "--free-value) are computed."
        ),
    ] = None,
    neighbours: Annotated[
        int, typer.Option(help="Fingerprints combined per cell (k nearest).")
    ] = 4,
    power: Annotated[float, typer.Option(help="Inverse-distance weight exponent.")] = 2.0,
    free_value: Annotated[
        int,
        typer.Option(
            "--free-value",
            help="The .occ value of cells the beacon can be in (published files: 0).",
        ),
    ] = 0,
    plots: Annotated[
        bool, typer.Option("--plots/--no-plots", help="Write a heat-map PNG per sensor.")
    ] = True,
) -> None:
    from annotator.io import radio_data
    from bgt_core.formats.hst import read_hst
    from bgt_core.formats.occ import read_occ

    with one_line_errors(), format_errors():
        if neighbours < 1:
            raise ConfigError(f"--neighbours must be at least 1, got {neighbours}")
        if power <= 0:
            raise ConfigError(f"--power must be positive, got {power}")
        h = read_hst(hst)
        occ = read_occ(occupancy) if occupancy is not None else None
        site = radio_data.detect_site(h.devices)
        if free_value not in (0, 1):
            raise ConfigError(f"--free-value must be 0 or 1, got {free_value}")
        grid = radio_data.make_grid(h, cell, occ, site, free_value=free_value)
        n_sensors = len({s for v in h.fingerprints.values() for s in v})
        with LazyProgress(console=console, transient=True) as bar:
            task = bar.add_task("interpolating", total=n_sensors)

            def advance(n: int) -> None:
                bar.advance(task, n)

            maps = radio_data.radio_maps(
                h, grid, neighbours=neighbours, power=power, progress=advance
            )
            task2 = bar.add_task("writing", total=len(maps))
            written = radio_data.write_radio_maps(
                maps,
                h,
                grid,
                out,
                hst.stem,
                plots=plots,
                site=site,
                progress=lambda n: bar.advance(task2, n),
            )
        console.print(
            f"wrote {len(written)} files to {out} ({int(grid.mask.sum())} cells of "
            f"{grid.cell:g} m, {len(maps)} sensors)",
            highlight=False,
        )


def register(app: typer.Typer) -> None:
    app.command("radiomap", help=HELP)(radiomap)
