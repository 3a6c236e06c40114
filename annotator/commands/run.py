"""`annotator run`: track, synchronise with the RSSI log and label every reading, in one go."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from annotator.commands._common import (
    LazyProgress,
    console,
    default_jobs,
    one_line_errors,
    print_sigma_budget,
    stage_columns,
    stage_progress,
)
from annotator.errors import ConfigError

if TYPE_CHECKING:
    from annotator.core.experiment import Experiment
    from annotator.io.report_records import Report
    from annotator.pipeline import RunResult

log = logging.getLogger(__name__)


def write_run_outputs(
    out_dir: str | Path, exp: Experiment, result: RunResult, *, plots: bool = True
) -> Report:
    """What `annotator run` writes into ``out_dir``: trajectory.csv, annotated/, annotated.parquet,
    the plots, refined/ (after a self-calibration) and report.json. Returns the report as
    written: ``result.report`` plus the names of the plot and refined files."""
    from annotator.core.uncertainty import sigma_budget
    from annotator.io.outputs import (
        POINT_TRAJECTORY,
        write_annotated_mbd,
        write_parquet,
        write_report,
    )
    from annotator.io.trajectory import write_trajectory

    traj, table, labels = result.trajectory, result.rssi, result.labels
    report: Report = {**result.report}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    receiver_mode = report.get("mode") == "receiver"
    by = "beacon" if receiver_mode else "sensor"
    write_trajectory(out / "trajectory.csv", traj)
    # The labelled antenna's own path, when it is not the bundle's origin: the truth that
    # `annotator score` takes for position estimates of that antenna.
    point = np.asarray(report.get("labelled_point_bundle_m", [0.0, 0.0, 0.0]), dtype=float)
    wanted = POINT_TRAJECTORY["receiver" if receiver_mode else "beacon"]
    if not (receiver_mode or point.any()):
        wanted = ""
    for name in POINT_TRAJECTORY.values():
        if name == wanted:
            write_trajectory(out / name, traj.at_point(point))
            report["antenna_trajectory"] = name
        else:  # an earlier run's into the same folder would be taken for this one's
            (out / name).unlink(missing_ok=True)
    write_annotated_mbd(out / "annotated", table, labels, by=by)
    write_parquet(out / "annotated.parquet", table, labels)
    if plots:
        from annotator.plots.run import write_run_plots

        valid_t = traj.t[traj.valid]
        written = write_run_plots(
            out,
            trajectory=traj.position,
            t_s=table.t_seconds(),
            rssi=table.rssi,
            sensor=table.beacon if receiver_mode else table.sensor,
            labelled=labels.labelled,
            label_positions=labels.positions,
            events=[(e.cover, e.release) for e in result.sync.rssi_events],
            span=(float(valid_t[0]), float(valid_t[-1])) if valid_t.size else None,
            markers=exp.markers.markers,
            video_starts={n: c.video_start for n, c in result.sync.clocks.items()},
            by=by,
        )
        report["plots"] = {k: p.name for k, p in written.items()}
    budget = sigma_budget(traj.quality)
    if budget is not None:  # the trajectory's rows; pos_sigma_m is the labelled readings'
        report["quality"] = {**report.get("quality", {}), "trajectory_sigma_m": budget.as_dict()}
    if result.refinement is not None:
        from annotator.io.refined import write_refined

        files = write_refined(out / "refined", result.refinement)
        report["refinement"] = {
            **result.refinement.report,
            "files": {k: f"refined/{v}" for k, v in files.items()},
        }
    write_report(out / "report.json", report)
    log.info("run: %d of %d readings labelled into %s", int(labels.labelled.sum()), len(table), out)
    return report


def run(
    experiment: Annotated[
        Path, typer.Argument(help="experiment.yaml (markers, rig, videos, rssi, sync).")
    ],
    out: Annotated[Path, typer.Option("--out", help="Folder for the results (created).")],
    method: Annotated[
        str,
        typer.Option(
            help="Tracking method: 'rig' (joint multi-marker, smoothed) "
            "or 'paper' (the published per-marker method)."
        ),
    ] = "rig",
    jobs: Annotated[
        int | None,
        typer.Option(
            help="Worker processes for decoding, detection and the joint solves.",
            show_default="one per core",
        ),
    ] = None,
    max_gap: Annotated[
        float,
        typer.Option(
            help="Leave a reading unlabelled when the poses around it are further apart than this, s."
        ),
    ] = 0.5,
    beacon: Annotated[
        str | None,
        typer.Option(
            help="MAC of the bundle's beacon (default: sync.beacon, else the most often heard one)."
        ),
    ] = None,
    receiver: Annotated[
        str | None,
        typer.Option(
            help="Receiver mode: MAC of the sensor on the bundle; every reading it took, of any "
            "beacon, is labelled with its antenna's position (rig.yaml antennas.receiver). "
            "Excludes --beacon.",
            show_default="experiment.yaml's receiver:, else beacon mode",
        ),
    ] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write the PNG plots.")] = True,
    refine: Annotated[
        str | None,
        typer.Option(
            help="none | map | all: self-calibration, as in `annotator track`; writes DIR/refined/ and "
            "report.json's refinement section.",
            show_default="experiment.yaml's refine.mode, else all",
        ),
    ] = None,
) -> None:
    """Write DIR/trajectory.csv, DIR/annotated/<sensor>.mbd + all_sensors.mbd (the dataset's trk
    rows), DIR/annotated.parquet (plus quality columns), DIR/report.json and plots.

    Beacon mode (the default) labels every reading of the bundle's beacon by the fixed sensors.
    Receiver mode (--receiver, or receiver: in experiment.yaml) labels every reading the
    bundle's receiver took, of any beacon: DIR/annotated/<beacon>.mbd per beacon heard, and
    DIR/receiver_trajectory.csv, the receiver antenna's path (`annotator score`'s truth).

    With `sync.mode: auto` each video's clock is found from the hands-cover event (video goes
    dark, the RSSI drops: of the beacon at every sensor, or of every beacon at the receiver);
    with `manual`, sync.video_start is used as given.
    """
    with one_line_errors():
        from annotator.core.labeling import describe_counts
        from annotator.io.experiment import load_experiment
        from annotator.pipeline import RunSettings, TrackSettings, run_experiment
        from bgt_core.wire import normalize_mac

        if refine is not None and refine not in ("none", "map", "all"):
            raise ConfigError(f"--refine must be none, map or all, not {refine!r}")
        if method not in ("rig", "paper"):
            raise ConfigError(f"--method must be 'rig' or 'paper', not {method!r}")
        jobs = default_jobs() if jobs is None else jobs
        if max_gap <= 0 or jobs < 1:
            raise ConfigError("--max-gap must be > 0 and --jobs >= 1")
        macs: dict[str, str | None] = {}
        for flag, value in (("--beacon", beacon), ("--receiver", receiver)):
            try:
                macs[flag] = None if value is None else normalize_mac(value)
            except ValueError:
                raise ConfigError(f"{flag} {value!r} is not a MAC address") from None
        if beacon is not None and receiver is not None:
            raise ConfigError("--beacon and --receiver exclude each other; give one")
        exp = load_experiment(experiment)
        settings = RunSettings(
            track=TrackSettings(method=method, jobs=jobs, refine=refine or exp.priors.mode),
            max_gap=max_gap,
            beacon=macs["--beacon"],
            receiver=macs["--receiver"],
        )
        # Lazy: the bars appear with the first frame, so an error in the RSSI files (read
        # first) is printed alone.
        with LazyProgress(*stage_columns(), console=console) as bar:
            result = run_experiment(exp, settings, stage_progress(bar))
        rep = write_run_outputs(out, exp, result, plots=plots)
        for name, cam in rep["sync"]["cameras"].items():
            sig = cam["video_start_sigma_s"]
            sig_text = f" ± {sig * 1000:.1f} ms" if sig is not None and math.isfinite(sig) else ""
            console.print(
                f"{name}: video_start {cam['video_start']:.4f}{sig_text} ({cam['method']})",
                highlight=False,
            )
        who = (
            f"receiver {rep['receiver']} ({len(rep['per_beacon'])} beacons heard)"
            if rep.get("mode") == "receiver"
            else f"beacon {rep['beacon']}"
        )
        console.print(
            f"{who}: {describe_counts(rep['counts'])} -> {out}",
            highlight=False,
            markup=False,
        )
        print_sigma_budget(
            console,
            result.trajectory.quality,
            refined=result.refinement is not None,
            jig=exp.priors.jig is not None,
        )


def register(app: typer.Typer) -> None:
    app.command(
        "run", short_help="Track, synchronise and label every RSSI reading: the annotated dataset."
    )(run)
