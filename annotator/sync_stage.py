"""The sync step of `annotator run` for the automatic modes: videos decoded on their own PTS clock
are mapped onto the RSSI clock, by the clock slate (``sync.mode: slate``) where a video filmed
one, else by the hands-cover events (``sync.mode: auto``, and the slate's fallback).

It sits between the pipeline (which decodes and tracks) and the pure sync functions
(``annotator.core.sync``); it reads the videos once more for what the sync looks at.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from annotator.core.sync import (
    CoverEvent,
    SyncResult,
    VideoSeries,
    detect_rssi_events,
    synchronise,
)
from annotator.core.sync.slate import SlateFit, fit_slate_clock
from annotator.errors import NoDataError

if TYPE_CHECKING:
    from collections.abc import Callable

    from annotator.core.experiment import Experiment
    from annotator.core.tracking import CameraFrames
    from annotator.core.trajectory import Trajectory
    from annotator.io.rssi import RssiTable

    Progress = Callable[[str, int, int], None]

log = logging.getLogger(__name__)

# Frames this close (s) to a filming of the slate are left out of tracking: the camera faces the
# screen, not the room.
SLATE_MARGIN_S = 0.1


def sync_frames(
    exp: Experiment,
    frames: list[CameraFrames],
    table: RssiTable,
    pooled_by: np.ndarray,
    subject: str,
    progress: Progress | None = None,
) -> tuple[list[CameraFrames], SyncResult]:
    """Frames decoded with ``video_start`` 0 (times are PTS) -> the same frames on the RSSI clock,
    and how each camera was synchronised. In slate mode a camera without a readable slate falls
    back to the hands cover; the RSSI cover events are found in either mode when present (their
    readings are never labelled)."""
    sc = exp.sync
    cover_s = (sc.min_cover_s, sc.max_cover_s)
    slate_mode = exp.sync_mode == "slate"
    rssi_events: list[CoverEvent] = []
    try:
        rssi_events = detect_rssi_events(
            table.t_seconds(),
            table.rssi,
            pooled_by,
            name=f"RSSI of {subject}",
            min_duration=cover_s[0],
            max_duration=cover_s[1],
        )
    except NoDataError:
        if not slate_mode:  # auto mode has nothing else to go by: say so before the long pass
            raise
    slates: dict[str, SlateFit] = {}
    if slate_mode:
        slates = _slate_fits(exp, frames, table, progress)
    by_cover = [cf for cf in frames if cf.camera not in slates]
    clocks = {name: fit.clock for name, fit in slates.items()}
    video_events: dict[str, list[CoverEvent]] = {}
    if by_cover:
        if not rssi_events:
            names = ", ".join(cf.camera for cf in by_cover)
            raise NoDataError(
                f"{names}: no readable clock slate, and no hands-cover event in the RSSI of "
                f"{subject} to fall back on"
            )
        cover = synchronise(
            _cover_series(exp, by_cover, progress),
            rssi_events,
            approx_start=exp.video_start,
            max_start_error=sc.max_start_error,
            min_duration=cover_s[0],
            max_duration=cover_s[1],
        )
        clocks.update(cover.clocks)
        video_events = cover.video_events
    mapped = []
    for cf in frames:
        fit = slates.get(cf.camera)
        if fit is not None:
            cf = trim_frames(cf, fit.segments)
        mapped.append(replace(cf, t=clocks[cf.camera].to_rssi(cf.t)))
    mode = "slate" if slate_mode else "auto"
    return mapped, SyncResult(clocks, video_events, rssi_events, mode, slates)


def _slate_fits(
    exp: Experiment, frames: list[CameraFrames], table: RssiTable, progress: Progress | None
) -> dict[str, SlateFit]:
    from annotator.io.sync import slate_readings

    sc = exp.sync
    near = float(np.median(table.t_seconds())) if len(table) else 0.0
    out = {}
    for cf in frames:
        n = len(cf.t)
        if not n:
            continue
        end = float(cf.t[-1])
        windows = [(-math.inf, sc.slate_window), (end - sc.slate_window, math.inf)]
        cb = _pass_progress(progress, f"{cf.camera} slate", n)
        readings = slate_readings(exp.videos[cf.camera], windows, cb)
        if cb is not None:
            cb(n)
        if not readings:
            log.warning("%s: no clock slate found; falling back to the hands cover", cf.camera)
            continue
        cal = exp.rig.cameras[cf.camera].calibration
        out[cf.camera] = fit_slate_clock(
            readings,
            height=int(cal.height),
            readout=float(cal.readout_s),
            near=near,
            refresh_hz=sc.slate_hz,
            latency=sc.slate_latency,
            latency_sigma=sc.slate_latency_sigma,
            name=cf.camera,
        )
    return out


def _cover_series(
    exp: Experiment, frames: list[CameraFrames], progress: Progress | None
) -> dict[str, VideoSeries]:
    from annotator.io.sync import brightness_series

    series = {}
    for cf in frames:
        n = len(cf.t)
        cb = _pass_progress(progress, f"{cf.camera} sync", n)
        pts, level = brightness_series(exp.videos[cf.camera], cb)
        if len(pts) < n:
            raise NoDataError(f"{exp.videos[cf.camera]}: decoded {len(pts)} frames, expected {n}")
        if cb is not None:
            cb(n)
        counts = np.array([len(d.ids) for d in cf.detections], dtype=float)
        series[cf.camera] = VideoSeries(cf.t, level[:n], counts)
    return series


def _pass_progress(progress: Progress | None, stage: str, n: int) -> Callable[[int], None] | None:
    """A pass over one video's ``n`` frames as ``stage`` of ``progress`` (frames decoded -> bar)."""
    if progress is None:
        return None
    return lambda k: progress(stage, min(k, n), n)


