"""Clock synchronisation between videos and the RSSI log, from a "hands cover the bundle" event.

Pure functions on arrays: detect the covered interval(s) in each video (brightness, marker count)
and in the pooled RSSI of all sensors (reading rate, level), then fit ``t_rssi = video_start +
pts * (1 + drift)`` per video. ``manual_clock_map`` is the fallback when the YAML gives the start.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter

from annotator.errors import NoDataError

log = logging.getLogger(__name__)


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


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist(), strict=True))


def _merge_runs(
    runs: list[tuple[int, int]], t: np.ndarray, max_gap: float
) -> list[tuple[int, int]]:
    """Join runs whose gap (time from the last True to the next True) is at most ``max_gap``."""
    out: list[tuple[int, int]] = []
    for a, b in runs:
        if out and t[a] - t[out[-1][1] - 1] <= max_gap:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


def _noise_sigma(x: np.ndarray) -> float:
    """Frame-to-frame noise of a mostly flat series (robust: MAD of first differences)."""
    x = x[np.isfinite(x)]
    if x.size < 3:
        return 0.0
    d = np.diff(x)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


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
        runs = _merge_runs(_runs(b < threshold), pts, max_gap=0.15)
        noise = _noise_sigma(b)
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
            runs = _merge_runs(_runs(~seen_any), pts, max_gap=0.15)
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


# ---------------------------------------------------------------------------------------------
# (b) pooled RSSI


def _normalised_levels(rssi: np.ndarray, sensor_codes: np.ndarray, use: np.ndarray) -> np.ndarray:
    """RSSI minus its sensor's median over the ``use`` readings (each sensor sits at its own range)."""
    z = np.full(rssi.shape, np.nan)
    for s in np.unique(sensor_codes):
        mine = sensor_codes == s
        ref = rssi[mine & use]
        if ref.size == 0:
            ref = rssi[mine]
        z[mine] = rssi[mine] - np.median(ref)
    return z


def _changepoint(
    t: np.ndarray,
    z: np.ndarray,
    lo: float,
    hi: float,
    grid: np.ndarray,
    into_covered: bool,
    same_advert_s: float = 0.0,
) -> tuple[float, float, float]:
    """Posterior mean, sigma and log-likelihood ratio of one change point on ``grid``.

    Model on [lo, hi): a Poisson stream of readings whose rate and mean (normalised) level change
    once. Profile log-likelihood of the split time, flat prior. Readings closer than
    ``same_advert_s`` are one advertisement (heard by several sensors): one event, their mean level. Taking the posterior mean (not the
    maximum) matters when readings vanish entirely: the last reading then comes on average one
    inter-reading gap before the true edge.
    """
    k0 = np.searchsorted(t, lo)
    k1 = np.searchsorted(t, hi)
    tt, zz = t[k0:k1], z[k0:k1]
    if same_advert_s > 0 and tt.size > 1:
        # One advertisement heard by several sensors is one event of the beacon's stream, not
        # several: counted per sensor, the rate model would claim a precision it does not have.
        new = np.concatenate([[True], np.diff(tt) > same_advert_s])
        g = np.cumsum(new) - 1
        cnt = np.bincount(g).astype(float)
        tt, zz = np.bincount(g, tt) / cnt, np.bincount(g, zz) / cnt
    n = tt.size
    k = np.searchsorted(tt, grid)  # adverts before each candidate split
    c1 = np.concatenate([[0.0], np.cumsum(zz)])
    c2 = np.concatenate([[0.0], np.cumsum(zz * zz)])
    n1, n2 = k.astype(float), (n - k).astype(float)
    t1, t2 = grid - lo, hi - grid

    def xlogy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(x > 0, x * np.log(np.where(y > 0, y, 1.0)), 0.0)

    ll_rate = xlogy(n1, n1 / t1) + xlogy(n2, n2 / t2) - n
    s1, s2 = c1[k], c1[n] - c1[k]
    q = c2[n]
    with np.errstate(divide="ignore", invalid="ignore"):
        rss = q - np.where(n1 > 0, s1 * s1 / n1, 0.0) - np.where(n2 > 0, s2 * s2 / n2, 0.0)
    var_floor = 1.0  # dB^2: RSSI is integer, a zero residual is quantisation, not certainty
    ll_level = -0.5 * n * np.log(np.maximum(rss / max(n, 1), var_floor))
    # The covered side must be quieter or weaker, else this is not a cover edge.
    m1 = np.where(n1 > 0, s1 / np.maximum(n1, 1), 0.0)
    m2 = np.where(n2 > 0, s2 / np.maximum(n2, 1), 0.0)
    r1, r2 = n1 / np.maximum(t1, 1e-9), n2 / np.maximum(t2, 1e-9)
    quieter = (r2 < r1) | (m2 < m1) if into_covered else (r1 < r2) | (m1 < m2)
    ll = np.where(quieter, ll_rate + ll_level, -np.inf)
    ll_null = (
        xlogy(np.array(float(n)), np.array(n / (hi - lo)))
        - n
        - 0.5 * n * np.log(max((q - c1[n] ** 2 / max(n, 1)) / max(n, 1), var_floor))
    )
    best = float(np.max(ll))
    if not math.isfinite(best):
        return math.nan, math.nan, 0.0
    w = np.exp(ll - best)
    w /= w.sum()
    mean = float(np.sum(w * grid))
    sd = float(np.sqrt(np.sum(w * (grid - mean) ** 2)))
    step = float(grid[1] - grid[0]) if grid.size > 1 else 0.0
    return mean, math.hypot(sd, step / math.sqrt(12.0)), best - float(ll_null)


