"""Offline smoothing of per-frame bundle poses: RTS on position, local fits on SO(3) for rotation.

Position: constant-velocity Kalman filter (filterpy) with each frame's own measurement
covariance, Mahalanobis gating of outliers, then a Rauch-Tung-Striebel backward pass.
Rotation: at each output time, a weighted local-linear fit of rotation-vector offsets around a
robust local mean (scipy Rotation), so rotations stay rotations and turns do not lag.
The frames' own scatter about the smoothed track says how noisy they really were: each run's
measured-to-stated noise ratio comes back beside the track (``noise_scale``), for the sigma a
caller reports; the filter's weights keep the stated covariances.
Pure functions on arrays; times in seconds; a time with no support comes back as NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import predict, rts_smoother, update
from scipy.spatial.transform import Rotation

CHI2_3DOF_999 = 16.27  # 99.9 % gate for a 3-d innovation


@dataclass(frozen=True, slots=True)
class SmootherSettings:
    accel_psd: float = 0.5  # white-acceleration spectral density, m^2/s^3 (a person carrying a rig)
    min_sigma_m: float = 0.002  # floor on a measurement's position sigma
    max_gap_s: float = 0.8  # no output across a longer run without measurements
    max_extrapolate_s: float = 0.1  # output this far beyond the first / last measurement of a run
    max_meas_sigma_m: float = 0.15  # measurements vaguer than this (a lone far marker) are ignored
    max_out_sigma_m: float = 0.05  # output times whose smoothed sigma exceeds this become gaps
    # The reported sigma follows the frames' scatter about the smoothed track (the ratio of the
    # noise they show to the noise they state) once this many frames were accepted; before, 1.
    min_scatter_frames: int = 30
    gate_chi2: float = CHI2_3DOF_999
    rot_bandwidth_s: float = 0.08  # Gaussian kernel sigma of the rotation fit
    # The kernel of the motion the self-calibration reads the rolling shutter from: narrower, so
    # a carried bundle's ~3 Hz wobble keeps its rate (0.08 s passes a third of it, 0.04 s 3/4).
    motion_rot_bandwidth_s: float = 0.04
    rot_gate_deg: float = 3.0  # a rotation this far from its neighbours' fit is an outlier
    # The track is re-anchored on the measurements when more than this many in a row, over more
    # than reset_after_s, all fail the gate (the filter, not the camera, is lost).
    reset_after: int = 15
    reset_after_s: float = 0.3


JUMP = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])  # a re-anchoring step's process noise: m^2, (m/s)^2


def _segments(t: np.ndarray, max_gap: float) -> list[tuple[int, int]]:
    """Index ranges [i, j) of measurement runs without a gap longer than max_gap."""
    if len(t) == 0:
        return []
    cuts = np.flatnonzero(np.diff(t) > max_gap) + 1
    edges = np.concatenate([[0], cuts, [len(t)]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _cv_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    F = np.eye(6)
    F[:3, 3:] = dt * np.eye(3)
    Q = np.zeros((6, 6))
    Q[:3, :3] = q * dt**3 / 3 * np.eye(3)
    Q[:3, 3:] = Q[3:, :3] = q * dt**2 / 2 * np.eye(3)
    Q[3:, 3:] = q * dt * np.eye(3)
    return F, Q


def smooth_positions(
    t_meas: np.ndarray,
    z: np.ndarray,
    cov: np.ndarray,
    t_out: np.ndarray,
    settings: SmootherSettings | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Smoothed positions at ``t_out``.

    ``t_meas`` (N,) sorted, ``z`` (N, 3), ``cov`` (N, 3, 3). Returns positions (M, 3) and their
    1-sigma (M,) from the stated covariances (NaN outside the measured spans), the (N,) mask of
    measurements accepted by the gate, and ``noise_scale``: how far the accepted measurements
    really scatter about the smoothed track in units of their stated sigma (1.0 with fewer than
    ``min_scatter_frames`` of them). An honest ``cov`` gives ~1; multiplying the returned sigma
    by it gives the sigma of the noise the frames show.
    """
    s = settings or SmootherSettings()
    t_meas, t_out = np.asarray(t_meas, float), np.asarray(t_out, float)
    out = np.full((len(t_out), 3), np.nan)
    sig = np.full(len(t_out), np.nan)
    accepted = np.zeros(len(t_meas), dtype=bool)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    floor = s.min_sigma_m**2 * np.eye(3)
    scatter: list[np.ndarray] = []  # per run: normalised squared residuals of accepted frames
    for a, b in _segments(t_meas, s.max_gap_s):
        lo, hi = t_meas[a], t_meas[b - 1]
        q_idx = np.flatnonzero((t_out >= lo) & (t_out <= hi))
        # One time grid holding both measurements (kind 0) and output times (kind 1).
        times = np.concatenate([t_meas[a:b], t_out[q_idx]])
        kind = np.concatenate([np.zeros(b - a, int), np.ones(len(q_idx), int)])
        ref = np.concatenate([np.arange(a, b), q_idx])
        order = np.lexsort((kind, times))
        times, kind, ref = times[order], kind[order], ref[order]
        n = len(times)
        x = np.concatenate([z[a], np.zeros(3)])
        P = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
        Xs, Ps = np.zeros((n, 6)), np.zeros((n, 6, 6))
        Fs, Qs = np.zeros((n, 6, 6)), np.zeros((n, 6, 6))
        Fs[0] = np.eye(6)
        streak, last_ok = 0, 0  # rejections in a row; grid index of the last accepted measurement
        jump_at = -1
        k = 0
        while k < n:
            F, Q = _cv_model(times[k] - times[max(k - 1, 0)], s.accel_psd)
            if k > 0:
                x, P = predict(x, P, F, Q)
                if k == jump_at:
                    # A jump in the process (in the model too, so the backward pass agrees).
                    Q = Q + JUMP
                    P = P + JUMP
                Fs[k - 1], Qs[k - 1] = F, Q  # module rts_smoother: Fs[k] takes step k to k+1
            if kind[k] == 0:
                i = ref[k]
                R = cov[i] + floor
                y = z[i] - H @ x
                S = H @ P @ H.T + R
                d2 = float(y @ np.linalg.solve(S, y))
                # The first measurement of a run cannot be judged against a 1 m prior; accept it.
                if d2 <= s.gate_chi2 or k == 0 or k == jump_at:
                    x, P = update(x, P, z[i], R, H)
                    accepted[i] = True
                    streak, last_ok = 0, k
                else:
                    streak += 1
                    if streak > s.reset_after and times[k] - times[last_ok] > s.reset_after_s:
                        # Every measurement for a while disagrees with the prediction: the filter
                        # (a bad start after a gap), not the camera, lost the track. Go back to the
                        # first rejected measurement and let the state jump there.
                        k = last_ok + 1
                        while kind[k] != 0:
                            k += 1
                        jump_at, streak = k, 0
                        x, P = Xs[k - 1], Ps[k - 1]
                        continue
            Xs[k], Ps[k] = x, P
            k += 1
        Xs, Ps, _, _ = rts_smoother(Xs, Ps, Fs, Qs)
        at = np.flatnonzero(kind == 0)
        at = at[accepted[ref[at]]]
        scatter.append(_normalised_residuals(z[ref[at]], cov[ref[at]] + floor, Xs[at], Ps[at]))
        q_rows = kind == 1
        out[ref[q_rows]] = Xs[q_rows, :3]
        sig[ref[q_rows]] = np.sqrt(np.trace(Ps[q_rows, :3, :3], axis1=1, axis2=2) / 3)
    q = np.concatenate(scatter) if scatter else np.zeros(0)
    scale = math.sqrt(float(np.mean(q)) / 3) if len(q) >= s.min_scatter_frames else 1.0
    return out, sig, accepted, scale


