"""The self-calibration's Jacobian: every corner's pixels differentiated by the chain rule through
the projection's stages (``_Model.forward``), and the forward-difference one it replaced, kept as
the reference the tests hold it to.

Rotations are rotation vectors r applied on the left of their start (R = exp(r) R0), so a change
d of r turns R by the left Jacobian of SO(3): exp(r + d) ~ exp(J_l(r) d) exp(r).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.core.refine.model import (
    _FD_STEP,
    BIAS,
    CLOCK,
    DIST,
    INTR,
    READOUT,
    RIG,
    SCALE,
    _Model,
)
from annotator.vision.geometry import skew

# Step of the central differences of the lens in normalised coordinates (the lens is smooth: the
# truncation error is ~1e-12, the rounding ~1e-10).
_LENS_STEP = 1e-6


def left_jacobian(r: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors -> (n, 3, 3) left Jacobians of SO(3)."""
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = th < 1e-8
    t = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / (t * t))
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / (t * t * t))
    return np.eye(3) + a * K + b * (K @ K)


def _lens_jacobian(model: _Model, xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2, 2): d(distorted normalised) / d(pinhole normalised), central differences."""
    J = np.empty((len(xy), 2, 2))
    for i in range(2):
        e = np.zeros(2)
        e[i] = _LENS_STEP
        J[:, :, i] = (model.distort(xy + e, dist) - model.distort(xy - e, dist)) / (2 * _LENS_STEP)
    return J


def analytic_jacobian(model: _Model, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d(pixels)/d(parameter deltas): the pose part (N, 2, 6) and the static part (N, 2, Q), each
    corner's Q columns being those of its marker, its camera and the printed size
    (``StaticSlots``)."""
    f = model.forward(x)
    L, o, v = model.L, model.p.obs, f.values
    u = model.unpack(x)
    N = len(o.keyframe)
    c = o.camera
    Kc = v["K"][c]
    # d(pixels)/d(camera point): the intrinsics, the lens and the pinhole.
    z = f.zs
    Pp = np.zeros((N, 2, 3))
    Pp[:, 0, 0] = Pp[:, 1, 1] = 1.0 / z
    Pp[:, :, 2] = -f.xy / z[:, None]
    D = _lens_jacobian(model, f.xy, f.dist)
    KD = D * Kc[:, :2, None]  # rows scaled by fx, fy
    P = KD @ Pp  # (N, 2, 3)
    A = np.swapaxes(v["R_bc"][c], 1, 2)  # d Xc / d Y
    PA = P @ A
    G = PA @ np.swapaxes(f.R_D, 1, 2)  # d uv / d Yk
    RkT = np.swapaxes(v["R_k"][o.keyframe], 1, 2)
    GR = G @ RkT  # d uv / d X (world)

    Jp = np.empty((N, 2, 6))
    Jl_pose = left_jacobian(u["pose"][:, :3])[o.keyframe]
    Jp[:, :, :3] = GR @ skew(f.X - v["p_k"][o.keyframe]) @ Jl_pose
    Jp[:, :, 3:] = -GR

    cols: dict[str, np.ndarray] = {}  # block -> (N, 2, size) columns of each corner's instance
    if L.M:
        Jl_m = left_jacobian(u["marker"][:, :3])[o.marker]
        scaled = f.X - v["t_m"][o.marker]  # R_m (s local)
        cols["marker"] = np.concatenate([-GR @ skew(scaled) @ Jl_m, GR], axis=2)
    blocks = L.static_slices()
    if RIG in blocks:
        Jl_r = left_jacobian(u[RIG][:, :3])[c]
        cols[RIG] = np.concatenate([PA @ skew(f.Y - v["t_bc"][c]) @ Jl_r, -PA], axis=2)
    if INTR in blocks:
        J = np.zeros((N, 2, 4))
        J[:, 0, 0], J[:, 1, 1] = f.xyd[:, 0], f.xyd[:, 1]
        J[:, 0, 2] = J[:, 1, 3] = 1.0
        cols[INTR] = J
    if DIST in blocks:
        J = np.empty((N, 2, L.nd))
        h = 1e-3  # the lens is linear in its coefficients: any step is exact
        for i in range(L.nd):
            d = f.dist.copy()
            d[:, i] += h
            J[:, :, i] = (model.distort(f.xy, d) - f.xyd) / h * Kc[:, :2]
        cols[DIST] = J
    if READOUT in blocks or CLOCK in blocks:
        dY = -np.einsum("nji,nj->ni", f.R_D, np.cross(o.omega, f.Yk - f.t_D) + o.vel)
        d_tau = np.einsum("naj,nj->na", PA, dY)  # d uv / d (row time)
        if READOUT in blocks:
            cols[READOUT] = (d_tau * model.row[:, None])[:, :, None]
        if CLOCK in blocks:
            cols[CLOCK] = d_tau[:, :, None]
    if BIAS in blocks:
        cols[BIAS] = model.diag[:, :, None]
    if SCALE in blocks:
        cols[SCALE] = (GR @ (f.X - v["t_m"][o.marker])[:, :, None]) / v["scale"][0]
    return Jp, _static_slots(model, cols)