def _coarse_dips(
    t: np.ndarray,
    rssi: np.ndarray,
    codes: np.ndarray,
    *,
    name: str,
    bin_s: float,
    window_s: float,
    rate_drop: float,
    level_drop_db: float,
) -> tuple[np.ndarray, list[tuple[int, int]], float]:
    """Candidate covers: bin edges, runs of bins where the pooled rate or level dips, base rate.

    The rate and the mean normalised level are taken in a sliding ``window_s`` window over
    ``bin_s`` bins; nearby runs are merged.
    """
    t0, t1 = float(t[0]), float(t[-1])
    nb = max(int(math.ceil((t1 - t0) / bin_s)), 1)
    edges = t0 + bin_s * np.arange(nb + 1)
    idx = np.clip(((t - t0) / bin_s).astype(int), 0, nb - 1)
    z_all = _normalised_levels(rssi, codes, np.ones(t.size, dtype=bool))
    counts = np.bincount(idx, minlength=nb).astype(float)
    zsum = np.bincount(idx, weights=z_all, minlength=nb)
    w = max(int(round(window_s / bin_s)), 1)
    kern = np.ones(w)
    cnt_w = np.convolve(counts, kern, mode="same")
    z_w = np.convolve(zsum, kern, mode="same")
    cover_w = np.convolve(np.ones(nb), kern, mode="same") * bin_s  # window length inside the record
    rate = cnt_w / cover_w
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.where(cnt_w > 0, z_w / cnt_w, -np.inf)
    base = float(np.median(rate))
    if base <= 0:
        raise NoDataError(f"{name}: no reading rate to speak of")
    low = (rate < rate_drop * base) | (level < -level_drop_db)
    centres = 0.5 * (edges[:-1] + edges[1:])
    runs = _merge_runs(_runs(low), centres, max_gap=window_s)
    return edges, runs, base


