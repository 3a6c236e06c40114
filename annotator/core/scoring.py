"""Scoring a localizer's position estimates against annotated ground truth, as pure array code.

Each estimate ``(t, x, y[, z])`` is compared with the ground truth *at its own timestamp*: the
truth is linearly interpolated between the two samples that bracket ``t`` and never
extrapolated, so an estimate before the first or after the last truth sample, or inside a truth
gap longer than ``max_gap_s``, is not scored (it counts against coverage instead). No alignment
of any kind is applied: the errors are what a user of the localizer would see.

Figures follow ISO/IEC 18305 naming: ``ce50``/``ce75``/``ce95`` are the 50th/75th/95th
percentiles of the horizontal (2-D) or spatial (3-D) error ("circular / spherical error
probable" at those levels); the EvAAL / IPIN competitions rank by the 75th percentile. The
truth's own 1-sigma (when the annotation carries one) is summarised beside them, so nobody reads
an error finer than the labels as meaningful.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from annotator.core.trajectory import bracket

DEFAULT_MAX_GAP_S = 1.0  # truth samples further apart than this are a gap, not interpolated
DEFAULT_COVERAGE_WINDOW_S = 1.0  # a truth instant is "covered" by an estimate this close in time
LATENCY_MIN_ESTIMATES = 10


@dataclass(frozen=True, slots=True)
class Truth:
    """Ground-truth positions: ``t`` sorted and unique (Unix s), ``position`` (N, 3) with NaN
    rows for gaps, ``sigma`` (N,) position 1-sigma in metres when the annotation has one."""

    t: np.ndarray
    position: np.ndarray
    sigma: np.ndarray | None = None
    source: str = ""

    @classmethod
    def from_samples(
        cls, t: np.ndarray, position: np.ndarray, sigma: np.ndarray | None = None, source: str = ""
    ) -> Truth:
        """Sorted by time; of several samples with the same timestamp the first is kept (track
        files repeat one pose on every sensor's row)."""
        t = np.asarray(t, dtype=float)
        position = np.asarray(position, dtype=float).reshape(-1, 3)
        order = np.argsort(t, kind="stable")
        t, position = t[order], position[order]
        keep = np.ones(len(t), dtype=bool)
        keep[1:] = t[1:] != t[:-1]
        sig = None if sigma is None else np.asarray(sigma, dtype=float)[order][keep]
        return cls(t[keep], position[keep], sig, source)


@dataclass(frozen=True, slots=True)
class ErrorSummary:
    mean: float
    median: float
    rmse: float
    ce50: float
    ce75: float
    ce95: float
    max: float
    n: int

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(self).items()
        }


def summarize(errors: np.ndarray) -> ErrorSummary:
    """Summary of the finite values; no finite value -> n 0 and NaN figures."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if not e.size:
        nan = float("nan")
        return ErrorSummary(nan, nan, nan, nan, nan, nan, nan, 0)
    p50, p75, p95 = np.percentile(e, [50, 75, 95])
    return ErrorSummary(
        float(e.mean()),
        float(p50),
        float(np.sqrt(np.mean(e * e))),
        float(p50),
        float(p75),
        float(p95),
        float(e.max()),
        int(e.size),
    )


def interpolate_truth(
    truth: Truth, t: np.ndarray, *, max_gap_s: float = DEFAULT_MAX_GAP_S, shift_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Truth position (M, 3) and sigma (M,) at times ``t - shift_s``; NaN where there is no
    bracketing pair of valid truth samples at most ``max_gap_s`` apart (never extrapolated).
    A time equal to a truth sample's takes that sample exactly."""
    tt = np.asarray(truth.t, dtype=float)
    q = np.asarray(t, dtype=float) - shift_s
    m = len(q)
    pos = np.full((m, 3), np.nan)
    sig = np.full(m, np.nan)
    if len(tt) == 0:
        return pos, sig
    valid = np.isfinite(truth.position[:, :2]).all(axis=1)
    if not valid.any():
        return pos, sig
    vt = tt[valid]
    vp = np.asarray(truth.position, dtype=float)[valid]
    vs = None if truth.sigma is None else np.asarray(truth.sigma, dtype=float)[valid]
    if len(vt) == 1:
        ok = q == vt[0]
        pos[ok] = vp[0]
        if vs is not None:
            sig[ok] = vs[0]
        return pos, sig
    i0, i1, frac = bracket(vt, q)  # the trajectory's bracketing (vt is unique: no empty span)
    span = vt[i1] - vt[i0]
    on_sample = (frac == 0.0) | (frac == 1.0)
    # a gap in the truth: the valid neighbours are far apart in time, or NaN rows lie between them
    nan_between = np.searchsorted(tt, vt[i1]) - np.searchsorted(tt, vt[i0]) > 1
    gap = (span > max_gap_s) | nan_between
    ok = np.isfinite(q) & (q >= vt[0]) & (q <= vt[-1]) & (on_sample | ~gap)
    if not ok.any():
        return pos, sig
    a, b, f = i0[ok], i1[ok], frac[ok]
    pos[ok] = vp[a] * (1.0 - f[:, None]) + vp[b] * f[:, None]
    if vs is not None:
        sig[ok] = vs[a] * (1.0 - f) + vs[b] * f
    return pos, sig


@dataclass(frozen=True)
class Latency:
    shift_s: float  # estimates lag the truth by this much (positive: the localizer is late)
    ce50_at_shift: float
    ce50_at_zero: float
    searched: tuple[float, float, float]  # (-max, max, step)

    def as_dict(self) -> dict[str, object]:
        return {
            "shift_s": self.shift_s,
            "ce50_2d_at_shift_m": _num(self.ce50_at_shift),
            "ce50_2d_at_zero_m": _num(self.ce50_at_zero),
            "searched_s": list(self.searched),
            "meaning": "the time shift that minimises the median 2-D error; positive = "
            "the estimates lag the truth",
        }