def trim_frames(cf: CameraFrames, segments: list[tuple[float, float]]) -> CameraFrames:
    """The frames of ``cf`` outside the slate's filmings (PTS ``segments``, widened by
    :data:`SLATE_MARGIN_S`)."""
    keep = np.ones(len(cf.t), dtype=bool)
    for a, b in segments:
        keep &= ~((cf.t >= a - SLATE_MARGIN_S) & (cf.t <= b + SLATE_MARGIN_S))
    idx = np.flatnonzero(keep)

    def pick(items: list[Any]) -> list[Any]:
        return [items[i] for i in idx] if len(items) == len(cf.t) else items

    return replace(
        cf,
        t=cf.t[idx],
        detections=pick(cf.detections),
        poses=pick(cf.poses),
        marker_poses=pick(cf.marker_poses),
    )


def clock_shift(sync: SyncResult, offsets: dict[str, float]) -> SyncResult:
    """The clock maps with each camera's start moved by the offset the self-calibration found
    (its frames were seen that much later than the sync put them; the cameras' mean is 0)."""
    clocks = {
        n: replace(
            c, video_start=c.video_start + offsets.get(n, 0.0), refined_offset_s=offsets.get(n, 0.0)
        )
        for n, c in sync.clocks.items()
    }
    return replace(sync, clocks=clocks)


def readout_shift(
    sync: SyncResult, used: dict[str, float], found: dict[str, float], trajectory: Trajectory
) -> tuple[SyncResult, Trajectory]:
    """The slate's clock maps with the readout the self-calibration found instead of the one the
    calibration files gave (``used``): a slate read at row fraction f was seen ``readout * f``
    after its frame's stamp, so each video starts ``(found - used) * f`` earlier than fitted.
    The trajectory's times move by the mean of that over the cameras (frames of both cameras
    were paired by the earlier times; a shift of a few ms changes no pairing)."""
    shifts = {
        name: (found[name] - used[name]) * fit.row_fraction
        for name, fit in sync.slates.items()
        if name in found and name in used
    }
    if set(sync.slates) != set(sync.clocks):
        return sync, trajectory  # a camera synchronised by the cover: its frames keep their times
    shifts = {k: v for k, v in shifts.items() if abs(v) > 1e-6}
    if not shifts:
        return sync, trajectory
    clocks = dict(sync.clocks)
    for name, dt in shifts.items():
        clocks[name] = replace(clocks[name], video_start=clocks[name].video_start - dt)
        log.info("%s: slate sync moved by %.1f ms for the readout found", name, -1e3 * dt)
    mean = float(np.mean(list(shifts.values())))
    return replace(sync, clocks=clocks), replace(trajectory, t=trajectory.t - mean)