def detect_rssi_events(
    t: np.ndarray,
    rssi: np.ndarray,
    sensor: np.ndarray,
    *,
    name: str = "RSSI",
    bin_s: float = 0.1,
    window_s: float = 0.5,
    min_duration: float = 0.3,
    max_duration: float = 10.0,
    rate_drop: float = 0.5,
    level_drop_db: float = 6.0,
    min_llr: float = 20.0,
    min_edge_llr: float = 6.0,
    search_s: float = 1.0,
    context_s: float = 3.0,
    grid_s: float = 0.005,
    same_advert_s: float = 0.002,
) -> list[CoverEvent]:
    """Covered intervals in the pooled readings of every sensor (one beacon), in the RSSI clock.

    ``t`` in seconds (any origin), ``rssi`` in dBm, ``sensor`` any per-reading sensor id. A
    candidate is where the short-window pooled rate falls below ``rate_drop`` of its median or the
    mean per-sensor level falls ``level_drop_db`` dB; each edge is then placed by a change-point
    fit on the raw readings (rate and level together) between ``search_s`` outside the candidate
    edge and the candidate's middle,
    with ``context_s`` of data each side. An event is kept when its edges' log-likelihood ratios
    (step vs no step) add up to ``min_llr`` and each reaches ``min_edge_llr``. Raises NoDataError
    naming ``name`` when nothing is found.
    """
    t = np.asarray(t, dtype=float)
    rssi = np.asarray(rssi, dtype=float)
    sensor = np.asarray(sensor)
    if not (t.shape == rssi.shape == sensor.shape) or t.ndim != 1:
        raise ValueError("t, rssi and sensor must be 1-D arrays of the same length")
    if t.size < 20:
        raise NoDataError(f"{name}: only {t.size} readings; too few to find the cover event")
    order = np.argsort(t, kind="stable")
    t, rssi = t[order], rssi[order]
    _, codes = np.unique(sensor[order], return_inverse=True)

    t0, t1 = float(t[0]), float(t[-1])
    edges, runs, base = _coarse_dips(
        t,
        rssi,
        codes,
        name=name,
        bin_s=bin_s,
        window_s=window_s,
        rate_drop=rate_drop,
        level_drop_db=level_drop_db,
    )
    nb = edges.size - 1

    events: list[CoverEvent] = []
    candidates = 0
    for a, b in runs:
        c_cov, c_rel = float(edges[a]), float(edges[b])
        if not (min_duration - window_s <= c_rel - c_cov <= max_duration + window_s):
            continue
        at_start, at_end = a == 0, b == nb
        mid = 0.5 * (c_cov + c_rel)
        outside = (t < c_cov - window_s) | (t > c_rel + window_s)
        near = (t > c_cov - context_s) & (t < c_rel + context_s)
        z = _normalised_levels(rssi, codes, outside & near)
        cover = release = math.nan
        cs = rs = math.nan
        # Each edge is fitted against the other's estimate (the coarse middle at first): a chance
        # dip can stretch a coarse edge far, and each fit needs covered readings on its inner side.
        llr_c = llr_r = math.nan
        lo = max(c_cov - context_s, t0)
        hi = min(c_rel + context_s, t1)
        half = 0.5 * min_duration
        inner_c = mid
        for _ in range(2):
            if not at_start:
                grid = np.arange(max(c_cov - search_s, lo + grid_s), inner_c, grid_s)
                if grid.size:
                    cover, cs, llr_c = _changepoint(
                        t, z, lo, inner_c, grid, into_covered=True, same_advert_s=same_advert_s
                    )
            if not at_end:
                inner_r = cover + half if math.isfinite(cover) else mid
                grid = np.arange(inner_r + grid_s, min(c_rel + search_s, hi), grid_s)
                if grid.size:
                    release, rs, llr_r = _changepoint(
                        t, z, inner_r, hi, grid, into_covered=False, same_advert_s=same_advert_s
                    )
            if at_start or not math.isfinite(release):
                break
            inner_c = release - half
        llrs = [v for v in (llr_c, llr_r) if math.isfinite(v)]
        log.debug(
            "%s: edges %.3f +- %.3f / %.3f +- %.3f s, LLR %.1f / %.1f",
            name,
            cover,
            cs,
            release,
            rs,
            llr_c,
            llr_r,
        )
        candidates += 1
        if not llrs or sum(llrs) < min_llr or min(llrs) < min_edge_llr:
            continue
        if math.isnan(cover) and math.isnan(release):
            continue
        if (
            math.isfinite(cover)
            and math.isfinite(release)
            and not (min_duration <= release - cover <= max_duration)
        ):
            continue
        events.append(CoverEvent(cover, release, cs, rs, "rssi"))
    if not events:
        why = (
            f"{candidates} dip(s) of the pooled rate or level were too weak to be a cover"
            if candidates
            else f"the pooled reading rate never fell below {rate_drop:.0%} of {base:.1f}/s nor the "
            f"level by {level_drop_db:g} dB for {min_duration}-{max_duration} s"
        )
        raise NoDataError(
            f"{name}: no cover event found ({why}); cover the beacon with both hands for "
            "1-2 s, or use sync.mode: manual with sync.video_start"
        )
    log.info(
        "%s: %d cover event(s): %s",
        name,
        len(events),
        ", ".join(f"{e.cover:.3f}-{e.release:.3f}" for e in events),
    )
    return events


# ---------------------------------------------------------------------------------------------
# (c) the clock map


