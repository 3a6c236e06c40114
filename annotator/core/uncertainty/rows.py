"""Each trajectory row's parameter variance and smear: the frames around it, their propagated
covariance averaged over a short kernel, and the block scales checked against the residuals."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from concurrent.futures import Executor
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import nnls

from annotator.core.experiment import Experiment
from annotator.core.parallel import map_in_runs
from annotator.core.priors import ParameterCovariance
from annotator.core.uncertainty.blur import exposures, fill_nearest, kernel_average
from annotator.core.uncertainty.propagation import (
    JacobianCache,
    frame_jacobians,
    parameter_covariance,
    propagate,
)
from annotator.core.uncertainty.records import (
    BLOCKS,
    RowUncertainty,
    UncertaintySettings,
    VideoFrames,
)
from annotator.core.uncertainty.views import FrameView, trajectory_twist, views_at
from annotator.vision.geometry import MarkerRoom

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


def _scales(
    var: np.ndarray,
    q: np.ndarray,
    e: np.ndarray,
    dof: np.ndarray,
    settings: UncertaintySettings,
) -> dict[str, float]:
    """Each block's prior scale from the residual energy of the whole capture.

    Regression over the rows: e = c dof + sum_b s_b^2 q_b (e: energy beyond the within-marker
    noise; c: corner noise the within-marker estimate misses, correlated over a square). A block
    is shrunk to the upper end of its 2-sigma range when that is below 1 (the capture rules its
    prior out); a block the capture cannot check keeps its prior. Then, if the residuals still
    hold significantly more than the (shrunk) priors predict, every block is inflated by the
    lower end of that common factor's 2-sigma range (the priors were optimistic, or something
    unmodelled moves the corners).
    Priors only: a posterior (refinement) was fitted to these same residuals, see row_uncertainty.
    """
    out = {b: 1.0 for b in BLOCKS}
    use = np.isfinite(e) & (dof > 2) & np.isfinite(q).all(1)
    if not settings.scale_priors or use.sum() < 20:
        return out
    wt = 1.0 / np.maximum(dof[use], 1.0)  # rows differ a lot in corner count

    def fit(cols: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        X = np.column_stack(cols) * wt[:, None]
        y = e[use] * wt
        coef, _ = nnls(X, y)
        res = y - X @ coef
        s2 = float(res @ res) / max(len(y) - X.shape[1], 1)
        return coef, np.sqrt(np.maximum(np.diag(s2 * np.linalg.pinv(X.T @ X)), 0.0))

    ks = [k for k in range(4) if q[use, k].sum() > 0]
    coef, se = fit([dof[use]] + [q[use, k] for k in ks])
    for c, k in enumerate(ks, 1):
        upper = coef[c] + 2.0 * se[c]
        out[BLOCKS[k]] = float(np.clip(math.sqrt(max(upper, 0.0)), settings.min_scale, 1.0))
    shrunk = q[use] @ np.array([out[b] ** 2 for b in BLOCKS])
    coef2, se2 = fit([dof[use], shrunk])
    lower = coef2[1] - 2.0 * se2[1]
    inflate = float(np.clip(math.sqrt(max(lower, 1.0)), 1.0, settings.max_scale))
    out = {b: v * inflate for b, v in out.items()}
    log.debug(
        "scale^2 regression: %s; common factor^2 %.3g +- %.2g",
        ", ".join(f"{BLOCKS[k]} {coef[c]:.3g} +- {se[c]:.2g}" for c, k in enumerate(ks, 1)),
        coef2[1],
        se2[1],
    )
    log.info(
        "prior scales from the residuals: %s", ", ".join(f"{b} {v:.2f}" for b, v in out.items())
    )
    return out


def _propagate_rows(
    shared: tuple[MarkerRoom, ParameterCovariance, float, UncertaintySettings, dict[str, float]],
    views: Sequence[list[FrameView]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row of ``views``: the blocks' variance, their predicted residual energy, the residual
    energy, its degrees of freedom, and the smear (px); NaN where a row has no Jacobian."""
    room, pc, readout_sigma, s, exposure = shared
    n = len(views)
    var = np.full((n, 4), np.nan)
    q = np.full((n, 4), np.nan)
    e = np.full(n, np.nan)
    dof = np.full(n, np.nan)
    smear = np.full(n, np.nan)
    cache = JacobianCache()
    for k in range(n):
        if not views[k]:
            continue
        jac = frame_jacobians(views[k], room, pc, readout_sigma, s, cache)
        if jac is None:
            continue
        out = propagate(jac)
        if out is None:
            continue
        var[k], q[k], e[k], dof[k] = out
        smear[k] = float(np.median(jac.image_speed)) * max(exposure[v.camera] for v in views[k])
    return var, q, e, dof, smear


