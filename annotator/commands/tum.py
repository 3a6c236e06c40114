"""`annotator tum`: export a trajectory, a track or estimates as a TUM file for evo and friends."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

HELP = (
    "Export poses as a TUM trajectory file: one line 't x y z qx qy qz qw' per pose.\n\n"
    "INPUT is a trajectory.csv or an annotated run directory (full pose), a published track "
    "(.mbd file or folder: the pose at each timestamp, orientations projected to the nearest "
    "rotation), or an estimates CSV t,x,y[,z] (identity orientation, z 0 when absent).\n\n"
    "--at ESTIMATES.csv writes INPUT interpolated at the estimates' timestamps, exactly as "
    "`annotator score` compares them (never extrapolated; times it would not score are left "
    "out). --flat writes z = 0, for 2-D figures.\n\n"
    "Example (the same figures as `annotator score`, error_3d_m):\n\n"
    "  annotator tum trk/straight_01_all_sensors.mbd --at est.csv --out truth.tum\n\n"
    "  annotator tum est.csv --out est.tum\n\n"
    "  evo_ape tum truth.tum est.tum\n"
)


def tum(
    source: Annotated[
        Path,
        typer.Argument(
            metavar="INPUT", help="Trajectory, run dir, track or estimates.", show_default=False
        ),
    ],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="TUM file to write.", show_default=False)
    ],
    at: Annotated[
        Path | None, typer.Option(help="Estimates CSV: write INPUT interpolated at its timestamps.")
    ] = None,
    flat: Annotated[bool, typer.Option(help="Write z = 0 (2-D comparisons).")] = False,
    max_gap: Annotated[
        float, typer.Option(help="With --at: INPUT samples further apart than this (s) are a gap.")
    ] = 1.0,
) -> None:
    with one_line_errors():
        from annotator.io.scoring import read_estimates
        from annotator.io.tum import read_poses, resample, write_tum

        if not max_gap > 0:
            raise ConfigError(f"--max-gap must be positive, got {max_gap}")
        poses = read_poses(source)
        if at is not None:
            poses = resample(poses, read_estimates(at).t, max_gap_s=max_gap)
        n = write_tum(out, poses, flat=flat)
        console.print(f"wrote {n} poses to {out}", highlight=False, soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    app.command("tum", help=HELP)(tum)