def _match_events(
    video: list[CoverEvent],
    rssi: list[CoverEvent],
    approx_start: float | None,
    tol: float,
    max_start_error: float,
) -> list[tuple[CoverEvent, CoverEvent]]:
    """Pair video events with RSSI events under one common offset.

    Every (video i, RSSI j) pair proposes an offset; the proposal that pairs the most events with
    consistent times and durations wins, then the smallest duration mismatch, then the one closest
    to ``approx_start``.
    """

    def anchor(e: CoverEvent) -> float:
        return e.cover if math.isfinite(e.cover) else e.release

    best: tuple[tuple[float, ...], list[tuple[CoverEvent, CoverEvent]]] | None = None
    for v in video:
        for r in rssi:
            # Align on an edge both have seen.
            if math.isfinite(v.cover) and math.isfinite(r.cover):
                off = r.cover - v.cover
            elif math.isfinite(v.release) and math.isfinite(r.release):
                off = r.release - v.release
            else:
                continue
            if approx_start is not None and abs(off - approx_start) > max_start_error:
                continue
            pairs, mismatch = [], 0.0
            used: set[int] = set()
            for vv in video:
                for j, rr in enumerate(rssi):
                    if j in used:
                        continue
                    if abs(anchor(rr) - (anchor(vv) + off)) > tol and not (
                        math.isfinite(vv.release)
                        and math.isfinite(rr.release)
                        and abs(rr.release - (vv.release + off)) <= tol
                    ):
                        continue
                    dd = rr.duration - vv.duration
                    if math.isfinite(dd) and abs(dd) > max(tol, 0.3 * abs(vv.duration)):
                        continue
                    pairs.append((vv, rr))
                    used.add(j)
                    mismatch += abs(dd) if math.isfinite(dd) else 0.0
                    break
            prior = abs(off - approx_start) if approx_start is not None else 0.0
            key = (-len(pairs), mismatch, prior)
            if best is None or key < best[0]:
                best = (key, pairs)
    return [] if best is None else best[1]


# A camera's clock runs off the RSSI clock by its crystal's error (tens of ppm; 100 ppm as one
# sigma is generous), unless its timestamps follow a nominal frame rate (30 fps stamped on a
# sensor that runs at 29.97: 1000 ppm). Which case a camera is, is not known: the prior on the
# drift is an even mixture of the two, as (weight, sigma). Two events 25 s apart measure the drift
# only to ~650 ppm; the crystal case then keeps that noise out of the clock map, and the wide one
# lets a large drift through when the data show it (docs/annotator_run.md has the trade-off).
DRIFT_PRIOR: tuple[tuple[float, float], ...] = ((0.5, 1e-4), (0.5, 3e-3))