@dataclass(frozen=True)
class Score:
    t: np.ndarray  # (M,) estimate times
    error_2d: np.ndarray  # (M,) metres, NaN where not scored
    error_3d: np.ndarray  # (M,) metres, NaN where not scored or the estimate has no z
    truth_at_estimates: np.ndarray  # (M, 3)
    truth_sigma: np.ndarray  # (M,) truth 1-sigma at the scored estimates (NaN: unknown)
    coverage: dict[str, object]
    latency: Latency | None = None
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def summary_2d(self) -> ErrorSummary:
        return summarize(self.error_2d)

    @property
    def summary_3d(self) -> ErrorSummary:
        return summarize(self.error_3d)

    def report(self) -> dict[str, object]:
        sig = self.truth_sigma[np.isfinite(self.truth_sigma)]
        truth_sigma: dict[str, object] = {
            "n": int(sig.size),
            "median": _num(float(np.median(sig))) if sig.size else None,
            "p95": _num(float(np.percentile(sig, 95))) if sig.size else None,
            "note": (
                "the ground truth's own position 1-sigma at the scored estimates; errors "
                "below it are not resolved"
                if sig.size
                else "the ground truth carries no per-sample sigma"
            ),
        }
        return {
            "error_2d_m": self.summary_2d.as_dict(),
            "error_3d_m": self.summary_3d.as_dict(),
            "truth_sigma_m": truth_sigma,
            "coverage": self.coverage,
            "latency": None if self.latency is None else self.latency.as_dict(),
            **self.extra,
        }


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _errors(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = est - ref
    e2 = np.hypot(d[:, 0], d[:, 1])
    e3 = np.sqrt(e2 * e2 + d[:, 2] * d[:, 2])
    return e2, e3


def coverage(
    t: np.ndarray, scored: np.ndarray, truth: Truth, window_s: float = DEFAULT_COVERAGE_WINDOW_S
) -> dict[str, object]:
    """How much was scored: estimates scored of all given, and the fraction of the truth's valid
    samples that have a scored estimate within ``window_s`` seconds."""
    n = len(t)
    valid_t = np.asarray(truth.t)[np.isfinite(np.asarray(truth.position)[:, :2]).all(axis=1)]
    st = np.sort(np.asarray(t)[scored])
    if st.size and valid_t.size:
        i = np.searchsorted(st, valid_t)
        before = np.abs(valid_t - st[np.clip(i - 1, 0, st.size - 1)])
        after = np.abs(st[np.clip(i, 0, st.size - 1)] - valid_t)
        covered = float(np.mean(np.minimum(before, after) <= window_s))
    else:
        covered = 0.0
    return {
        "estimates": int(n),
        "scored": int(scored.sum()),
        "not_scored": int(n - scored.sum()),
        "scored_fraction": float(scored.mean()) if n else 0.0,
        "truth_covered_fraction": covered,
        "coverage_window_s": window_s,
        "truth_span_s": [float(valid_t[0]), float(valid_t[-1])] if valid_t.size else None,
    }


def estimate_latency(
    t: np.ndarray,
    est: np.ndarray,
    truth: Truth,
    *,
    max_shift_s: float = 3.0,
    step_s: float = 0.05,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
) -> Latency | None:
    """The time shift in [-max, max] (grid of ``step_s``) minimising the median 2-D error of
    ``est`` against the truth at ``t - shift``; None when too few estimates can be scored."""
    shifts = np.round(np.arange(-max_shift_s, max_shift_s + step_s / 2, step_s), 9)
    best = (math.inf, 0.0)
    at_zero = math.nan
    for s in shifts:
        ref, _ = interpolate_truth(truth, t, max_gap_s=max_gap_s, shift_s=float(s))
        e2, _ = _errors(est, ref)
        e2 = e2[np.isfinite(e2)]
        if e2.size < LATENCY_MIN_ESTIMATES:
            continue
        med = float(np.median(e2))
        if s == 0:
            at_zero = med
        if med < best[0] - 1e-12 or (abs(med - best[0]) <= 1e-12 and abs(s) < abs(best[1])):
            best = (med, float(s) + 0.0)
    if not math.isfinite(best[0]):
        return None
    return Latency(best[1], best[0], at_zero, (-max_shift_s, max_shift_s, step_s))


def score(
    t: np.ndarray,
    est: np.ndarray,
    truth: Truth,
    *,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    coverage_window_s: float = DEFAULT_COVERAGE_WINDOW_S,
    latency_max_s: float | None = None,
    latency_step_s: float = 0.05,
) -> Score:
    """Per-estimate 2-D and 3-D errors of ``est`` (M, 3; z NaN when the localizer gives none)
    at times ``t`` against ``truth``, with coverage and, if ``latency_max_s`` is given, the
    latency estimate."""
    t = np.asarray(t, dtype=float)
    est = np.asarray(est, dtype=float).reshape(-1, 3)
    ref, sig = interpolate_truth(truth, t, max_gap_s=max_gap_s)
    e2, e3 = _errors(est, ref)
    scored = np.isfinite(e2)
    sig = np.where(scored, sig, np.nan)
    lat = None
    if latency_max_s is not None and latency_max_s > 0:
        lat = estimate_latency(
            t, est, truth, max_shift_s=latency_max_s, step_s=latency_step_s, max_gap_s=max_gap_s
        )
    return Score(t, e2, e3, ref, sig, coverage(t, scored, truth, coverage_window_s), lat)