def _static_slots(model: _Model, cols: dict[str, np.ndarray]) -> np.ndarray:
    """The static blocks' columns side by side (N, 2, Q); a marker that is not a parameter's
    columns are zero."""
    J = np.concatenate([cols[name] for name in model.L.static_slices()], axis=2)
    slots = StaticSlots.of(model)
    J *= slots.free[:, None, :]
    return J


@dataclass(frozen=True, eq=False)
class StaticSlots:
    """Which static parameter each of a corner's Q Jacobian columns is (its marker's, its
    camera's, the printed size's), and the corners grouped by (marker, camera): a group's
    corners share their columns."""

    columns: np.ndarray  # (N, Q) index into the static vector
    free: np.ndarray  # (N, Q) False: a marker that is not a parameter
    order: np.ndarray  # corners sorted by group
    starts: np.ndarray  # each group's first position in ``order``

    @classmethod
    def of(cls, model: _Model) -> StaticSlots:
        """The model's slots (computed once, then kept with the model)."""
        hit = model.patterns.get("slots")
        if isinstance(hit, StaticSlots):
            return hit
        L, o = model.L, model.p.obs
        N = len(o.keyframe)
        inst = _instances(model)
        cols, free = [], []
        for name, (off, _n, size) in L.static_slices().items():
            which = inst[name]
            cols.append(off + which[:, None] * size + np.arange(size))
            ok = L.free_markers[which] if name == "marker" else np.ones(N, bool)
            free.append(np.repeat(ok[:, None], size, axis=1))
        group = o.marker * L.C + o.camera
        order = np.argsort(group, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
        slots = cls(np.concatenate(cols, axis=1), np.concatenate(free, axis=1), order, starts)
        model.patterns["slots"] = slots
        return slots


def _instances(model: _Model) -> dict[str, np.ndarray]:
    """Which instance of each static block every corner depends on."""
    o = model.p.obs
    return {
        "marker": o.marker,
        RIG: o.camera,
        INTR: o.camera,
        DIST: o.camera,
        READOUT: o.camera,
        CLOCK: o.camera,
        BIAS: o.camera,
        SCALE: np.zeros(len(o.keyframe), int),
    }


def numeric_jacobian(model: _Model, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same by forward differences on the deltas (one prediction per parameter of a kind):
    slower, kept as the reference the analytic one is checked against (and timed against, in
    bench/refine_solver.py)."""
    L = model.L
    uv0 = model.predict(x)[0]
    N = len(model.p.obs.keyframe)
    Jp = np.zeros((N, 2, 6))
    for i in range(6):
        xp = x.copy()
        xp[i : L.n_pose : 6] += _FD_STEP["pose"]
        Jp[:, :, i] = (model.predict(xp)[0] - uv0) / _FD_STEP["pose"]
    cols: dict[str, np.ndarray] = {}
    for name, (off, n, size) in L.static_slices().items():
        h = _FD_STEP[name]
        J = np.empty((N, 2, size))
        for i in range(size):
            xp = x.copy()
            xp[L.n_pose + off + i : L.n_pose + off + n * size : size] += h
            J[:, :, i] = (model.predict(xp)[0] - uv0) / h
        cols[name] = J
    return Jp, _static_slots(model, cols)
