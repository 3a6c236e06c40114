"""The clock slate: a screen that shows the collector's clock as a time code, filmed by each
camera for a second at the start and the end of a capture (``sync.mode: slate``).

A code is four ArUco markers of :data:`SLATE_DICTIONARY` in a row, read along the markers' own
x axis: the clock in milliseconds modulo 10^9 (11.6 days) as three base-1000 digits, then a check
digit, so a code caught across two refreshes (a tear, the rolling shutter passing a refresh, an
exposure spanning one) is refused instead of read wrong. The page (`collector slate`) shows two
such codes one above the other, updated on alternate refreshes (:func:`slate_value_shown`), each
showing the time at the middle of the two refreshes it stays on screen: whatever the camera's
exposure and phase, one of them reads cleanly, unbiased to within a refresh.

Pure functions here; reading a video's frames is ``annotator.io.sync.slate_readings``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.core.sync.clock_fit import DRIFT_PRIOR, drift_mixture_posterior
from annotator.core.sync.records import ClockMap
from annotator.errors import NoDataError

log = logging.getLogger(__name__)

SLATE_DICTIONARY = "DICT_5X5_1000"
DIGIT_BASE = 1000
PERIOD_MS = DIGIT_BASE**3  # the code repeats after 10^9 ms
SEGMENT_GAP_S = 2.0  # slate frames further apart than this belong to different filmings


def check_digit(a: int, b: int, c: int) -> int:
    """Weights prime to 1000: any change of one digit changes the check digit."""
    return (7 * a + 3 * b + c + 1) % DIGIT_BASE


def encode_slate(t_ms: int) -> tuple[int, int, int, int]:
    """Marker ids, left to right, that show ``t_ms`` (Unix milliseconds)."""
    v = int(t_ms) % PERIOD_MS
    a, b, c = v // DIGIT_BASE**2, (v // DIGIT_BASE) % DIGIT_BASE, v % DIGIT_BASE
    return a, b, c, check_digit(a, b, c)


def decode_slate(ids: Sequence[int]) -> int | None:
    """Milliseconds modulo :data:`PERIOD_MS` from four ids in reading order; None if the check
    digit disagrees."""
    if len(ids) != 4 or not all(0 <= int(i) < DIGIT_BASE for i in ids):
        return None
    a, b, c, k = (int(i) for i in ids)
    if check_digit(a, b, c) != k:
        return None
    return (a * DIGIT_BASE + b) * DIGIT_BASE + c


def read_slate_markers(corners: np.ndarray, ids: np.ndarray) -> list[tuple[int, float]]:
    """(milliseconds mod period, image row of the code) of each code that passes its check in
    one frame's detected slate markers (``corners`` (N, 4, 2) as ArUco gives them, ``ids``
    (N,)). Markers are grouped into codes along the markers' own y axis and read along their x
    axis, so a camera held sideways or upside down still reads the digits in order."""
    c = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
    ids = np.asarray(ids).reshape(-1)
    if len(ids) < 4:
        return []
    x_axis = (c[:, 1] - c[:, 0]).mean(axis=0)
    y_axis = (c[:, 3] - c[:, 0]).mean(axis=0)
    side = float(np.hypot(*y_axis))
    if side == 0 or float(np.hypot(*x_axis)) == 0:
        return []
    centres = c.mean(axis=1)
    across = centres @ (y_axis / side)
    along = centres @ (x_axis / float(np.hypot(*x_axis)))
    found = []
    rows = np.argsort(across)
    # a new code row starts where the markers' centres step by more than half a marker side
    cuts = np.flatnonzero(np.diff(across[rows]) > side / 2) + 1
    for group in np.split(rows, cuts):
        order = group[np.argsort(along[group])]
        for k in range(len(order) - 3):
            pick = order[k : k + 4]
            value = decode_slate([int(i) for i in ids[pick]])
            if value is not None:
                found.append((value, float(centres[pick, 1].mean())))
                break
    return found


@dataclass(frozen=True, slots=True)
class SlateReading:
    """One frame that showed a readable slate."""

    pts: float  # the frame's stamp, s from the video's first frame
    row: float  # image row of the code's centre, px
    value_ms: int  # the time shown, ms modulo PERIOD_MS


@dataclass(frozen=True, eq=False)
class SlateFit:
    """A video's clock map from its slate frames, and what it was fitted from."""

    clock: ClockMap
    segments: list[tuple[float, float]]  # (first, last) pts of each filming of the slate
    frames_used: int
    frames_refused: int  # readings far off the fit (a misread that passed the check)
    row_fraction: float  # mean row of the code / image height (for a later readout change)


def unwrap_ms(value_ms: np.ndarray, near: float) -> np.ndarray:
    """Seconds on the full clock: the value modulo 10^9 ms nearest to ``near`` (Unix s)."""
    period = PERIOD_MS / 1000.0
    v = np.asarray(value_ms, dtype=float) / 1000.0
    return v + period * np.round((near - v) / period)


def _segments(pts: np.ndarray) -> list[np.ndarray]:
    order = np.argsort(pts)
    cuts = np.flatnonzero(np.diff(pts[order]) > SEGMENT_GAP_S) + 1
    return [order[a:b] for a, b in zip([0, *cuts], [*cuts, len(order)], strict=True)]


