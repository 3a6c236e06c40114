"""The self-calibration's gate: which corrections are within noise of their prior (and are
held there), the markers' floors, and the rows that move held markers as one rigid body."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from annotator.core.refine.model import (
    CLOCK,
    READOUT,
    RIG,
    SCALE,
    Problem,
    RefineSettings,
    _Layout,
)

log = logging.getLogger(__name__)


def _rigid_basis(offsets: np.ndarray) -> np.ndarray:
    """(6k, 6): how k (rotation, position) deltas follow one small rigid motion (a rotation w
    about a centre, then a shift t) of points at ``offsets`` (k, 3) from that centre: each
    rotation delta is w and each position delta t + w x d = t - [d]x w."""
    basis = np.zeros((6 * len(offsets), 6))
    for k, d in enumerate(offsets):
        basis[6 * k : 6 * k + 3, :3] = np.eye(3)
        basis[6 * k + 3 : 6 * k + 6, :3] = -np.array(
            [[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]]
        )
        basis[6 * k + 3 : 6 * k + 6, 3:] = np.eye(3)
    return basis


def _rigid_rows(prob: Problem, layout: _Layout, markers: Sequence[int]) -> np.ndarray:
    """Rows A (cost |A x|^2 / 2, stiff) that hold the deltas of ``markers`` to one common small
    rigid motion (a world rotation w about their centre and a shift t): per marker the rotation
    delta is w and the position delta t + w x (p - centre). Fewer than two markers: no rows."""
    if len(markers) < 2:
        return np.zeros((0, layout.n_static))
    p = prob.t_m[list(markers)]
    basis = _rigid_basis(p - p.mean(axis=0))
    q, _ = np.linalg.qr(basis)
    mb = layout.static_slices()["marker"][0]
    cols = (mb + 6 * np.asarray(markers)[:, None] + np.arange(6)).ravel()
    rows = np.zeros((len(cols), layout.n_static))
    rows[:, cols] = np.eye(len(cols)) - q @ q.T
    return rows * 1e5


def _mahalanobis(d: np.ndarray, cov: np.ndarray) -> float:
    """sqrt(d^T cov^-1 d / dof): the discrepancy in sigmas per degree of freedom."""
    try:
        return math.sqrt(max(float(d @ np.linalg.solve(cov, d)), 0.0) / len(d))
    except np.linalg.LinAlgError:
        return 0.0


def marker_floors(prob: Problem, s: RefineSettings) -> np.ndarray:
    """(M, 6, 6) covariance of the errors common to all of a marker's frames (rotation, position).

    ``marker_floor_deg`` / ``marker_floor_m`` on every axis, plus along the marker's mean line of
    sight (from the keyframes that see it) the depth error of a ``marker_size_floor_px`` error in
    its size in the image: depth x size error / side. A small far marker seen from one direction has
    a depth the data know far less well than their frame count suggests.

    Likewise its turn out of its own plane: the image gives it only through the square's
    foreshortening (side x sine of the view angle) and perspective (the near edge longer by
    side x length / depth), so the same size error is a turn of size error / (side x that). A far
    marker seen almost face-on has a slant the video hardly knows (the field renders: 4-6 deg off
    at 11 m while the joint solve claimed ~1 deg).
    """
    o = prob.obs
    out = np.zeros((len(prob.markers), 6, 6))
    out[:, :3, :3] = math.radians(s.marker_floor_deg) ** 2 * np.eye(3)
    out[:, 3:, 3:] = s.marker_floor_m**2 * np.eye(3)
    if s.marker_size_floor_px <= 0 or not len(o.marker):
        return out
    quad = o.uv.reshape(-1, 4, 2)
    side = np.linalg.norm(quad - np.roll(quad, 1, axis=1), axis=2).mean(axis=1)  # per detection, px
    mk, kf = o.marker[::4], o.keyframe[::4]
    for m in np.unique(mk):
        sel = mk == m
        ray = prob.t_m[m] - prob.p_k[kf[sel]]
        depth = np.linalg.norm(ray, axis=1)
        los = np.mean(ray / np.maximum(depth, 1e-9)[:, None], axis=0)
        los /= max(float(np.linalg.norm(los)), 1e-9)
        sd = float(
            np.median(depth) * s.marker_size_floor_px / max(float(np.median(side[sel])), 1.0)
        )
        out[m, 3:, 3:] += sd * sd * np.outer(los, los)
        # The view direction in the marker's frame: x, y in its plane, z out of its face.
        view = -(ray / np.maximum(depth, 1e-9)[:, None]) @ prob.R_m[m]
        persp = prob.length / np.maximum(depth, 1e-9) * view[:, 2]
        for axis, across in ((0, 1), (1, 0)):  # a turn about the marker's x shows along its y
            gain = side[sel] * np.hypot(view[:, across], persp)  # px of shape per radian
            rms = float(np.sqrt(np.mean(gain**2)))
            var = min((s.marker_size_floor_px / max(rms, 1e-9)) ** 2, 1.0)
            ax = prob.R_m[m][:, axis]
            out[m, :3, :3] += var * np.outer(ax, ax)
    return out


def _gate(
    x: np.ndarray,
    cov: np.ndarray,
    layout: _Layout,
    s: RefineSettings,
    has_prior: np.ndarray,
    prior_sd: np.ndarray,
) -> tuple[list[int], list[int]]:
    """Static indices held at their prior: (what the capture did not show, the corrections of
    the significance-gated blocks and markers that are within noise).

    - Each component of a camera's rig pose, lens, readout, clock or corner bias (x, yaw, fx, cx,
      k1, ...) the capture did not show: its posterior sigma at least ``observable_ratio`` of its
      prior's (``prior_sd``). The principal point of a level walk is one: it trades with the
      rig's turn, and its correction then follows the corners' errors (2-4 px off on a push,
      measured); so is the rig's height or pitch on a level push (the corrections it took there
      moved the labels 1.04 -> 1.11 cm median on the push-real cell). The rig's mean over the
      cameras is pinned besides (the gauge).
    - The blocks in ``gate_blocks`` whose correction is within ``gate_sigma`` posterior sigmas:
      the rig and the cameras' clocks as a whole (gauged to the cameras' mean, one camera cannot
      be judged alone), the cameras' readouts together (any combination beyond the gate), the
      other blocks per camera, the markers' printed size.
    - Surveyed markers whose correction's Mahalanobis distance per degree of freedom (against the
      posterior widened by the floors) is below ``marker_gate_sigma``.
    """
    out: list[int] = []
    unseen_all: list[int] = []
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-30))
    xs = x[layout.n_pose :]
    for name, (off, n, size) in layout.static_slices().items():
        if name == "marker":
            if s.marker_gate_sigma > 0:
                out.extend(_held_markers(xs, cov, off, n, layout, s, has_prior))
            continue
        # The printed size is one scale every marker shows: judged by the significance gate.
        if name != SCALE and s.observable_ratio > 0:
            ratio = sd[off : off + n * size] / np.maximum(prior_sd[off : off + n * size], 1e-30)
            for c in range(n):
                unseen = np.flatnonzero(ratio[c * size : (c + 1) * size] >= s.observable_ratio)
                if len(unseen):
                    log.info(
                        "refine: %s of camera %d: components %s not shown by the capture; "
                        "priors kept",
                        name,
                        c,
                        unseen.tolist(),
                    )
                unseen_all.extend(off + c * size + int(k) for k in unseen)
        if s.gate_sigma > 0 and name in s.gate_blocks:
            out.extend(_insignificant(name, xs, cov, sd, off, n, size, s.gate_sigma))
    unseen_set = set(unseen_all)
    return sorted(unseen_set), sorted(set(out) - unseen_set)


def _held_markers(
    xs: np.ndarray,
    cov: np.ndarray,
    off: int,
    n: int,
    layout: _Layout,
    s: RefineSettings,
    has_prior: np.ndarray,
) -> list[int]:
    """The surveyed markers' indices whose correction is within ``marker_gate_sigma``."""
    out: list[int] = []
    floor = np.diag([math.radians(s.marker_floor_deg) ** 2] * 3 + [s.marker_floor_m**2] * 3)
    for m in range(n):
        i = off + 6 * m
        if not (layout.free_markers[m] and has_prior[m]):
            continue
        if _mahalanobis(xs[i : i + 6], cov[i : i + 6, i : i + 6] + floor) < s.marker_gate_sigma:
            out.extend(range(i, i + 6))
    return out