def _drift_mixture_posterior(
    aw: np.ndarray, bw: np.ndarray, k: int, prior: tuple[tuple[float, float], ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the unknowns of the whitened system ``aw x = bw`` when unknown ``k``
    has a Gaussian-mixture prior [(weight, sigma), ...] and the others a flat one.

    Each component's posterior is Gaussian; its weight is the prior weight times its evidence,
    ``exp(-chi2 / 2) / (sigma sqrt(det H))`` (chi2 with the prior term, H the posterior precision).
    The mixture is returned as one Gaussian with the same mean and covariance.
    """
    h0 = aw.T @ aw
    g = aw.T @ bw
    logs, means, covs = [], [], []
    for weight, sigma in prior:
        h = h0.copy()
        h[k, k] += 1.0 / sigma**2
        c = np.linalg.inv(h)
        mu = c @ g
        r = bw - aw @ mu
        chi2 = float(r @ r) + float(mu[k]) ** 2 / sigma**2
        logs.append(math.log(weight) - math.log(sigma) - 0.5 * chi2 - 0.5 * np.linalg.slogdet(h)[1])
        means.append(mu)
        covs.append(c)
    p = np.exp(np.asarray(logs) - max(logs))
    p /= p.sum()
    mean = np.sum([pi * m for pi, m in zip(p, means, strict=True)], axis=0)
    cov = np.sum(
        [pi * (c + np.outer(m - mean, m - mean)) for pi, m, c in zip(p, means, covs, strict=True)],
        axis=0,
    )
    return mean, cov


def fit_clock_map(
    video_events: list[CoverEvent],
    rssi_events: list[CoverEvent],
    *,
    name: str = "video",
    approx_start: float | None = None,
    max_start_error: float = math.inf,
    fit_drift: bool | None = None,
    min_drift_span: float = 10.0,
    match_tol: float = 0.75,
    lone_edge_sigma: float = 0.03,
    method: str = "auto",
    drift_prior: tuple[tuple[float, float], ...] | None = DRIFT_PRIOR,
) -> ClockMap:
    """Map a video's PTS onto the RSSI clock from matched cover events.

    Each edge seen on both sides is one equation ``t_rssi = start + pts (1 + drift)``, weighted by
    both edges' sigmas; using cover *and* release cancels a detector that widens (or narrows) the
    interval on one side. Drift is fitted when edges span at least ``min_drift_span`` seconds of
    video (i.e. a second event), unless ``fit_drift`` says otherwise, under the mixture prior
    ``drift_prior`` (None: a flat prior, the plain least-squares fit). The uncertainties come from
    the posterior covariance, scaled up when the residuals are larger than the sigmas.

    A gradual cover shifts the two signals' edges in opposite directions (brightness and RSSI do
    not fade alike), by up to about half the closing time. A cover/release pair cancels that; an
    event with only one edge on both sides (e.g. the video started while covered) keeps it, so
    such a lone edge gets ``lone_edge_sigma`` added to its uncertainty.
    """
    if not video_events:
        raise NoDataError(f"{name}: no cover event in the video to synchronise with")
    if not rssi_events:
        raise NoDataError("no cover event in the RSSI to synchronise with")
    pairs = _match_events(video_events, rssi_events, approx_start, match_tol, max_start_error)
    if not pairs:
        raise NoDataError(
            f"{name}: its cover events ({', '.join(f'{e.duration:.2f} s' for e in video_events)}) match "
            f"no RSSI cover event ({', '.join(f'{e.duration:.2f} s' for e in rssi_events)})"
        )
    # One equation per edge seen on both sides; sign: -1 cover, +1 release.
    x, y, s, sign = [], [], [], []
    has_pair = False
    edges = []
    for v, r in pairs:
        both = [
            (tv, sv, tr, sr, sg)
            for tv, sv, tr, sr, sg in (
                (v.cover, v.cover_sigma, r.cover, r.cover_sigma, -1.0),
                (v.release, v.release_sigma, r.release, r.release_sigma, 1.0),
            )
            if math.isfinite(tv) and math.isfinite(tr)
        ]
        has_pair |= len(both) == 2
        edges.append(both)
    for both in edges:
        # Without any pair the symmetric bias cannot be fitted: a lone edge carries it as noise.
        lone = lone_edge_sigma if (len(both) == 1 and not has_pair) else 0.0
        for tv, sv, tr, sr, sg in both:
            x.append(tv)
            y.append(tr)
            sign.append(sg)
            s.append(
                math.sqrt(
                    (sv if math.isfinite(sv) else 0.0) ** 2
                    + (sr if math.isfinite(sr) else 0.0) ** 2
                    + lone**2
                )
            )
    xa, ya, ga = np.asarray(x), np.asarray(y), np.asarray(sign)
    sa = np.maximum(np.asarray(s), 1e-4)  # never infinitely sure of an edge
    span = float(xa.max() - xa.min())
    drift = fit_drift if fit_drift is not None else (len(pairs) >= 2 and span >= min_drift_span)
    # Unknowns: start, [edge bias (half the cover/release widening), ] [drift].
    cols = [np.ones_like(xa)]
    if has_pair:
        cols.append(ga)
    if drift and xa.size > len(cols):
        cols.append(xa)
    else:
        drift = False
    A = np.column_stack(cols)
    wts = 1.0 / sa**2
    yd = ya - xa
    Aw = A * np.sqrt(wts)[:, None]
    coef, *_ = np.linalg.lstsq(Aw, yd * np.sqrt(wts), rcond=None)
    cov = np.linalg.inv(Aw.T @ Aw)
    n_par = float(A.shape[1])
    if drift and drift_prior:
        coef, cov = _drift_mixture_posterior(Aw, yd * np.sqrt(wts), A.shape[1] - 1, drift_prior)
        n_par = float(np.trace(Aw.T @ Aw @ cov))  # a drift the prior holds is not a free unknown
    resid = yd - A @ coef
    dof = xa.size - n_par
    if dof > 0.5:
        chi2 = float(np.sum(wts * resid**2)) / dof
        cov = cov * max(1.0, chi2)
    k = A.shape[1] - 1  # drift is the last column when fitted
    cm = ClockMap(
        video_start=float(coef[0]),
        drift=float(coef[k]) if drift else 0.0,
        video_start_sigma=float(math.sqrt(cov[0, 0])),
        drift_sigma=float(math.sqrt(cov[k, k])) if drift else math.nan,
        method=method,
        n_edges=int(xa.size),
        residual_rms=float(np.sqrt(np.mean(resid**2))),
        edge_bias=float(coef[1]) if has_pair else math.nan,
        start_drift_cov=float(cov[0, k]) if drift else 0.0,
    )
    log.info(
        "%s: video_start %.4f +- %.4f s, drift %.2e, from %d edges",
        name,
        cm.video_start,
        cm.video_start_sigma,
        cm.drift,
        cm.n_edges,
    )
    return cm


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
