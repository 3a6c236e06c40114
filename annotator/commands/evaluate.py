"""`annotator evaluate`: a trajectory against a reference trajectory or a planned path;
writes a JSON report and a PNG plot (the metrics themselves live in annotator/core/evaluate.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError
from annotator.io.waypoints import load_waypoints


def _plot_truth(png: Path, est, truth, cmp) -> None:  # noqa: ANN001 - internal helper
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=(1, 1.3))
    ax1.plot(truth.position[:, 0], truth.position[:, 1], color="0.6", lw=3, label="reference")
    ax1.plot(est.position[:, 0], est.position[:, 1], color="tab:blue", lw=1, label="trajectory")
    ax1.set(xlabel="x (m)", ylabel="y (m)", aspect="equal", title="top view")
    ax1.legend()
    t = cmp.t - cmp.t[0] if len(cmp.t) else cmp.t
    ax2.plot(t, cmp.position_error * 100, color="tab:blue", lw=1)
    ax2.set(xlabel="time (s)", ylabel="position error (cm)", title="error against the reference")
    ax3 = ax2.twinx()
    ax3.plot(t, cmp.rotation_error_deg, color="tab:orange", lw=0.8, alpha=0.7)
    ax3.set_ylabel("rotation error (deg)", color="tab:orange")
    fig.savefig(png, dpi=110)


def _plot_path(png: Path, est, waypoints: np.ndarray, cmp) -> None:  # noqa: ANN001
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=(1, 1.3))
    ax1.plot(waypoints[:, 0], waypoints[:, 1], "o-", color="0.6", lw=3, label="planned path")
    ax1.plot(est.position[:, 0], est.position[:, 1], color="tab:blue", lw=1, label="trajectory")
    ax1.set(xlabel="x (m)", ylabel="y (m)", aspect="equal", title="top view")
    ax1.legend()
    t = est.t - est.t[0] if len(est.t) else est.t
    ax2.plot(t, cmp.deviation * 100, color="tab:blue", lw=1)
    ax2.set(xlabel="time (s)", ylabel="deviation from the path (cm)", title="deviation")
    fig.savefig(png, dpi=110)


def evaluate(
    trajectory: Annotated[Path, typer.Argument(help="trajectory.csv to evaluate.")],
    truth: Annotated[
        Path | None, typer.Option(help="Reference trajectory (trajectory.csv format).")
    ] = None,
    path: Annotated[
        Path | None, typer.Option(help="Planned path YAML: waypoints: [[x, y], ...].")
    ] = None,
    report: Annotated[
        Path | None,
        typer.Option(help="JSON report to write [default: evaluation.json next to TRAJECTORY]."),
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(help="PNG plot to write [default: evaluation.png next to TRAJECTORY]."),
    ] = None,
) -> None:
    """Against --truth: position error (median, mean, 75th/95th percentile, max; no alignment,
    reference interpolated in time) and rotation error in degrees. Against --path: deviation
    from the planned polyline and along-track drag at each segment end."""
    with one_line_errors():
        from annotator.core.evaluate import compare_to_path, compare_to_truth
        from annotator.io.trajectory import read_trajectory

        if (truth is None) == (path is None):
            raise ConfigError("give exactly one of --truth TRUTH.csv or --path PATH.yaml")
        est = read_trajectory(trajectory)
        report = report or trajectory.with_name("evaluation.json")
        plot = plot or trajectory.with_name("evaluation.png")
        if truth is not None:
            ref = read_trajectory(truth)
            cmp = compare_to_truth(
                est.t, est.position, est.rotation, ref.t, ref.position, ref.rotation
            )
            body: dict[str, Any] = {
                "trajectory": str(trajectory),
                "truth": str(truth),
                **cmp.report(),
            }
            if body["compared"] == 0:
                raise ConfigError(f"{trajectory}: no pose falls inside the time range of {truth}")
            _plot_truth(plot, est, ref, cmp)
            p, r = body["position_error_m"], body["rotation_error_deg"]
            console.print(
                f"position error: median {p['median'] * 100:.2f} cm, mean {p['mean'] * 100:.2f}, "
                f"p75 {p['p75'] * 100:.2f}, p95 {p['p95'] * 100:.2f}, max {p['max'] * 100:.2f} cm "
                f"over {body['compared']} poses; rotation error median {r['median']:.2f} deg, "
                f"p95 {r['p95']:.2f} deg",
                highlight=False,
                soft_wrap=True,
                markup=False,
            )
        else:
            assert path is not None  # exactly one of --truth and --path, checked above
            wp = load_waypoints(path)
            path_cmp = compare_to_path(est.position, wp)
            body = {"trajectory": str(trajectory), "path": str(path), **path_cmp.report()}
            if body["compared"] == 0:
                raise ConfigError(f"{trajectory}: no poses to compare")
            _plot_path(plot, est, wp, path_cmp)
            d = body["deviation_m"]
            drags = ", ".join("-" if v is None else f"{v * 100:.1f}" for v in body["drag_m"])
            console.print(
                f"deviation from the path: median {d['median'] * 100:.2f} cm, p95 {d['p95'] * 100:.2f}, "
                f"max {d['max'] * 100:.2f} cm; drag at segment ends (cm): {drags}",
                highlight=False,
                soft_wrap=True,
                markup=False,
            )
        report.write_text(
            json.dumps(_json_safe(body), indent=2, allow_nan=False) + "\n", encoding="utf-8"
        )
        console.print(f"wrote {report} and {plot}", highlight=False, soft_wrap=True, markup=False)


def _json_safe(v: object) -> object:
    """NaN/inf -> null: strict JSON readers reject them."""
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def register(app: typer.Typer) -> None:
    app.command(
        "evaluate", short_help="Compare a trajectory with the exact truth or with the planned path."
    )(evaluate)