def _normalised_residuals(z: np.ndarray, R: np.ndarray, x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """r^T (R - P)^-1 r of each measurement about the smoothed state at its own time.

    A smoothed state leans on its own measurement, so an honest R leaves residuals of covariance
    R - P (P the smoothed position covariance), and the mean of this over many frames is 3.
    Where R - P is not positive definite (a lone measurement the track rests on), R is used.
    """
    r = z - x[:, :3]
    C = R - P[:, :3, :3]
    ok = np.all(np.linalg.eigvalsh(C) > 1e-3 * np.trace(R, axis1=1, axis2=2)[:, None] / 3, axis=1)
    C = np.where(ok[:, None, None], C, R)
    return np.einsum("ni,ni->n", r, np.linalg.solve(C, r[:, :, None])[:, :, 0])


def supported(
    t_meas: np.ndarray, t_out: np.ndarray, max_gap: float, max_extrapolate: float
) -> np.ndarray:
    """Output times that lie between two measurements closer than max_gap, or near one measurement."""
    t_meas = np.asarray(t_meas, float)
    if len(t_meas) == 0:
        return np.zeros(len(t_out), dtype=bool)
    i = np.searchsorted(t_meas, t_out)
    prev = t_meas[np.clip(i - 1, 0, len(t_meas) - 1)]
    nxt = t_meas[np.clip(i, 0, len(t_meas) - 1)]
    exact = np.isclose(nxt, t_out, rtol=0, atol=1e-9)
    inside = (i > 0) & (i < len(t_meas)) & (nxt - prev <= max_gap)
    near = np.minimum(np.abs(t_out - prev), np.abs(nxt - t_out)) <= max_extrapolate
    return exact | inside | near


def _fit_many(
    t0: np.ndarray, t: np.ndarray, rot: Rotation, weight: np.ndarray, h: float, exclude_self: bool
) -> tuple[Rotation | None, np.ndarray]:
    """Weighted local-linear rotation fits at all times ``t0`` at once.

    Each fit uses the measurements within +-3h of its time, Gaussian weights in
    time times ``weight`` (0 = ignore). Offsets are rotation vectors relative to a reference
    (first the best-weighted measurement, then the first fit: one re-linearisation), so the
    straight-line fit in the tangent space follows steady turns without lag. Returns the fits
    and a mask of times that had any support.
    """
    n, m = len(t), len(t0)
    if n == 0 or m == 0:
        return None, np.zeros(m, dtype=bool)
    # The window: every measurement within 3h of t0 (the kernel is zero beyond), sized by the
    # busiest window rather than the smallest frame step (two interleaved cameras have tiny steps).
    lo = np.searchsorted(t, t0 - 3 * h, side="left")
    hi = np.searchsorted(t, t0 + 3 * h, side="right")
    k = int(min(n, max(4, int((hi - lo).max()) if m else 4)))
    first = np.clip(lo, 0, n - k)
    idx = first[:, None] + np.arange(k)[None, :]  # (m, k)
    dt = t[idx] - t0[:, None]
    w = np.exp(-0.5 * (dt / h) ** 2) * weight[idx] * (np.abs(dt) <= 3 * h)
    if exclude_self:
        w = np.where(np.abs(dt) < 1e-12, 0.0, w)
    ok = w.sum(1) > 0
    w = np.where(ok[:, None], w, 1.0)  # keep the algebra finite; those rows are dropped after
    wsum = w.sum(1, keepdims=True)
    ref = rot[idx[np.arange(m), np.argmax(w, axis=1)]]
    flat = rot[idx.ravel()]
    A_t = np.stack([np.ones_like(dt), dt], axis=2)  # (m, k, 2) design: offset + rate
    AtWA = np.einsum("mki,mk,mkj->mij", A_t, w, A_t)
    # Guard against a window whose weight sits at a single time (rate not identifiable).
    AtWA += np.eye(2)[None] * np.array([1e-12, 1e-9])[None, :, None]
    for _ in range(2):
        ref_rep = Rotation.from_quat(np.repeat(ref.as_quat(), k, axis=0))
        v = (ref_rep.inv() * flat).as_rotvec().reshape(m, k, 3)
        AtWv = np.einsum("mki,mk,mkc->mic", A_t, w, v)
        coef = np.linalg.solve(AtWA, AtWv)  # (m, 2, 3)
        offset = np.where(
            (w > 0).sum(1)[:, None] >= 3, coef[:, 0], (w[:, :, None] * v).sum(1) / wsum
        )
        ref = ref * Rotation.from_rotvec(offset)
    return ref, ok


def smooth_rotations(
    t_meas: np.ndarray,
    rot: Rotation,
    var: np.ndarray,
    t_out: np.ndarray,
    settings: SmootherSettings | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed rotation matrices (M, 3, 3) at ``t_out`` (NaN where no measurement is near), and
    the (N,) mask of accepted measurements.

    ``var`` (N,) is each measurement's rotation variance (rad^2), used as an inverse weight.
    A measurement farther than ``rot_gate_deg`` from the fit of its neighbours is rejected.
    """
    s = settings or SmootherSettings()
    t_meas = np.asarray(t_meas, float)
    t_out = np.asarray(t_out, float)
    h = s.rot_bandwidth_s
    inv_var = 1.0 / np.maximum(np.asarray(var, float), np.radians(0.01) ** 2)
    accepted = np.ones(len(t_meas), dtype=bool)
    out = np.full((len(t_out), 3, 3), np.nan)
    if len(t_meas) == 0:
        return out, accepted
    gate = np.radians(s.rot_gate_deg)
    for _ in range(2):  # a second round once gross outliers no longer pull the fits
        fits, ok = _fit_many(t_meas, t_meas, rot, inv_var * accepted, h, exclude_self=True)
        if fits is None:
            break
        angle = (fits.inv() * rot).magnitude()
        accepted = ~ok | (angle <= gate)
    fits, ok = _fit_many(t_out, t_meas, rot, inv_var * accepted, h, exclude_self=False)
    if fits is not None:
        ok &= _fit_holds(t_meas[accepted], t_out, h, s.max_extrapolate_s)
        out[ok] = fits.as_matrix()[ok]
    return out, accepted


def _fit_holds(t_used: np.ndarray, t_out: np.ndarray, h: float, reach: float) -> np.ndarray:
    """Where a local-linear rotation fit can be trusted: between measurements on both sides
    within the kernel's 3h, or within ``reach`` of one. Past a measurement on one side only, the
    fit runs on the rate of the few measurements at the kernel's edge: 0.2 s beyond the last
    pose of a fast turn that was tens of degrees off. Such rows are left to the caller (the
    smoother blends the rotations on either side of a short gap)."""
    n = len(t_used)
    if n == 0:
        return np.zeros(len(t_out), dtype=bool)
    i = np.searchsorted(t_used, t_out)
    left = np.where(i > 0, t_out - t_used[np.clip(i - 1, 0, n - 1)], np.inf)
    right = np.where(i < n, t_used[np.clip(i, 0, n - 1)] - t_out, np.inf)
    return ((left <= 3 * h) & (right <= 3 * h)) | (np.minimum(left, right) <= reach)
