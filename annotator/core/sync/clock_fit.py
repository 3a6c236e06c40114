"""The clock map of a video: match its cover events to the RSSI ones and fit
``t_rssi = video_start + pts * (1 + drift)``, with the uncertainty of both."""

from __future__ import annotations

import logging
import math

import numpy as np

from annotator.core.sync.records import ClockMap, CoverEvent
from annotator.errors import NoDataError

log = logging.getLogger(__name__)

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


def drift_mixture_posterior(
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
        coef, cov = drift_mixture_posterior(Aw, yd * np.sqrt(wts), A.shape[1] - 1, drift_prior)
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
