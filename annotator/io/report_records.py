"""The shape of report.json (`annotator run`) as a typed, versioned record; its
``refinement`` section (refinement.json) is ``annotator.core.refine.report.RefinementReport``.

The builders (``annotator.io.outputs.build_report``, ``annotator.core.refine.capture
.refinement_report``) return these types, so a key written under the wrong name or with the
wrong kind of value is a type error; readers of a file written earlier go through
:func:`read_report`, which checks the version and the sections they use and gives a one-line
error naming the file. Version 1 is the first with the ``version`` key; files from before it
read as version 1 (their shape is the same).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypedDict

from annotator.core.refine.report import RefinementReport
from annotator.errors import ConfigError

REPORT_VERSION = 1


class ReportError(ConfigError):
    """A report.json or refinement.json that is not one; one line naming the file."""


# --- report.json -------------------------------------------------------------------------------


class Stats(TypedDict):
    median: float | None
    p95: float | None
    max: float | None


class SyncEvent(TypedDict, total=False):
    """A cover event; a video's also says where it lands on the RSSI clock."""

    cover: float
    release: float
    cover_sigma: float
    release_sigma: float
    duration: float
    signal: str
    cover_rssi_clock: float
    release_rssi_clock: float


class SlateUse(TypedDict):
    filmings_pts_s: list[list[float]]
    frames_used: int
    frames_refused: int
    row_fraction: float


class CameraSync(TypedDict, total=False):
    """One video's clock against the collector's (``slate`` only when it filmed the slate)."""

    video_start: float
    video_start_sigma_s: float
    drift: float
    drift_sigma: float
    edges_used: int
    edge_residual_rms_s: float
    edge_bias_s: float
    method: str
    refined_offset_s: float
    events: list[SyncEvent]
    slate: SlateUse


class SyncReport(TypedDict):
    mode: str
    cameras: dict[str, CameraSync]
    rssi_events: list[SyncEvent]


class TrackedSpan(TypedDict):
    start: float | None
    stop: float | None
    poses: int
    frames: int


class Coverage(TypedDict):
    labelled_of_tracked_span: float
    labelled_of_all: float
    max_gap_s: float


class MarkersUsed(TypedDict):
    median: float | None
    zero: int


class Quality(TypedDict, total=False):
    pos_sigma_m: Stats  # the labelled readings'
    gap_to_pose_s: Stats
    markers_used: MarkersUsed
    trajectory_sigma_m: dict[str, Any]  # uncertainty.SigmaBudget.as_dict()


class ReadingCount(TypedDict):
    readings: int
    labelled: int


class Report(TypedDict, total=False):
    """report.json. ``per_sensor`` in beacon mode, ``per_beacon`` in receiver mode; ``plots``,
    ``antenna_trajectory`` and ``refinement`` as `annotator run` wrote them."""

    version: int
    experiment: str
    method: str
    mode: str  # "beacon" or "receiver"
    beacon: str | None
    receiver: str | None
    labelled_point_bundle_m: list[float]
    sync: SyncReport
    tracked_span: TrackedSpan
    counts: dict[str, int]
    coverage: Coverage
    quality: Quality
    per_sensor: dict[str, ReadingCount]
    per_beacon: dict[str, ReadingCount]
    plots: dict[str, str]
    antenna_trajectory: str
    refinement: RefinementReport


# The sections a report.json has whatever the capture, each a JSON object.
_REPORT_SECTIONS = ("sync", "tracked_span", "counts", "coverage", "quality")


def report_from_dict(d: object, where: str) -> Report:
    """A report.json document as its record; ReportError (one line naming ``where``) when it is
    not a mapping, has another version, or lacks a section or has one of the wrong kind."""
    if not isinstance(d, dict):
        raise ReportError(f"{where}: not a report.json (a JSON object)")
    version = d.get("version", REPORT_VERSION)
    if version != REPORT_VERSION:
        raise ReportError(
            f"{where}: report version {version!r}; this suite reads version {REPORT_VERSION}"
        )
    if not isinstance(d.get("experiment"), str):
        raise ReportError(f"{where}: experiment must be a string")
    for key in _REPORT_SECTIONS:
        if not isinstance(d.get(key), dict):
            raise ReportError(f"{where}: {key} is missing or not an object")
    if not isinstance(d["sync"].get("cameras"), dict):
        raise ReportError(f"{where}: sync.cameras is missing or not an object")
    refinement = d.get("refinement")
    if refinement is not None and not isinstance(refinement, dict):
        raise ReportError(f"{where}: refinement must be an object")
    out: Report = {**d, "version": REPORT_VERSION}
    return out


def read_report(path: str | Path) -> Report:
    """A report.json from disk (see report_from_dict); ReportError for an unreadable file."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ReportError(f"{path}: cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ReportError(f"{path}: not JSON: {e}") from None
    return report_from_dict(doc, str(path))
