"""The records of the synchronisation (a cover event, a video's clock map) and the small
interval helpers the video and RSSI detectors share."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class CoverEvent:
    """One covered interval on some clock, in seconds; an edge outside the recording is NaN."""

    cover: float
    release: float
    cover_sigma: float
    release_sigma: float
    source: str = ""  # "brightness", "markers" or "rssi": which signal found it

    @property
    def duration(self) -> float:
        return self.release - self.cover

    def edges(self) -> list[tuple[float, float]]:
        """(time, sigma) of the edges that were seen."""
        return [
            (t, s)
            for t, s in ((self.cover, self.cover_sigma), (self.release, self.release_sigma))
            if math.isfinite(t)
        ]


@dataclass(frozen=True, slots=True)
class ClockMap:
    """``t_rssi = video_start + pts * (1 + drift)`` with 1-sigma uncertainties (NaN if unknown)."""

    video_start: float
    drift: float = 0.0
    video_start_sigma: float = math.nan
    drift_sigma: float = math.nan
    method: str = "manual"  # "manual" or "auto"
    n_edges: int = 0
    residual_rms: float = math.nan  # of the fitted edges, seconds
    # How much later the RSSI saw the release (and earlier the cover) than the video, s: the two
    # signals fade differently while the hands close. Fitted when a cover/release pair exists.
    edge_bias: float = math.nan
    start_drift_cov: float = 0.0  # covariance of video_start and drift from the fit (s * 1)
    # How far the self-calibration moved video_start: this camera's clock against the others'
    # (``Refinement.clock_s``), already in video_start; 0 when not refined.
    refined_offset_s: float = 0.0

    def to_rssi(self, pts: np.ndarray | float) -> np.ndarray:
        return self.video_start + np.asarray(pts, dtype=float) * (1.0 + self.drift)

    def to_video(self, t_rssi: np.ndarray | float) -> np.ndarray:
        return (np.asarray(t_rssi, dtype=float) - self.video_start) / (1.0 + self.drift)

    def sigma_at(self, pts: np.ndarray | float) -> np.ndarray:
        """1-sigma uncertainty of the mapped time at ``pts`` (with the fit's start-drift covariance:
        both are fitted from the same edges, so the mapped time is best known between them)."""
        pts = np.asarray(pts, dtype=float)
        ds = self.drift_sigma if math.isfinite(self.drift_sigma) else 0.0
        cov = self.start_drift_cov if ds > 0 else 0.0
        var = self.video_start_sigma**2 + 2.0 * pts * cov + (pts * ds) ** 2
        return np.sqrt(np.maximum(var, 0.0))


def manual_clock_map(video_start: float) -> ClockMap:
    """The fallback: the user states the wall time of the first frame (``sync.video_start``)."""
    return ClockMap(video_start=float(video_start), method="manual")


# ---------------------------------------------------------------------------------------------
# Small array helpers


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist(), strict=True))


def merge_runs(runs: list[tuple[int, int]], t: np.ndarray, max_gap: float) -> list[tuple[int, int]]:
    """Join runs whose gap (time from the last True to the next True) is at most ``max_gap``."""
    out: list[tuple[int, int]] = []
    for a, b in runs:
        if out and t[a] - t[out[-1][1] - 1] <= max_gap:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


def noise_sigma(x: np.ndarray) -> float:
    """Frame-to-frame noise of a mostly flat series (robust: MAD of first differences)."""
    x = x[np.isfinite(x)]
    if x.size < 3:
        return 0.0
    d = np.diff(x)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))