def fit_slate_clock(
    readings: Sequence[SlateReading],
    *,
    height: int,
    readout: float,
    near: float,
    refresh_hz: float = 60.0,
    latency: float = 0.0,
    latency_sigma: float = 0.005,
    name: str = "video",
    drift_prior: tuple[tuple[float, float], ...] = DRIFT_PRIOR,
) -> SlateFit:
    """Fit ``t_clock = video_start + pts * (1 + drift)`` from a video's slate frames.

    A frame stamped ``pts`` saw the code at ``pts + readout * row / height`` (its rolling shutter)
    and shows the clock at that moment minus ``latency`` (the screen's own delay), give or take
    a refresh (half a refresh for the mean of both codes). Consecutive frames of one filming
    share that refresh phase (a camera and a screen run at nearly fixed rates), so each filming
    counts as one measurement with that quantisation as its floor, however many frames it holds. Two
    filmings (start and end) fit the drift under ``drift_prior``; one keeps it at zero, as the
    hands-cover sync does with one event. ``near`` (any Unix time within days of the capture,
    e.g. the first RSSI reading) resolves the code's 11.6-day period. The stated sigma adds
    ``latency_sigma`` for the screen's delay, which the video cannot show.
    """
    if not readings:
        raise NoDataError(f"{name}: no readable clock slate in the video")
    if not (refresh_hz > 0 and height > 0 and readout >= 0):
        raise ValueError("refresh_hz and height must be positive, readout not negative")
    pts = np.array([r.pts for r in readings], dtype=float)
    rows = np.array([r.row for r in readings], dtype=float)
    tau = pts + readout * rows / height
    shown = unwrap_ms(np.array([r.value_ms for r in readings]), near) + latency
    y = shown - tau  # video_start + drift * tau; drift * tau is small within a filming
    period = 1.0 / refresh_hz
    keep = np.ones(len(y), dtype=bool)
    means, mean_tau, sigmas = [], [], []
    segments = []
    for idx in _segments(pts):
        seg = y[idx]
        med = float(np.median(seg))
        mad = 1.4826 * float(np.median(np.abs(seg - med)))
        ok = np.abs(seg - med) <= max(3.0 * mad, 2 * period + 1e-3)  # codes a refresh apart
        keep[idx[~ok]] = False
        good = idx[ok]
        n = int(good.size)
        # Both codes read in most frames: their errors (uniform over one refresh each, a refresh
        # apart) average to a uniform error over half a refresh; one code alone: over a refresh.
        both = n >= 1.5 * np.unique(pts[good]).size
        quant = period / math.sqrt(12.0 if both else 3.0)
        spread = float(np.std(y[good], ddof=1)) if n > 1 else 1.0 / refresh_hz
        means.append(float(np.mean(y[good])))
        mean_tau.append(float(np.mean(tau[good])))
        sigmas.append(math.sqrt(quant**2 + spread**2 / n))
        segments.append((float(pts[good].min()), float(pts[good].max())))
    m, tm, s = np.array(means), np.array(mean_tau), np.array(sigmas)
    span = float(tm.max() - tm.min())
    drift = len(m) >= 2 and span >= 10.0
    if drift:
        a = np.column_stack([np.ones_like(tm), tm]) / s[:, None]
        coef, cov = drift_mixture_posterior(a, m / s, 1, drift_prior)
        start, d = float(coef[0]), float(coef[1])
        start_var, d_sigma, cross = float(cov[0, 0]), float(math.sqrt(cov[1, 1])), float(cov[0, 1])
    else:
        w = 1.0 / s**2
        start, d = float(np.sum(w * m) / np.sum(w)), 0.0
        start_var, d_sigma, cross = float(1.0 / np.sum(w)), math.nan, 0.0
    resid = y[keep] - (start + d * tau[keep])
    clock = ClockMap(
        video_start=start,
        drift=d,
        video_start_sigma=math.sqrt(start_var + latency_sigma**2),
        drift_sigma=d_sigma,
        method="slate",
        n_edges=len(m),
        residual_rms=float(np.sqrt(np.mean(resid**2))),
        start_drift_cov=cross,
    )
    refused = int((~keep).sum())
    log.info(
        "%s: slate sync video_start %.4f +- %.4f s, drift %.2e, %d frames in %d filming(s), "
        "%d refused",
        name,
        clock.video_start,
        clock.video_start_sigma,
        clock.drift,
        int(keep.sum()),
        len(m),
        refused,
    )
    return SlateFit(clock, segments, int(keep.sum()), refused, float(np.mean(rows[keep]) / height))


def slate_value_shown(
    t: np.ndarray | float, refresh_hz: float = 60.0, phase: float = 0.0, code_row: int = 0
) -> np.ndarray:
    """What code row ``code_row`` (0 or 1) of the slate page shows at wall time(s) ``t``, in ms.

    The screen refreshes at ``phase + k / refresh_hz``; row 0 takes a new value on even
    refreshes and row 1 on odd ones, and each shows the middle of the two refreshes it stays on
    screen. A frame whose exposure (or rolling shutter) spans a refresh blurs or tears at most
    one of the two rows, so the other reads cleanly. The simulator draws this; the page does the
    same with its measured refresh interval."""
    period = 1.0 / refresh_hz
    start = phase + code_row * period
    k = np.floor((np.asarray(t, dtype=float) - start) / (2 * period))
    return np.round((start + (2 * k + 1) * period) * 1000.0).astype(np.int64)
