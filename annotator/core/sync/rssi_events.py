"""Cover events in the pooled RSSI readings: the rate and the level of the readings drop while
hands cover the bundle; each edge placed by a change-point fit on the raw readings."""

from __future__ import annotations

import logging
import math

import numpy as np

from annotator.core.sync.records import CoverEvent, merge_runs, true_runs
from annotator.errors import NoDataError

log = logging.getLogger(__name__)

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
    runs = merge_runs(true_runs(low), centres, max_gap=window_s)
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
