"""The self-calibration's solve on a built problem: the rounds (fit, drop contradicted survey
priors, gate), and the solution with its covariance. The least squares are in refine/lm.py, the
gate in refine/gate.py, the covariance record in refine/covariance.py."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.refine.covariance import (
    _correlation_stretch,
    _covariance,
    _joint_index,
    _rig_gauge,
)
from annotator.core.refine.gate import _gate, _mahalanobis, _rigid_rows, marker_floors
from annotator.core.refine.lm import _LM
from annotator.core.refine.model import (
    BIAS,
    CLOCK,
    DIST,
    INTR,
    READOUT,
    RIG,
    SCALE,
    CameraParams,
    Observations,
    Problem,
    RefineSettings,
    Solution,
    _Layout,
    supported_lens,
)

__all__ = ["marker_floors", "solve"]

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)

# --- entry point on a built problem -------------------------------------------------------------


def _rms_per_camera(
    uv: np.ndarray, obs: Observations, cameras: list[CameraParams], k: float
) -> dict[str, float]:
    out = {}
    n = np.linalg.norm(uv - obs.uv, axis=1)
    for i, c in enumerate(cameras):
        sel = obs.camera == i
        # RMS of the inliers (a few gross outliers would hide the calibration's effect).
        v = n[sel & (n < 10 * k)]
        out[c.name] = float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")
    return out


def solve(
    prob: Problem,
    settings: RefineSettings | None = None,
    starts: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Solution:
    """`_solve` on one BLAS thread: its dense systems are a few hundred wide, where OpenBLAS's
    threads gain little alone and, on a busy machine, spin against each other and other work
    (2.6x slower solves measured with two threads on two loaded cores; bench/refine_timing.py)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _solve(prob, settings, starts)


