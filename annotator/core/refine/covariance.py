"""What the self-calibration hands to the uncertainty propagation: the covariance of its
blocks, the joint record's index, the rig's gauge and the keyframes' correlation stretch."""

from __future__ import annotations

import logging
import math

import numpy as np

from annotator.core.priors import PRINTED_SCALE, ParameterCovariance
from annotator.core.refine.gate import _rigid_basis
from annotator.core.refine.lm import _LM
from annotator.core.refine.model import (
    BIAS,
    DIST,
    INTR,
    READOUT,
    RIG,
    SCALE,
    Problem,
    _Layout,
)

log = logging.getLogger(__name__)


def _correlation_stretch(
    prob: Problem, uv: np.ndarray, sigma_px: float, max_lag: int = 40
) -> float:
    """How many times fewer independent corners the keyframes hold than their count.

    The errors of one marker corner seen by one camera are alike from keyframe to keyframe (the
    same view, blur, print) and stay so while the view changes little. For errors with
    autocorrelation rho_k at a lag of k keyframes the variance of an average is tau = 1 + 2 sum_k
    rho_k times the independent one's (the integrated autocorrelation time; (1 + rho) / (1 - rho)
    for a first-order process). rho_k: the solve's residuals (beyond 3 sigma clipped), pooled
    over the corners; the sum stops at the first lag whose correlation is not positive (the noise
    of the estimates beyond). 1 when the errors are independent.
    """
    o = prob.obs
    r = np.clip(uv - o.uv, -3 * sigma_px, 3 * sigma_px)
    key = (o.marker * len(prob.cameras) + o.camera) * 4 + o.corner
    order = np.lexsort((o.keyframe, key))
    k, kf, r = key[order], o.keyframe[order], r[order]
    num = np.zeros(max_lag + 1)
    den = np.zeros(max_lag + 1)
    pairs = np.zeros(max_lag + 1)
    for j in range(1, max_lag + 1):  # j-th next observation of the same corner track
        lag = kf[j:] - kf[:-j]
        ok = (k[j:] == k[:-j]) & (lag <= max_lag)
        if not ok.any():
            break
        a, b = r[:-j][ok], r[j:][ok]
        num += np.bincount(lag[ok], np.sum(a * b, axis=1), max_lag + 1)
        den += np.bincount(lag[ok], 0.5 * np.sum(a * a + b * b, axis=1), max_lag + 1)
        pairs += np.bincount(lag[ok], minlength=max_lag + 1)
    if pairs[1] < 20:
        return 1.0
    tau = 1.0
    for n, d in zip(num[1:], den[1:], strict=True):
        rho = n / d if d > 0 else 0.0
        if rho <= 0:
            break
        tau += 2.0 * min(rho, 0.99)
    tau = min(tau, 50.0)
    log.info(
        "refine: keyframe residuals' correlation time %.1f keyframes (information / %.1f)", tau, tau
    )
    return tau


def _rig_gauge(layout: _Layout, prob: Problem, t_bc: np.ndarray) -> np.ndarray:
    """Covariance of the rig's gauge in the static parameters (zero without a rig block).

    The solve pins the mean change over the cameras to the measured rig (_prior_precision), so its
    covariance says nothing of the error of that mean; yet the measured rig is off by its cameras'
    mean error (prior / n per axis), a rigid motion of every camera that the data cannot see: a
    rotation W about the cameras' mean position and a shift T, i.e. camera c's rotation W and
    shift W x (t_c - mean t) + T. It moves the beacon (the bundle's origin) in the world. With a
    jig (priors.jig) the pipeline sets that motion from the rest and conditions this covariance on
    it (uncertainty.condition_on_rest).
    """
    out = np.zeros((layout.n_static, layout.n_static))
    sl = layout.static_slices()
    if RIG not in sl:
        return out
    o, n, _ = sl[RIG]
    pr = prob.priors
    G = np.zeros((layout.n_static, 6))
    G[o : o + 6 * n] = _rigid_basis(t_bc - t_bc.mean(axis=0))
    var = np.array([math.radians(pr.rig_sigma_deg) ** 2] * 3 + [pr.rig_sigma_m**2] * 3) / n
    return (G * var) @ G.T


# The refinement's blocks under their names in ParameterCovariance.joint_index.
_KIND = {RIG: "rig", INTR: "intrinsics", DIST: "distortion", READOUT: "readout", BIAS: "bias"}


def _joint_index(layout: _Layout, prob: Problem) -> dict[tuple[str, int | str], np.ndarray]:
    """Rows of each block of the static covariance, keyed as ParameterCovariance.joint_index."""
    sl = layout.static_slices()
    off = sl["marker"][0]
    index: dict[tuple[str, int | str], np.ndarray] = {}
    for m, mid in enumerate(prob.markers):
        if layout.free_markers[m]:
            index["markers", int(mid)] = np.arange(off + 6 * m, off + 6 * m + 6)
    for c, cam in enumerate(prob.cameras):
        for name, kind in _KIND.items():
            if name in sl:
                o, _, size = sl[name]
                index[kind, cam.name] = np.arange(o + c * size, o + (c + 1) * size)
    if SCALE in sl:  # the markers' printed size, one for all: relative to the length used
        index[PRINTED_SCALE] = np.array([sl[SCALE][0]])
    return index


def _covariance(
    cov: np.ndarray, layout: _Layout, prob: Problem, lm: _LM
) -> tuple[ParameterCovariance, np.ndarray]:
    sl = layout.static_slices()
    off = sl["marker"][0]
    markers, msig = {}, np.full(layout.M, np.nan)
    for m, mid in enumerate(prob.markers):
        if not layout.free_markers[m]:
            sr, sm = prob.marker_sigma[m]
            if np.isfinite(sr):
                markers[mid] = np.diag([sr * sr] * 3 + [sm * sm] * 3)
                msig[m] = sm
            continue
        b = off + 6 * m
        markers[mid] = cov[b : b + 6, b : b + 6].copy()
        msig[m] = math.sqrt(np.trace(markers[mid][3:, 3:]) / 3)
    rig: dict[str, np.ndarray] = {}
    intr: dict[str, np.ndarray] = {}
    dist: dict[str, np.ndarray] = {}
    readout: dict[str, np.ndarray] = {}
    for c, cam in enumerate(prob.cameras):
        for name, target in ((RIG, rig), (INTR, intr), (DIST, dist), (READOUT, readout)):
            if name not in sl:
                continue
            o, _, size = sl[name]
            b = o + c * size
            target[cam.name] = cov[b : b + size, b : b + size].copy()
        if RIG not in sl:
            pr = prob.priors
            rig[cam.name] = np.diag(
                [math.radians(pr.rig_sigma_deg) ** 2] * 3 + [pr.rig_sigma_m**2] * 3
            )
        if INTR not in sl:
            f = prob.priors.focal_sigma_rel
            intr[cam.name] = np.diag(
                [
                    (f * cam.K[0, 0]) ** 2,
                    (f * cam.K[1, 1]) ** 2,
                    prob.priors.principal_sigma_px**2,
                    prob.priors.principal_sigma_px**2,
                ]
            )
    return ParameterCovariance(markers, rig, intr, distortion=dist, readout=readout), msig
