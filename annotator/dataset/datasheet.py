"""The dataset's README.md: a datasheet generated from the campaign and the runs' reports, so
what it says is what the files hold."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Any

from annotator.dataset.campaign import Campaign
from annotator.dataset.runs import RunDone, suite_version


def _utc(t: float | None) -> str:
    if t is None or not math.isfinite(t):
        return "-"
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _cm(v: Any) -> str:
    return f"{100 * float(v):.2f}" if isinstance(v, int | float) and math.isfinite(v) else "-"


def _ms(v: Any) -> str:
    return f"{1000 * float(v):.1f}" if isinstance(v, int | float) and math.isfinite(v) else "-"


def run_row(name: str, report: dict[str, Any]) -> str:
    span = report.get("tracked_span", {})
    counts = report.get("counts", {})
    quality = report.get("quality", {})
    pos = quality.get("pos_sigma_m", {})
    parts = quality.get("trajectory_sigma_m", {}).get("parts_median", {})
    budget = ", ".join(f"{k.removeprefix('sigma_')} {_cm(v)}" for k, v in parts.items()) or "-"
    sync = report.get("sync", {})
    cams = sync.get("cameras", {})
    methods = sorted({str(c.get("method", "?")) for c in cams.values()})
    sync_sigma = max((c.get("video_start_sigma_s") or 0.0 for c in cams.values()), default=0.0)
    start, stop = span.get("start"), span.get("stop")
    seconds = stop - start if isinstance(start, float) and isinstance(stop, float) else math.nan
    return (
        f"| [{name}](runs/{name}/report.json) | {_utc(start)} | {seconds:.1f} | "
        f"{counts.get('labelled', 0)} of {counts.get('readings_of_beacon', 0)} | "
        f"{len(report.get('per_sensor', {}))} | {_cm(pos.get('median'))} / {_cm(pos.get('p95'))} | "
        f"{budget} | {'/'.join(methods)}, {_ms(sync_sigma)} | "
        f"![{name}](trk/{name}.png) |"
    )


def datasheet(
    campaign: Campaign,
    runs: list[RunDone],
    reports: dict[str, dict[str, Any]],
    tables: dict[str, int],
    occupancy_agreement: dict[float, float],
) -> str:
    starts = [r.get("tracked_span", {}).get("start") for r in reports.values()]
    stops = [r.get("tracked_span", {}).get("stop") for r in reports.values()]
    starts = [t for t in starts if isinstance(t, float)]
    stops = [t for t in stops if isinstance(t, float)]
    hardware = "\n".join(f"- {k}: {v}" for k, v in sorted(campaign.hardware.items()))
    lines = [
        f"# {campaign.name}",
        "",
        campaign.description
        or "An indoor-positioning dataset: BLE RSSI readings, each labelled "
        "with the position the ArUco-marker video measured for it.",
        "",
        "## What, where, when",
        "",
        f"- Site: `{campaign.site.name}` (sensors and beacons in `cnf/{campaign.site.devices.name}`"
        f", floor plan `map/{campaign.site.plan.name}`, marker map `vid/marker_positions.dat`).",
        f"- Captured: {_utc(min(starts) if starts else None)} to "
        f"{_utc(max(stops) if stops else None)}; {len(runs)} run(s).",
        f"- Built by ble-groundtruth {suite_version()} (`annotator dataset build`), from "
        f"`{campaign.path.name}`.",
        f"- Tables: {', '.join(f'parquet/{k}.parquet ({v} rows)' for k, v in tables.items())}.",
        "",
        "## Hardware",
        "",
        hardware or "- not stated in the campaign file (`hardware:`)",
        "",
        "## Runs",
        "",
        "Span and times on the sensors' clock. sigma: each labelled reading's 1-sigma position "
        "uncertainty per axis, median / p95 (cm); its budget: the medians of its parts (cm). "
        "Sync: how each video was put on the sensors' clock and the largest stated 1-sigma (ms).",
        "",
        "| run | start | seconds | labelled readings | sensors | sigma (cm) | sigma budget (cm) "
        "| sync | path |",
        "|---|---|---|---|---|---|---|---|---|",
        *(run_row(r.name, reports[r.name]) for r in runs),
        "",
        "## What the labels cannot tell",
        "",
        "- A label is the position of the bundle's antenna when the reading was taken, with the "
        "uncertainty stated per reading (`pos_sigma` in parquet/readings.parquet): the map's "
        "survey, the rig and lens calibration, the video's noise and the clock sync are in it; "
        "the antenna's own pattern and the body of whoever carried the bundle are not.",
        "- The sync's uncertainty becomes position uncertainty at walking speed (10 ms at 1 m/s "
        "is 1 cm); it is part of `pos_sigma`.",
        "- Orientation: the rotation about the vertical is known to about a degree (the marker "
        "map's survey); it is in the trajectories, not in the readings' labels.",
        "- Readings while hands covered the bundle, or outside the tracked span, are not "
        "labelled; each run's report.json counts them.",
        "",
        "## Occupancy grids",
        "",
        "Made from the floor plan (`annotator occupancy`): a cell is occupied (1) when 30 % of "
        "the plan under it is not bare floor, or a wall crosses it; free floor is 0.",
        "",
        *(
            f"- {cell:g} m: `occ/{campaign.site.name}_{float(cell)!r}.occ`"
            + (
                f" ({100 * occupancy_agreement[cell]:.1f} % of cells agree with the site's "
                "published grid)"
                if cell in occupancy_agreement
                else ""
            )
            for cell in campaign.occupancy_cells
        ),
        "",
        "## Files",
        "",
        "The formats are those of the published tetam dataset (docs/formats.md of ble-groundtruth)"
        "; `SHA256SUMS` lists every file (`sha256sum -c SHA256SUMS`).",
        "",
        "## Licence and citation",
        "",
        f"Licence: {campaign.licence}.",
        "",
        campaign.citation
        or "Cite the dataset by its name and the ble-groundtruth version that built it; the "
        "method follows Daniş et al., Pervasive and Mobile Computing, 2022.",
        "",
    ]
    return "\n".join(lines)
