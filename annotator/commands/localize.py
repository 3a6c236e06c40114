"""`annotator localize`: baseline localizers (weighted kNN, grid HMM) on a radio map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

HELP = (
    "Locate a beacon from its RSSI readings with a baseline method on a radio map, writing "
    "estimates in the input format of `annotator score` (t,x,y).\n\n"
    "RUN is a collector run (rssi/), an annotated run (annotated/), a published track (.mbd file "
    "or folder) or any .mbd file. --radiomap is a folder of .grd files from `annotator radiomap`."
    "\n\n"
    "knn: every --step seconds, the mean RSSI per sensor over the last --window seconds is "
    "matched to the k cells with the nearest mean map RSSI, averaged with weights 1/(d + 1 dB); "
    "stamped at the window's centre.\n\n"
    "grid-hmm: a forward filter on the free grid cells: Gaussian motion between cells (sigma "
    "--speed x --step), each reading weighted by its RSSI's histogram bin in the cell's map; "
    "the posterior mean after each step, stamped at the step's end.\n\n"
    "Example:\n\n"
    "  annotator localize trk/straight_01 --radiomap radiomap/ --method grid-hmm --out hmm.csv\n"
)


def localize(
    run: Annotated[
        Path,
        typer.Argument(help="Readings: run folder, track folder or .mbd file.", show_default=False),
    ],
    radiomap: Annotated[Path, typer.Option(help="Folder of .grd radio maps.", show_default=False)],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Estimates CSV to write.", show_default=False)
    ],
    method: Annotated[str, typer.Option(help="knn or grid-hmm.")] = "grid-hmm",
    beacon: Annotated[
        str | None, typer.Option(help="Beacon MAC (default: the most heard beacon the map has).")
    ] = None,
    occupancy: Annotated[
        Path | None,
        typer.Option(
            help="Occupancy grid (.occ): only its free cells (value 0) are candidate positions."
        ),
    ] = None,
    k: Annotated[int, typer.Option("--k", help="knn: cells averaged.")] = 4,
    window: Annotated[float, typer.Option(help="knn: seconds of readings per estimate.")] = 2.0,
    step: Annotated[float, typer.Option(help="Seconds between estimates.")] = 0.5,
    speed: Annotated[float, typer.Option(help="grid-hmm: typical walking speed, m/s.")] = 1.0,
) -> None:
    with one_line_errors():
        import numpy as np

        from annotator.io.localize import localize_run
        from annotator.io.scoring import write_estimates

        for name, v in (("--window", window), ("--step", step), ("--speed", speed)):
            if not v > 0:
                raise ConfigError(f"{name} must be positive, got {v}")
        if k < 1:
            raise ConfigError(f"--k must be at least 1, got {k}")
        est, used = localize_run(
            run,
            radiomap,
            method,
            beacon=beacon,
            occupancy=occupancy,
            k=k,
            window_s=window,
            step_s=step,
            speed_mps=speed,
        )
        write_estimates(out, est.t, est.xy)
        n = int(np.isfinite(est.xy).all(axis=1).sum())
        console.print(
            f"wrote {n} {method} estimates of beacon {used} to {out}",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.command("localize", help=HELP)(localize)
