"""Labelling RSSI readings with the bundle pose at their own timestamps.

Pure: positions are interpolated linearly and rotations by Slerp between the two poses that
bracket each reading (annotator.core.trajectory's ``bracket`` and ``blend``). Readings before/after the tracked span or inside a long tracking gap are
left unlabelled (NaN), never extrapolated.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from annotator.core.trajectory import Trajectory, blend, bracket

log = logging.getLogger(__name__)

# Why a reading got no pose.
LABELLED, BEFORE_SPAN, AFTER_SPAN, IN_GAP, COVERED = 0, 1, 2, 3, 4
REASONS = {
    LABELLED: "labelled",
    BEFORE_SPAN: "before the tracked span",
    AFTER_SPAN: "after the tracked span",
    IN_GAP: "inside a tracking gap",
    COVERED: "during a cover event",
}


@dataclass(frozen=True, eq=False)
class Labels:
    """Per reading (same order as the input): pose, quality, and why unlabelled."""

    positions: np.ndarray  # (M, 3), NaN where unlabelled
    rotations: np.ndarray  # (M, 3, 3), NaN where unlabelled
    sigma: np.ndarray  # (M,) interpolated position sigma, NaN if unknown
    markers: np.ndarray  # (M,) markers used by the nearest pose, -1 if unknown
    gap_s: np.ndarray  # (M,) time to the nearest pose, s (NaN if outside the span)
    reason: np.ndarray  # (M,) int8: LABELLED, BEFORE_SPAN, AFTER_SPAN, IN_GAP, COVERED
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def labelled(self) -> np.ndarray:
        return self.reason == LABELLED


def label_readings(
    poses: Trajectory,
    t_ns: np.ndarray,
    *,
    max_gap: float = 0.5,
    exclude: Sequence[tuple[float, float]] = (),
    time_sigma: float | np.ndarray | None = None,
) -> Labels:
    """Pose of the bundle at each reading time ``t_ns`` (int64 Unix ns).

    ``poses``' rows without a pose are gaps; its optional quality arrays ``sigma_m`` (position
    1-sigma, m) and ``markers`` (markers used) give the readings' ``sigma`` and ``markers``.

    A reading is labelled when it lies inside [first pose, last pose] and the two poses around it
    are at most ``max_gap`` seconds apart. Position: linear interpolation; rotation: Slerp.
    Readings inside an ``exclude`` interval (Unix seconds; the sync cover events, when hands
    over the beacon distort the RSSI) are never labelled, whatever the poses.
    ``time_sigma`` (s, scalar or per reading): 1-sigma uncertainty of the readings' times against
    the video clock (the sync); a reading's sigma then adds speed x time_sigma / sqrt(3) in
    quadrature, the speed being that of the two poses around it. A clock error moves the label
    along the direction of motion only, and ``sigma`` is per axis (the rms over x, y and z, as the
    trajectory's ``sigma_m``): that one axis holds a third of the 3-D variance.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    m = t_ns.size
    # Only the rows with a pose, in time order, one per time (two cameras' frames fused at one time).
    poses = poses.compact()
    tp = poses.t
    out_pos = np.full((m, 3), np.nan)
    out_rot = np.full((m, 3, 3), np.nan)
    out_sig = np.full(m, np.nan)
    out_mk = np.full(m, -1, dtype=np.int64)
    gap_s = np.full(m, np.nan)
    reason = np.full(m, BEFORE_SPAN, dtype=np.int8)
    if tp.size == 0 or m == 0:
        return Labels(out_pos, out_rot, out_sig, out_mk, gap_s, reason, _count(reason))

    # Work relative to the first pose: float seconds of ~1.7e9 keep only ~0.2 us.
    ref_ns = int(round(tp[0] * 1e9))
    tr = (t_ns - ref_ns).astype(np.float64) / 1e9
    tpr = tp - tp[0]
    reason[tr > tpr[-1]] = AFTER_SPAN
    inside = (tr >= 0.0) & (tr <= tpr[-1])
    lo, hi, w = bracket(tpr, tr)
    span = tpr[hi] - tpr[lo]
    near = np.minimum(np.abs(tr - tpr[lo]), np.abs(tpr[hi] - tr))
    gap_s[inside] = near[inside]
    good = inside & (span <= max_gap)
    reason[inside & ~good] = IN_GAP
    for a, b in exclude:
        lo_ns = -(2**62) if a == -np.inf else int(round(a * 1e9))
        hi_ns = 2**62 if b == np.inf else int(round(b * 1e9))
        hit = inside & (t_ns >= lo_ns) & (t_ns <= hi_ns)
        good &= ~hit
        reason[hit] = COVERED
    reason[good] = LABELLED
    if not good.any():
        return Labels(out_pos, out_rot, out_sig, out_mk, gap_s, reason, _count(reason))

    g_lo, g_hi, w, span = lo[good], hi[good], w[good], span[good]
    P = poses.position
    out_pos[good], out_rot[good] = blend(P, poses.rotation, g_lo, g_hi, w)
    sigma, markers = poses.quality.get("sigma_m"), poses.quality.get("markers")
    if sigma is not None:
        S = np.asarray(sigma, dtype=float)
        out_sig[good] = S[g_lo] + (S[g_hi] - S[g_lo]) * w
        if time_sigma is not None:
            ts = np.broadcast_to(np.nan_to_num(np.asarray(time_sigma, dtype=float), nan=0.0), (m,))[
                good
            ]
            speed = np.divide(
                np.linalg.norm(P[g_hi] - P[g_lo], axis=1),
                span,
                out=np.zeros_like(span),
                where=span > 0,
            )
            out_sig[good] = np.hypot(out_sig[good], speed * ts / np.sqrt(3.0))
    if markers is not None:
        M = np.asarray(markers)
        nearest = np.where(w <= 0.5, g_lo, g_hi)
        out_mk[good] = np.nan_to_num(M[nearest].astype(float), nan=-1).astype(np.int64)
    labels = Labels(out_pos, out_rot, out_sig, out_mk, gap_s, reason, _count(reason))
    log.info(
        "labelled %d of %d readings (%s)",
        labels.counts["labelled"],
        m,
        ", ".join(f"{k}: {v}" for k, v in labels.counts.items() if k != "labelled"),
    )
    return labels


def _count(reason: np.ndarray) -> dict[str, int]:
    return {REASONS[k]: int(np.sum(reason == k)) for k in REASONS}


def describe_counts(counts: dict[str, int]) -> str:
    """One sentence saying what the counts of :func:`label_readings` count, e.g. "labelled 3032
    of 3032 readings inside the tracked span; 326 left out (179 after it ends, 147 while the
    bundle was covered)". Takes ``Labels.counts`` or report.json's ``counts`` (underscores)."""
    n = {k.replace("_", " "): int(v) for k, v in counts.items()}
    labelled, gap = n.get(REASONS[LABELLED], 0), n.get(REASONS[IN_GAP], 0)
    text = f"labelled {labelled} of {labelled + gap} readings inside the tracked span"
    if gap:
        text += f" ({gap} in tracking gaps longer than the largest gap allowed)"
    parts = [
        (n.get(REASONS[BEFORE_SPAN], 0), "before it starts"),
        (n.get(REASONS[AFTER_SPAN], 0), "after it ends"),
        (n.get(REASONS[COVERED], 0), "while the bundle was covered"),
    ]
    out = sum(k for k, _ in parts)
    if out:
        text += f"; {out} left out (" + ", ".join(f"{k} {why}" for k, why in parts if k) + ")"
    return text


def tracked_span_coverage(labels: Labels) -> float:
    """Fraction of the readings inside the tracked span that got a pose (1.0 if none are inside).

    Readings during a cover event do not count: they are left out on purpose.
    """
    inside = (labels.reason == LABELLED) | (labels.reason == IN_GAP)
    n = int(inside.sum())
    return float(labels.labelled.sum()) / n if n else 1.0
