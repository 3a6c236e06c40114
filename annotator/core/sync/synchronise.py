"""All cameras of an experiment: detect each video's events, fit its clock map against the
RSSI events (or take the stated starts: manual sync), and the intervals never labelled."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.core.sync.clock_fit import fit_clock_map
from annotator.core.sync.records import ClockMap, CoverEvent, manual_clock_map
from annotator.core.sync.video_events import detect_video_events
from annotator.errors import NoDataError

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# (d) all cameras of an experiment


@dataclass(frozen=True, eq=False)
class VideoSeries:
    """Per-frame signals of one video for event detection (PTS seconds from its first frame)."""

    pts: np.ndarray
    brightness: np.ndarray
    marker_count: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class SyncResult:
    clocks: dict[str, ClockMap]
    video_events: dict[str, list[CoverEvent]]  # per camera, PTS seconds
    rssi_events: list[CoverEvent]  # RSSI clock (Unix seconds)
    mode: str
    # slate mode: the cameras synchronised by the clock slate (annotator.core.sync.slate.SlateFit)
    slates: dict[str, Any] = field(default_factory=dict)


def synchronise(
    series: dict[str, VideoSeries],
    rssi_events: list[CoverEvent],
    *,
    approx_start: dict[str, float] | None = None,
    max_start_error: float = 60.0,
    min_duration: float = 0.3,
    max_duration: float = 10.0,
) -> SyncResult:
    """Clock map of every video onto the RSSI clock (``sync.mode: auto``).

    ``rssi_events`` come from :func:`detect_rssi_events` (run it first: it is cheap and fails
    early). ``approx_start`` (e.g. a rough ``video_start``) restricts each video's start to within
    ``max_start_error`` seconds of it. The cameras are synchronised independently: each may start
    recording at its own time.
    """
    clocks: dict[str, ClockMap] = {}
    video_events: dict[str, list[CoverEvent]] = {}
    for name, s in series.items():
        evs = detect_video_events(
            s.pts,
            s.brightness,
            s.marker_count,
            name=name,
            min_duration=min_duration,
            max_duration=max_duration,
        )
        video_events[name] = evs
        prior = None if approx_start is None else approx_start.get(name)
        clocks[name] = fit_clock_map(
            evs,
            rssi_events,
            name=name,
            approx_start=prior,
            max_start_error=max_start_error if prior is not None else math.inf,
        )
    # A camera that saw an event only in part (it started or stopped while covered) can do better
    # through a camera that saw it whole: both watch the same hands, so their edges agree without
    # the brightness-vs-RSSI bias that only a cover/release pair cancels.
    complete = [
        n
        for n, evs in video_events.items()
        if any(math.isfinite(e.cover) and math.isfinite(e.release) for e in evs)
    ]
    for name, evs in video_events.items():
        if name in complete:
            continue
        for ref in complete:
            cm = clocks[ref]
            mapped = [
                CoverEvent(
                    float(cm.to_rssi(e.cover)),
                    float(cm.to_rssi(e.release)),
                    math.hypot(e.cover_sigma, cm.video_start_sigma),
                    math.hypot(e.release_sigma, cm.video_start_sigma),
                    f"video {ref}",
                )
                for e in video_events[ref]
            ]
            try:
                via = fit_clock_map(
                    evs, mapped, name=name, lone_edge_sigma=0.0, method=f"auto via {ref}"
                )
            except NoDataError:
                continue
            if via.video_start_sigma < clocks[name].video_start_sigma:
                log.info(
                    "%s: synchronised through %s (%.1f ms instead of %.1f ms)",
                    name,
                    ref,
                    1e3 * via.video_start_sigma,
                    1e3 * clocks[name].video_start_sigma,
                )
                clocks[name] = via
    return SyncResult(clocks, video_events, list(rssi_events), "auto")


def cover_intervals(events: list[CoverEvent], margin: float = 0.1) -> list[tuple[float, float]]:
    """The events as (start, stop) intervals widened by ``margin`` (and 3 sigma) on each side; an
    edge outside the recording becomes -inf / +inf."""
    out = []
    for e in events:
        a = e.cover - max(margin, 3 * e.cover_sigma) if math.isfinite(e.cover) else -math.inf
        b = e.release + max(margin, 3 * e.release_sigma) if math.isfinite(e.release) else math.inf
        out.append((a, b))
    return out


def manual_sync(video_start: dict[str, float]) -> SyncResult:
    """``sync.mode: manual``: the user-given start of every video, no drift, unknown uncertainty."""
    return SyncResult({k: manual_clock_map(v) for k, v in video_start.items()}, {}, [], "manual")
