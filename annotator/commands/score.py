"""`annotator score`: any localizer's position estimates against annotated ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError, NoDataError

HELP = (
    "Score position estimates against the ground truth of an annotated run or a published track."
    "\n\nESTIMATES is a CSV with a header t,x,y[,z] (Unix seconds, metres in the site frame; "
    "other columns are ignored). Each estimate is compared with the truth interpolated to its own "
    "timestamp (never extrapolated; estimates outside the truth's span or in its gaps are not "
    "scored and lower the coverage). No alignment is applied.\n\n"
    "Writes DIR/score.json (error_2d_m and error_3d_m: mean, median, rmse, ce50, ce75, ce95, max, "
    "n; the truth's own sigma; coverage; with --latency S the latency) and three PNGs: error CDF, error over time, "
    "estimates and truth on the floor plan.\n\n"
    "Example:\n\n"
    "  annotator score knn.csv --truth trk/straight_01_all_sensors.mbd --out scores/knn\n"
)


def score(
    estimates: Annotated[
        Path, typer.Argument(help="Estimates CSV: t,x,y[,z].", show_default=False)
    ],
    truth: Annotated[
        Path,
        typer.Option(
            help="Annotated run directory (trajectory.csv), trajectory.csv, or a track .mbd / folder.",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(
            "--out", "-o", help="Folder for score.json and the plots.", show_default=False
        ),
    ],
    max_gap: Annotated[
        float,
        typer.Option(
            help="Truth samples further apart than this (s) are a gap: nothing in it is scored."
        ),
    ] = 1.0,
    latency: Annotated[
        float,
        typer.Option(
            help="Also estimate the latency: the time shift within +-this many seconds (0.05 s steps) "
            "that minimises the median 2-D error; 0 = off."
        ),
    ] = 0.0,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write the PNG plots.")] = True,
) -> None:
    with one_line_errors():
        from annotator.core.scoring import score as score_estimates
        from annotator.io.scoring import read_estimates, read_truth, write_score

        if not max_gap > 0:
            raise ConfigError(f"--max-gap must be positive, got {max_gap}")
        if latency < 0:
            raise ConfigError(f"--latency must be 0 (off) or positive, got {latency}")
        est = read_estimates(estimates)
        ref = read_truth(truth)
        s = score_estimates(
            est.t, est.position, ref, max_gap_s=max_gap, latency_max_s=latency or None
        )
        if s.coverage["scored"] == 0:
            raise NoDataError(f"{estimates}: no estimate falls inside the time span of {truth}")
        path = write_score(out, s, estimates=str(estimates), truth=str(truth), has_z=est.has_z)
        if plots:
            from annotator.plots.scoring import write_score_plots

            write_score_plots(out, s, est.position, ref)
        e = s.summary_2d
        msg = (
            f"2-D error: CE50 {e.ce50:.3f} m, CE75 {e.ce75:.3f}, CE95 {e.ce95:.3f}, mean "
            f"{e.mean:.3f}, rmse {e.rmse:.3f}, max {e.max:.3f} m over {e.n} of "
            f"{s.coverage['estimates']} estimates"
        )
        if est.has_z:
            msg += f"; 3-D CE50 {s.summary_3d.ce50:.3f} m"
        if s.latency is not None:
            msg += f"; latency {s.latency.shift_s:+.2f} s"
        console.print(msg, highlight=False, soft_wrap=True, markup=False)
        console.print(f"wrote {path}", highlight=False, soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    app.command("score", help=HELP)(score)
