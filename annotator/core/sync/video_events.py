"""Cover events in a video: the frames go dark and the markers vanish while hands cover the
lens; each edge placed from the brightness and marker-count series (PTS seconds)."""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy.ndimage import median_filter

from annotator.core.sync.records import CoverEvent, merge_runs, noise_sigma, true_runs
from annotator.errors import NoDataError

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# (a) video


def _frame_durations(pts: np.ndarray) -> np.ndarray:
    """Time each frame stands for: half the gap to each neighbour (robust to a dropped frame)."""
    if pts.size == 1:
        return np.ones(1)
    d = np.diff(pts)
    left = np.concatenate([[d[0]], d])
    right = np.concatenate([d, [d[-1]]])
    return 0.5 * (left + right)


def _brightness_edge(
    pts: np.ndarray,
    b: np.ndarray,
    dur: np.ndarray,
    i: int,
    level_before: float,
    level_after: float,
    noise: float,
    max_span: float,
) -> tuple[float, float]:
    """Sub-frame time of one brightness edge near index ``i`` (the first frame of the new state).

    Each frame integrates light over its own interval, so the fraction of that interval spent in
    the old state is (b - new) / (old - new). Summing those fractions over the transition frames
    gives the time spent in the old state after the transition window opened: the edge. The same
    sum gives the midpoint of a gradual cover, and it averages the pixel noise.
    """
    span = level_before - level_after
    frac_old = np.clip((b - level_after) / span, 0.0, 1.0)  # 1 = old state, 0 = new state
    tau = 0.15
    n = pts.size
    # Widen the window to frames clearly in the old state (left) and the new state (right).
    a = i - 1
    while a > 0 and frac_old[a] < 1.0 - tau and pts[i] - pts[a] < max_span:
        a -= 1
    c = i
    while c < n - 1 and frac_old[c] > tau and pts[c] - pts[i] < max_span:
        c += 1
    a = max(a, 0)
    window = slice(a, c + 1)
    t_open = pts[a] - 0.5 * dur[a]
    t_edge = t_open + float(np.sum(frac_old[window] * dur[window]))
    n_mixed = int(np.sum((frac_old[window] > tau) & (frac_old[window] < 1.0 - tau)))
    sig_noise = (noise / abs(span)) * float(np.sqrt(np.sum(dur[window] ** 2)))
    frame = float(np.median(dur[window]))
    # A transition with no intermediate frame only tells us which frame gap it fell in.
    sig_model = frame / math.sqrt(12.0) if n_mixed == 0 else frame / 6.0
    return float(t_edge), math.hypot(sig_noise, sig_model)


def detect_video_events(
    pts: np.ndarray,
    brightness: np.ndarray,
    marker_count: np.ndarray | None = None,
    *,
    name: str = "video",
    min_duration: float = 0.3,
    max_duration: float = 10.0,
    min_contrast: float = 0.3,
) -> list[CoverEvent]:
    """Covered intervals of one video, in its own PTS seconds, from per-frame series.

    ``brightness`` is the mean grey level of each frame; ``marker_count`` (optional) the number of
    map markers detected. A covered interval is a dark run lasting ``min_duration`` to
    ``max_duration`` seconds in which (if counts are given) no marker is seen. If the brightness
    never drops enough (``min_contrast`` of its typical level) the marker count alone is used,
    with frame-level timing. Raises NoDataError naming ``name`` when nothing is found.
    """
    pts = np.asarray(pts, dtype=float)
    b = np.asarray(brightness, dtype=float)
    if pts.shape != b.shape or pts.ndim != 1:
        raise ValueError("pts and brightness must be 1-D arrays of the same length")
    mc = None if marker_count is None else np.asarray(marker_count, dtype=float)
    if mc is not None and mc.shape != pts.shape:
        raise ValueError("marker_count must have the same length as pts")
    if pts.size < 5:
        raise NoDataError(f"{name}: only {pts.size} frames; too few to find the cover event")

    ok = np.isfinite(b) & np.isfinite(pts)
    pts, b = pts[ok], b[ok]
    mc = None if mc is None else mc[ok]
    dur = _frame_durations(pts)
    bright = float(np.median(b))
    # The darkest few consecutive frames: a cover may be a tiny share of a long video (so no
    # percentile will do), and a single glitched black frame must not count.
    dark = float(np.min(median_filter(b, size=5, mode="nearest")))
    contrast = (bright - dark) / bright if bright > 0 else 0.0

    events: list[CoverEvent] = []
    if contrast >= min_contrast:
        threshold = dark + 0.5 * (bright - dark)
        runs = merge_runs(true_runs(b < threshold), pts, max_gap=0.15)
        noise = noise_sigma(b)
        for a, z in runs:
            seen = pts[z - 1] - pts[a] + dur[a]
            if not (min_duration <= seen <= max_duration):
                continue
            if mc is not None and np.median(mc[a:z]) > 0:
                log.debug("%s: dark run at %.2f s still shows markers; not a cover", name, pts[a])
                continue
            level_dark = float(np.median(b[a:z]))
            pre = (pts >= pts[a] - 0.6) & (pts < pts[a] - 0.1)
            post = (pts > pts[z - 1] + 0.1) & (pts <= pts[z - 1] + 0.6)
            lb = float(np.median(b[pre])) if pre.any() else bright
            la = float(np.median(b[post])) if post.any() else bright
            cover = release = math.nan
            cs = rs = math.nan
            if a > 0:
                cover, cs = _brightness_edge(pts, b, dur, a, lb, level_dark, noise, 0.5)
            if z < pts.size:
                release, rs = _brightness_edge(pts, b, dur, z, level_dark, la, noise, 0.5)
            events.append(CoverEvent(cover, release, cs, rs, "brightness"))
    if not events and mc is not None:
        # Too little light change (e.g. a dark room): frames with no marker mark the cover.
        seen_any = mc > 0
        if seen_any.any():
            runs = merge_runs(true_runs(~seen_any), pts, max_gap=0.15)
            for a, z in runs:
                seen = pts[z - 1] - pts[a] + dur[a]
                if a == 0 or z == pts.size or not (min_duration <= seen <= max_duration):
                    continue
                frame = float(np.median(dur[max(a - 1, 0) : z + 1]))
                cover = float(0.5 * (pts[a - 1] + pts[a]))
                release = float(0.5 * (pts[z - 1] + pts[z]))
                events.append(CoverEvent(cover, release, frame, frame, "markers"))
    if not events:
        why = (
            f"brightness drops only {contrast:.0%} below its median"
            if contrast < min_contrast
            else f"no dark run of {min_duration}-{max_duration} s without markers"
        )
        raise NoDataError(
            f"{name}: no cover event found ({why}); cover the bundle with both hands for "
            "1-2 s at the start, or use sync.mode: manual with sync.video_start"
        )
    log.info(
        "%s: %d cover event(s): %s",
        name,
        len(events),
        ", ".join(f"{e.cover:.3f}-{e.release:.3f} s" for e in events),
    )
    return events