def _insignificant(
    name: str,
    xs: np.ndarray,
    cov: np.ndarray,
    sd: np.ndarray,
    off: int,
    n: int,
    size: int,
    gate: float,
) -> list[int]:
    """The indices of block ``name`` whose correction is within ``gate`` posterior sigmas."""
    if name in (RIG, CLOCK):  # gauged to the cameras' mean: judged as a whole
        z = np.abs(xs[off : off + n * size]) / sd[off : off + n * size]
        if z.max() < gate:
            log.info(
                "refine: %s change not significant (max %.1f sigma); %s kept",
                "rig" if name == RIG else "cameras' clock",
                z.max(),
                "the measured rig" if name == RIG else "the sync's offsets",
            )
            return list(range(off, off + n * size))
        return []
    if name == READOUT and n > 1:
        # The cameras' readouts together: with their clocks free, a readout trades against its
        # camera's clock where the markers fill few rows (a level cart), while their common
        # part, the walk's rolling shutter, stays sharp. Kept at the priors only if no
        # combination of them moved beyond the gate (the largest z in any direction).
        idx = np.arange(off, off + n * size)
        d = xs[idx]
        try:
            z_max = math.sqrt(max(float(d @ np.linalg.solve(cov[np.ix_(idx, idx)], d)), 0.0))
        except np.linalg.LinAlgError:
            z_max = float(np.max(np.abs(d) / sd[idx]))
        if z_max < gate:
            log.info("refine: readouts not significant (%.1f sigma); priors kept", z_max)
            return idx.tolist()
        return []
    out: list[int] = []
    for c in range(n):
        i = off + c * size
        z = np.abs(xs[i : i + size]) / sd[i : i + size]
        if z.max() < gate:
            log.info(
                "refine: %s%s not significant (max %.1f sigma); prior kept",
                name,
                "" if name == SCALE else f" of camera {c}",
                z.max(),
            )
            out.extend(range(i, i + size))
    return out
