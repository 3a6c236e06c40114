"""The self-calibration's analytic Jacobian against forward differences of its own projection."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.priors import Priors
from annotator.core.refine import RefineSettings, build_problem
from annotator.core.refine.jacobian import (
    StaticSlots,
    analytic_jacobian,
    left_jacobian,
    numeric_jacobian,
)
from annotator.core.refine.lm import _LM, _robust_weights
from annotator.core.refine.model import (
    BIAS,
    CLOCK,
    DIST,
    INTR,
    READOUT,
    RIG,
    SCALE,
    _Layout,
    _Model,
)
from tests.annotator.core.test_refine import _moving_keyframes

BLOCKS = (RIG, INTR, DIST, READOUT, BIAS, CLOCK, SCALE)


def _model(lens: str) -> tuple[_Model, np.ndarray]:
    """A turning, moving walk (rolling shutter on, 15 ms readout) with every block free, the second
    camera's lens ``lens``, one marker held fixed, and parameters away from their start."""
    survey, cams, keyframes, length = _moving_keyframes(0.004)
    cams = [dataclasses.replace(c, readout_s=0.015, corner_bias_px=0.2) for c in cams]
    if lens == "fisheye":
        cams[1] = dataclasses.replace(
            cams[1], model="fisheye", dist=np.array([0.02, -0.01, 0.004, -0.001])
        )
    priors = Priors(survey_sigma_m=0.015, survey_sigma_deg=1.0, readout_sigma_s=1e-3)
    prob, _ = build_problem(survey, length, cams, keyframes, priors, length_sigma_rel=0.01)
    free = np.zeros(len(prob.markers), bool)
    free[np.unique(prob.obs.marker)] = True
    free[int(prob.obs.marker[0])] = False  # a marker that is not a parameter has no columns
    layout = _Layout(len(prob.R_k), len(prob.markers), len(cams), 5, free, BLOCKS)
    rng = np.random.default_rng(7)
    x = np.zeros(layout.n_pose + layout.n_static)
    x[: layout.n_pose] = 0.05 * rng.standard_normal(layout.n_pose)  # turns of ~5 deg, 5 cm
    x[layout.n_pose :] = 2e-3 * rng.standard_normal(layout.n_static)
    return _Model(prob, layout), x


@pytest.mark.parametrize("lens", ["radtan", "fisheye"])
def test_analytic_jacobian_matches_forward_differences(lens: str) -> None:
    model, x = _model(lens)
    Jp, Js = analytic_jacobian(model, x)
    Np, Ns = numeric_jacobian(model, x)
    # Forward differences are good to ~1e-6 of the largest derivative (their truncation error).
    assert np.abs(Jp - Np).max() < 1e-5 * np.abs(Np).max()
    at = 0
    for name, (_off, _n, size) in model.L.static_slices().items():
        cols = slice(at, at + size)
        at += size
        scale = np.abs(Ns[:, :, cols]).max()
        assert scale > 0, name  # every block moves some corner
        assert np.abs(Js[:, :, cols] - Ns[:, :, cols]).max() < 1e-5 * scale, name
    # The marker that is not a parameter moves nothing.
    held = model.p.obs.marker == model.p.obs.marker[0]
    assert not Js[held][:, :, :6].any()


def test_normal_equations_sum_each_corners_columns_where_they_belong() -> None:
    """The grouped sums (corners of a marker and camera share their columns) equal J^T W J and
    J^T W r of the whole Jacobian written out."""
    model, x = _model("radtan")
    L, o = model.L, model.p.obs
    lm = _LM(model.p, L, RefineSettings(clock_sigma_s=0.01))
    uv = model.predict(x)[0]
    Hpp, gp, Hps, Hss, gs = lm.normal_equations(x, uv)
    Jp, Js = analytic_jacobian(model, x)
    N = len(o.keyframe)
    J = np.zeros((N, 2, L.n_pose + L.n_static))
    for n in range(N):
        J[n, :, 6 * o.keyframe[n] : 6 * o.keyframe[n] + 6] = Jp[n]
        J[n][:, L.n_pose + StaticSlots.of(model).columns[n]] = Js[n]
    J = J.reshape(2 * N, -1)
    r = (uv - o.uv) / lm.sigma_px
    w = np.repeat(o.weight * _robust_weights(r, lm.s.huber_px / lm.sigma_px), 2)
    H = J.T @ (w[:, None] * J)
    g = J.T @ (w * (uv - o.uv).ravel())
    xs = x[L.n_pose :]
    prior_H = np.diag(lm.prec) + lm.A.T @ lm.A
    assert Hss == pytest.approx(H[L.n_pose :, L.n_pose :] + prior_H, rel=1e-9, abs=1e-6)
    assert Hps == pytest.approx(H[: L.n_pose, L.n_pose :], rel=1e-9, abs=1e-6)
    assert gs == pytest.approx(g[L.n_pose :] + prior_H @ xs, rel=1e-9, abs=1e-6)
    for k in range(L.K):
        assert Hpp[k] == pytest.approx(H[6 * k : 6 * k + 6, 6 * k : 6 * k + 6], rel=1e-9)
    assert gp.ravel() == pytest.approx(g[: L.n_pose], rel=1e-9, abs=1e-6)


def test_left_jacobian_turns_a_rotation_vector_change_into_a_left_turn() -> None:
    rng = np.random.default_rng(3)
    r = rng.standard_normal((5, 3))
    r[0] = 0.0  # the identity, where J_l = I
    d = 1e-7 * rng.standard_normal((5, 3))
    J = left_jacobian(r)
    for k in range(5):
        lhs = Rotation.from_rotvec(r[k] + d[k]) * Rotation.from_rotvec(r[k]).inv()
        assert lhs.as_rotvec() == pytest.approx(J[k] @ d[k], rel=1e-5, abs=1e-13)
    assert J[0] == pytest.approx(np.eye(3))