def _solve(
    prob: Problem,
    settings: RefineSettings | None = None,
    starts: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Solution:
    """Refine the problem's parameters; the marker, rig and lens values in the result are final.

    ``starts``: start poses of markers that differ from their prior mean (see build_problem).
    """
    s = settings or RefineSettings()
    t0 = time.perf_counter()
    nd = max(len(c.dist) for c in prob.cameras)
    nd = 5 if any(c.model == "radtan" for c in prob.cameras) and nd >= 5 else nd
    seen = np.zeros(len(prob.markers), bool)
    seen[np.unique(prob.obs.marker)] = True
    blocks: tuple[str, ...] = (RIG, INTR, DIST, READOUT, BIAS) if s.mode == "all" else (BIAS,)
    if s.mode == "all" and not all(supported_lens(c.model, c.dist) for c in prob.cameras):
        log.warning("refine: a lens model with more than 5 coefficients: distortion held fixed")
        blocks = (RIG, INTR, READOUT, BIAS)
    if s.mode == "all" and len(prob.cameras) > 1 and s.clock_sigma_s > 0:
        blocks = (*blocks, CLOCK)
    if s.mode == "all" and prob.length_sigma_rel > 0:
        blocks = (*blocks, SCALE)
    layout = _Layout(len(prob.R_k), len(prob.markers), len(prob.cameras), nd, seen, blocks)
    lm = _LM(prob, layout, s)
    x = np.zeros(layout.n_pose + layout.n_static)
    # "Before": the keyframe poses that fit the given map, rig and lenses best.
    lm.prec[:] = 1e12
    x, _ = lm.solve(x, 5)
    lm._priors()
    _, uv_before = lm.cost(x)
    for mid, (R, centre) in (starts or {}).items():
        m = prob.markers.index(mid)
        b = layout.n_pose + layout.static_slices()["marker"][0] + 6 * m
        x[b : b + 3] = Rotation.from_matrix(R @ prob.R_m[m].T).as_rotvec()
        x[b + 3 : b + 6] = centre - prob.t_m[m]
    rms_before = _rms_per_camera(uv_before, prob.obs, prob.cameras, s.huber_px)
    # 1: a first solve with a conservative noise level; 2: markers whose survey the data contradict
    # lose their prior ("moved since the survey?"), the noise is re-estimated, solve again.
    x, it1 = lm.solve(x, s.iterations)
    sig_m = prob.marker_sigma
    _, uv = lm.cost(x)
    res = np.linalg.norm(uv - prob.obs.uv, axis=1)
    lm.sigma_px = max(s.min_sigma_px, 1.4826 * float(np.median(res)) / math.sqrt(2 * math.log(2)))
    u = lm.model.unpack(x)
    floor = marker_floors(prob, s)
    rot_dev = np.linalg.norm(u["marker"][:, :3], axis=1) / np.where(
        np.isfinite(sig_m[:, 0]), sig_m[:, 0], np.inf
    )
    pos_dev = np.array(
        [
            _mahalanobis(u["marker"][m, 3:], sig_m[m, 1] ** 2 * np.eye(3) + floor[m, 3:, 3:])
            if np.isfinite(sig_m[m, 1])
            else 0.0
            for m in range(layout.M)
        ]
    )
    dev = np.maximum(rot_dev / math.sqrt(3), pos_dev)  # per-axis sigmas over 3 axes
    lm.skip = seen & (dev > s.moved_sigma)
    lm._priors()
    x, it2 = lm.solve(x, s.iterations)
    _, uv = lm.cost(x)
    Hpp, _, Hps, Hss, _ = lm.normal_equations(x, uv)
    cov = lm.static_covariance(Hpp, Hps, Hss)
    post = cov  # the posterior of the final solve, before what the gate holds back
    has_prior = np.isfinite(prob.marker_sigma[:, 1]) & ~lm.skip
    prior_sd = 1 / np.sqrt(np.maximum(lm.prec, 1e-30))
    unseen, within_noise = _gate(x, cov, layout, s, has_prior, prior_sd)
    gated = sorted(unseen + within_noise)
    # What the data say of the printed size, before the gate holds it at the stated length.
    scale_found = float(lm.model.static_values(x)["scale"][0])
    held = np.zeros(layout.n_static)  # the corrections the data asked for and that were not applied
    if gated:
        g = layout.n_pose + np.array(gated)
        before = x[g].copy()
        # Hold those at the prior and let the rest settle without them. A held camera block is
        # pinned; held surveyed markers keep their surveyed shape but move together, as one rigid
        # body, with the rest of the map: pinning them would make the few markers that pass the
        # gate the map's datum (their mean survey error, not that of all the surveyed markers).
        x[g] = 0.0
        mb, mn, _ = layout.static_slices()["marker"]
        in_map = (np.array(gated) >= mb) & (np.array(gated) < mb + 6 * mn)
        lm.prec[np.array(gated)[~in_map]] = 1e12
        held_markers = sorted({(i - mb) // 6 for i in np.array(gated)[in_map]})
        log.debug(
            "refine: markers held at their survey: %s", [prob.markers[m] for m in held_markers]
        )
        lm.A = np.vstack([lm.A, _rigid_rows(prob, layout, held_markers)])
        x, it3 = lm.solve(x, s.iterations)
        it2 += it3
        lm._priors()
        _, uv = lm.cost(x)
        Hpp, _, Hps, Hss, _ = lm.normal_equations(x, uv)
        cov = post = lm.static_covariance(Hpp, Hps, Hss)
        # A held block is not at its posterior mean but at its prior: its error is the posterior
        # spread plus the correction it was denied (mean square error = P + d d^T). Without this the
        # held blocks claim the data's precision while keeping the survey's error (over-confident).
        held[gated] = before - x[g]
        # ... except what the capture did not show: the data's "correction" there is mostly the
        # noise of a weak estimate (a principal point trades with the rig's turn, and the
        # posterior keeps that trade in its cross terms, which a d d^T on the diagonal ignores).
        held[unseen] = 0.0
        cov = cov + np.outer(held, held)
    _, uv = lm.cost(x)
    v = lm.model.static_values(x)
    u = lm.model.unpack(x)
    rejected = [prob.markers[m] for m in np.flatnonzero(lm.skip)]
    gated_set = set(gated)
    slices = layout.static_slices()
    determined = {
        cam.name: {
            # Determined: the capture set at least one of the block's components.
            name: not all(i in gated_set for i in range(off + c * size, off + (c + 1) * size))
            for name, (off, _n, size) in slices.items()
            if name not in ("marker", SCALE)
        }
        for c, cam in enumerate(prob.cameras)
    }
    clock_sigma: dict[str, float] = {}
    if CLOCK in slices:
        o = slices[CLOCK][0]
        clock_sigma = {
            cam.name: math.sqrt(max(float(post[o + c, o + c]), 0.0))
            for c, cam in enumerate(prob.cameras)
        }
    scale_sigma, scale_determined = float("nan"), False
    if SCALE in slices:
        i = slices[SCALE][0]
        scale_sigma = math.sqrt(max(float(post[i, i]), 0.0))
        scale_determined = i not in gated
        log.info(
            "refine: markers printed %.4f x the stated length (+- %.4f)%s",
            scale_found,
            scale_sigma,
            "" if scale_determined else ": within noise of 1, the stated length kept",
        )
    moved = []
    mo = layout.n_pose + layout.static_slices()["marker"][0]
    for m in range(layout.M):
        if not np.isfinite(sig_m[m, 1]) or not seen[m]:
            continue
        # The survey and the video disagree by more than both together allow: the survey's sigma,
        # the video's (the normal matrix with the robust weights) and the errors common to every
        # frame of the marker that no number of frames averages away (the floors).
        b = mo + 6 * m - layout.n_pose
        video = cov[b : b + 6, b : b + 6] + floor[m]
        d = max(
            _mahalanobis(u["marker"][m, 3:], sig_m[m, 1] ** 2 * np.eye(3) + video[3:, 3:]),
            _mahalanobis(u["marker"][m, :3], sig_m[m, 0] ** 2 * np.eye(3) + video[:3, :3]),
        )
        log.debug("refine: marker %d discrepancy %.2f sigma", prob.markers[m], d)
        if d > s.flag_sigma and (lm.skip[m] or d > s.moved_sigma / 2):
            moved.append(prob.markers[m])
    cams = []
    for c, cam in enumerate(prob.cameras):
        K = cam.K.copy()
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = v["K"][c]
        dist = np.asarray(cam.dist, float).copy()
        dist[: min(len(dist), nd)] = v["dist"][c][: min(len(dist), nd)]
        cams.append(
            CameraParams(
                cam.name,
                v["R_bc"][c],
                v["t_bc"][c],
                K,
                dist,
                cam.model,
                float(max(v["readout"][c], 0.0)),
                cam.height,
                float(v["bias"][c]),
                cam.clock_s + float(v["clock"][c]),
            )
        )
    # A marker's stated uncertainty includes what its frames cannot average away (the floors): the
    # normal matrix alone, frames taken as independent, claims ~0.7 cm for far markers whose depth
    # is off by 5-9 cm on the field renders.
    # What the trajectory inherits (uncertainty.py): the joint covariance with the cross-block
    # terms (the map's datum is common to every marker), plus what the gate held back and the rig's
    # gauge; its data part is widened by the keyframes' correlation time only when asked
    # (RefineSettings.keyframe_correlation).
    # The markers' floors stay out of the marker blocks: they are errors common to all of a marker's
    # frames, and the tracker sees the same frames (docs/annotator.md, "What sigma_m means"). When
    # the walk maps skipped markers, the surveyed ones' floors enter through their priors
    # (RefineSettings.floors_in_record): the mapped markers inherit them.
    stretch = _correlation_stretch(prob, uv, lm.sigma_px) if s.keyframe_correlation else 1.0
    if s.floors_in_record and np.any(seen & ~np.isfinite(prob.marker_sigma[:, 1])):
        lm._priors(np.where(seen[:, None, None], floor, 0.0))
        Hpp, _, Hps, Hss, _ = lm.normal_equations(x, uv)
    joint = (
        lm.static_covariance(Hpp, Hps, Hss, stretch)
        + (cov - post)
        + _rig_gauge(layout, prob, v["t_bc"])
    )
    mb = layout.static_slices()["marker"][0]
    for k in (int(i) for i in np.flatnonzero(seen)):
        cov[mb + 6 * k : mb + 6 * k + 6, mb + 6 * k : mb + 6 * k + 6] += floor[k]
    covariance, marker_sigma = _covariance(cov, layout, prob, lm)
    covariance = replace(covariance, joint=joint, joint_index=_joint_index(layout, prob))
    return Solution(
        v["R_m"],
        v["t_m"],
        marker_sigma,
        moved,
        cams,
        v["R_k"],
        v["p_k"],
        covariance,
        rms_before,
        _rms_per_camera(uv, prob.obs, prob.cameras, s.huber_px),
        lm.sigma_px,
        it1 + it2,
        time.perf_counter() - t0,
        rejected,
        scale_found,
        scale_sigma,
        scale_determined,
        determined,
        clock_sigma,
    )
