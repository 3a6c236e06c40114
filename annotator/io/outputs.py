"""Writing the annotated results: trk-format .mbd files, annotated.parquet and report.json.

Every file is written to a temporary name and renamed into place, so an interrupted run never
leaves a half-written file where a complete one stood.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from annotator.core.labeling import Labels
from annotator.io.report_records import (
    REPORT_VERSION,
    CameraSync,
    ReadingCount,
    Report,
    Stats,
    SyncEvent,
    SyncReport,
)
from annotator.io.rssi import RssiTable
from bgt_core.formats.mbd import TRACK_COLUMNS
from bgt_core.wire import format_ts

log = logging.getLogger(__name__)

POSITION_DECIMALS = 5  # 10 um: well below the tracking error, short lines
ROTATION_DECIMALS = 6
ALL_SENSORS = "all_sensors.mbd"
# The path of the labelled antenna (when it is not the bundle's origin), beside trajectory.csv.
POINT_TRAJECTORY = {"receiver": "receiver_trajectory.csv", "beacon": "beacon_trajectory.csv"}


def _atomic_write_text(path: Path, lines: Iterable[str]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", encoding="utf-8", newline="\n") as f:
        f.writelines(lines)
    os.replace(tmp, path)


def track_lines(table: RssiTable, labels: Labels, rows: np.ndarray) -> list[str]:
    """The dataset's trk rows (``ts,sensor,beacon,rssi,x,y,z,r11..r33``) for the given row indices."""
    p = np.round(labels.positions[rows], POSITION_DECIMALS)
    r = np.round(labels.rotations[rows].reshape(-1, 9), ROTATION_DECIMALS) + 0.0  # no "-0.0"
    pf, rf = f"{{:.{POSITION_DECIMALS}f}}", f"{{:.{ROTATION_DECIMALS}f}}"
    out = []
    for k, i in enumerate(rows.tolist()):
        pos = ",".join(pf.format(v) for v in p[k])
        rot = ",".join(rf.format(v) for v in r[k])
        out.append(
            f"{format_ts(int(table.t_ns[i]))},{table.sensor[i]},{table.beacon[i]},"
            f"{int(table.rssi[i])},{pos},{rot}\n"
        )
    return out