def row_uncertainty(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_out: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    params: ParameterCovariance | None = None,
    settings: UncertaintySettings | None = None,
    pool: Executor | None = None,
    jobs: int = 1,
) -> RowUncertainty:
    """Parameter, blur and smear figures of every trajectory row (pose of the smoothed trajectory).

    ``params`` None: the experiment's priors, checked against the capture's residuals (see
    ``_scales``). Given: a posterior (refinement), used as it is. Its parameters were fitted to these
    same residuals, so what energy they still hold is not the parameters' error; scaling it up by
    that energy (as was done) made sigma_m cautious by 1.2-1.9x on 10-30 s field walks (rows within
    2.8 sigma_m pooled over 20 / 20 / 14 seeds: 99.9 / 100 / 100 %, now 95.2 / 95.6 / 99.8 %).

    ``frames`` are the pipeline's CameraFrames (camera, t, detections, frame_interval). With a
    ``pool``, the rows' propagation runs in runs of neighbouring rows in its processes
    (``annotator.core.parallel.map_in_runs``); the figures are the same as without.
    """
    s = settings or UncertaintySettings()
    pc = parameter_covariance(exp, params)
    readout_sigma = (
        exp.priors.readout_sigma_s
    )  # shared by the cameras unless the record has its own
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    omega, vel = trajectory_twist(t_out, pos, R)
    views = views_at(frames, exp, t_out, pos, R, omega, vel)
    exposure = exposures(frames, exp, s)
    # Neighbouring rows share views, which each run works out once.
    parts = map_in_runs(_propagate_rows, (room, pc, readout_sigma, s, exposure), views, pool, jobs)
    var, q, e, dof, smear = (np.concatenate(col) for col in zip(*parts, strict=True))
    scales = _scales(var, q, e, dof, s) if params is None else {b: 1.0 for b in BLOCKS}
    var = var * np.array([scales[b] ** 2 for b in BLOCKS])[None, :]
    if log.isEnabledFor(logging.DEBUG) and np.isfinite(var).any():
        med = np.sqrt(np.nanmedian(var, axis=0))
        log.debug(
            "median per-axis sigma by block (mm): %s",
            ", ".join(f"{b} {1e3 * v:.2f}" for b, v in zip(BLOCKS, med, strict=True)),
        )
    var = kernel_average(t_out, var, s.param_window_s)
    speed = np.linalg.norm(vel, axis=1)
    exp_row = max(exposure.values()) if exposure else 0.0
    # Uniform over the exposure (sqrt(12)), along the motion only (a third of it per axis).
    blur = speed * exp_row / math.sqrt(12.0 * 3.0)
    valid = np.isfinite(pos).all(1)
    # A posed row whose own frames gave no Jacobian (e.g. bridged gap) takes its neighbours' values.
    var[valid & ~np.isfinite(var).all(1)] = np.nan
    var = fill_nearest(t_out, var, valid)
    var[~valid] = np.nan
    blur[~valid] = np.nan
    return RowUncertainty(var, blur, smear, scales)
