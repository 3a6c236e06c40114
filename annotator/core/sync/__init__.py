"""Clock synchronisation between videos and the RSSI log, from a "hands cover the bundle" event.

Pure functions on arrays: detect the covered interval(s) in each video (brightness, marker count;
``video_events``) and in the pooled RSSI readings (reading rate, level; ``rssi_events``), then fit
``t_rssi = video_start + pts * (1 + drift)`` per video (``clock_fit``); ``synchronise`` does it
for every camera of an experiment, ``manual_sync`` takes the stated starts instead.
"""

from annotator.core.sync.clock_fit import DRIFT_PRIOR, fit_clock_map
from annotator.core.sync.records import ClockMap, CoverEvent, manual_clock_map
from annotator.core.sync.rssi_events import detect_rssi_events
from annotator.core.sync.synchronise import (
    SyncResult,
    VideoSeries,
    cover_intervals,
    manual_sync,
    synchronise,
)
from annotator.core.sync.video_events import detect_video_events

__all__ = [
    "DRIFT_PRIOR",
    "ClockMap",
    "CoverEvent",
    "SyncResult",
    "VideoSeries",
    "cover_intervals",
    "detect_rssi_events",
    "detect_video_events",
    "fit_clock_map",
    "manual_clock_map",
    "manual_sync",
    "synchronise",
]