def write_annotated_mbd(
    out_dir: str | Path, table: RssiTable, labels: Labels, *, by: str = "sensor"
) -> dict[str, Path]:
    """``<out_dir>/<MAC>.mbd`` per sensor (``by="sensor"``, beacon mode) or per beacon heard
    (``by="beacon"``, receiver mode) and ``all_sensors.mbd``, labelled rows in time order.

    ``out_dir`` belongs to these files: other ``.mbd`` files in it (an earlier run's) are removed.
    Returns {MAC or "all": path}.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = np.flatnonzero(labels.labelled)
    rows = rows[np.argsort(table.t_ns[rows], kind="stable")]
    lines = track_lines(table, labels, rows)
    written: dict[str, Path] = {}
    if by not in ("sensor", "beacon"):
        raise ValueError(f"by must be 'sensor' or 'beacon', not {by!r}")
    keys = (table.sensor if by == "sensor" else table.beacon)[rows]
    for s in sorted(set(keys.tolist())):
        mine = np.flatnonzero(keys == s)
        path = out_dir / f"{s}.mbd"
        _atomic_write_text(path, (lines[k] for k in mine))
        written[s] = path
    path = out_dir / ALL_SENSORS
    _atomic_write_text(path, lines)
    written["all"] = path
    # A sensor file left from an earlier run into the same folder would pass for this run's.
    for old in out_dir.glob("*.mbd"):
        if old not in written.values():
            log.warning("removing %s: not part of this run", old)
            old.unlink()
    log.info("wrote %d annotated rows for %d %ss to %s", len(lines), len(written) - 1, by, out_dir)
    return written


def annotated_frame(table: RssiTable, labels: Labels):  # -> pandas.DataFrame
    """Labelled rows as a DataFrame: trk columns (``ts`` exact text, plus ``t_ns``) and quality."""
    import pandas as pd

    rows = np.flatnonzero(labels.labelled)
    rows = rows[np.argsort(table.t_ns[rows], kind="stable")]
    data: dict[str, Any] = {
        "ts": [format_ts(int(v)) for v in table.t_ns[rows]],
        "t_ns": table.t_ns[rows].astype(np.int64),
        "sensor": table.sensor[rows].astype(str),
        "beacon": table.beacon[rows].astype(str),
        "rssi": table.rssi[rows].astype(np.int16),
    }
    for k, name in enumerate(TRACK_COLUMNS[4:7]):
        data[name] = labels.positions[rows, k]
    rot = labels.rotations[rows].reshape(-1, 9)
    for k, name in enumerate(TRACK_COLUMNS[7:]):
        data[name] = rot[:, k]
    data["pos_sigma"] = labels.sigma[rows]
    data["markers_used"] = labels.markers[rows].astype(np.int16)
    data["gap_s"] = labels.gap_s[rows]
    return pd.DataFrame(data)


def write_parquet(path: str | Path, table: RssiTable, labels: Labels) -> Path:
    path = Path(path)
    df = annotated_frame(table, labels)
    tmp = path.with_name(f".{path.name}.tmp")
    df.to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return path


def _json_safe(obj: Any) -> Any:
    """NaN/inf -> null, numpy scalars/arrays -> Python, Paths -> str (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_report(path: str | Path, report: Report) -> Path:
    path = Path(path)
    _atomic_write_text(path, [json.dumps(_json_safe(report), indent=2, allow_nan=False) + "\n"])
    return path


def _event_dict(e: Any, clock: Any = None) -> SyncEvent:
    d: SyncEvent = {
        "cover": e.cover,
        "release": e.release,
        "cover_sigma": e.cover_sigma,
        "release_sigma": e.release_sigma,
        "duration": e.duration,
        "signal": e.source,
    }
    if clock is not None:  # a video event: also where it lands on the RSSI clock
        d["cover_rssi_clock"] = float(clock.to_rssi(e.cover))
        d["release_rssi_clock"] = float(clock.to_rssi(e.release))
    return d


def _stats(x: np.ndarray) -> Stats:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if not x.size:
        return {"median": None, "p95": None, "max": None}
    return {
        "median": float(np.median(x)),
        "p95": float(np.percentile(x, 95)),
        "max": float(x.max()),
    }


def build_report(
    *,
    experiment: str | Path,
    sync: Any,
    beacon: str | None,
    readings_total: int,
    table: RssiTable,
    labels: Labels,
    traj_t: np.ndarray,
    traj_valid: np.ndarray,
    max_gap: float,
    method: str,
    receiver: str | None = None,
    antenna: np.ndarray | None = None,
) -> Report:
    """What report.json says: sync offsets with uncertainty, counts, coverage and quality.

    ``sync`` is an :class:`annotator.core.sync.SyncResult`; ``table`` and ``labels`` are the
    readings labelled (the bundle beacon's, or in receiver mode those ``receiver`` took) and their
    labels; ``antenna`` is the labelled point in the bundle frame.
    """
    from annotator.core.labeling import tracked_span_coverage

    tv = np.asarray(traj_t)[np.asarray(traj_valid, dtype=bool)]
    lab = labels.labelled
    cameras: dict[str, CameraSync] = {}
    for name, cm in sync.clocks.items():
        cameras[name] = {
            "video_start": cm.video_start,
            "video_start_sigma_s": cm.video_start_sigma,
            "drift": cm.drift,
            "drift_sigma": cm.drift_sigma,
            "edges_used": cm.n_edges,
            "edge_residual_rms_s": cm.residual_rms,
            "edge_bias_s": cm.edge_bias,
            "method": cm.method,
            "refined_offset_s": cm.refined_offset_s,
            "events": [_event_dict(e, cm) for e in sync.video_events.get(name, [])],
        }
        slate = sync.slates.get(name)
        if slate is not None:  # which frames showed the clock slate, on the video's own clock
            cameras[name]["slate"] = {
                "filmings_pts_s": [[round(a, 4), round(b, 4)] for a, b in slate.segments],
                "frames_used": slate.frames_used,
                "frames_refused": slate.frames_refused,
                "row_fraction": round(slate.row_fraction, 4),
            }
    sync_part: SyncReport = {
        "mode": sync.mode,
        "cameras": cameras,
        "rssi_events": [_event_dict(e) for e in sync.rssi_events],
    }
    markers = labels.markers[lab]
    column = table.beacon if receiver is not None else table.sensor
    per: dict[str, ReadingCount] = {
        s: {"readings": int(np.sum(column == s)), "labelled": int(np.sum(lab & (column == s)))}
        for s in sorted(set(column.tolist()))
    }
    report: Report = {
        "version": REPORT_VERSION,
        "experiment": str(experiment),
        "method": method,
        "mode": "receiver" if receiver is not None else "beacon",
        "beacon": beacon,
        "receiver": receiver,
        "labelled_point_bundle_m": (
            [0.0, 0.0, 0.0] if antenna is None else [float(v) for v in antenna]
        ),
        "sync": sync_part,
        "tracked_span": {
            "start": float(tv[0]) if tv.size else None,
            "stop": float(tv[-1]) if tv.size else None,
            "poses": int(tv.size),
            "frames": int(np.size(traj_t)),
        },
        "counts": {
            "readings_in_files": int(readings_total),
            "readings_of_beacon" if receiver is None else "readings_of_receiver": len(table),
            **{k.replace(" ", "_"): v for k, v in labels.counts.items()},
        },
        "coverage": {
            "labelled_of_tracked_span": tracked_span_coverage(labels),
            "labelled_of_all": float(lab.mean()) if lab.size else 0.0,
            "max_gap_s": max_gap,
        },
        "quality": {
            "pos_sigma_m": _stats(labels.sigma[lab]),
            "gap_to_pose_s": _stats(labels.gap_s[lab]),
            "markers_used": {
                "median": float(np.median(markers)) if markers.size else None,
                "zero": int(np.sum(markers == 0)),
            },
        },
    }
    if receiver is not None:
        report["per_beacon"] = per
    else:
        report["per_sensor"] = per
    return report
