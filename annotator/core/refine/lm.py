"""The self-calibration's least squares: the priors as precisions and Levenberg-Marquardt with a
Schur complement on the keyframe poses (the Jacobian: refine/jacobian.py)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from annotator.core.refine.jacobian import StaticSlots, analytic_jacobian
from annotator.core.refine.model import (
    BIAS,
    CLOCK,
    CORNER_BIAS_SIGMA_PX,
    DIST,
    INTR,
    READOUT,
    RIG,
    SCALE,
    Problem,
    RefineSettings,
    _Layout,
    _Model,
)


def _prior_precision(
    prob: Problem,
    layout: _Layout,
    model: _Model,
    skip_marker_prior: np.ndarray,
    floors: np.ndarray | None = None,
    clock_sigma_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal precision of the static priors and the rows A of the coupled priors (cost |A x|^2 / 2):
    each camera's aspect ratio, the rig's gauge, and (``floors``: (M, 6, 6)) each surveyed marker's
    prior widened by its floors, a full 6x6 block."""
    pr = prob.priors
    prec = np.zeros(layout.n_static)
    sl = layout.static_slices()
    off = sl["marker"][0]
    coupled_rows: list[np.ndarray] = []
    for m in range(layout.M):
        sr, sm = prob.marker_sigma[m]
        if skip_marker_prior[m] or not np.isfinite(sr):
            prec[off + 6 * m : off + 6 * m + 6] = 1e-6  # keeps a marker no keyframe sees well-posed
            continue
        if floors is None:
            prec[off + 6 * m : off + 6 * m + 3] = 1 / sr**2
            prec[off + 6 * m + 3 : off + 6 * m + 6] = 1 / sm**2
            continue
        prior = np.diag([sr * sr] * 3 + [sm * sm] * 3) + floors[m]
        rows = np.zeros((6, layout.n_static))
        rows[:, off + 6 * m : off + 6 * m + 6] = np.linalg.cholesky(np.linalg.inv(prior)).T
        coupled_rows.extend(rows)
    for name, (o, n, size) in sl.items():
        if name == "marker":
            continue
        for c in range(n):
            b = o + c * size
            if name == RIG:
                prec[b : b + 3] = 1 / math.radians(pr.rig_sigma_deg) ** 2
                prec[b + 3 : b + 6] = 1 / pr.rig_sigma_m**2
            elif name == INTR:
                fx, fy = model.K0[c, 0], model.K0[c, 1]
                prec[b : b + 4] = [
                    1 / (pr.focal_sigma_rel * fx) ** 2,
                    1 / (pr.focal_sigma_rel * fy) ** 2,
                    1 / pr.principal_sigma_px**2,
                    1 / pr.principal_sigma_px**2,
                ]
                a = np.zeros(layout.n_static)
                a[b], a[b + 1] = 1 / fx, -1 / fy
                coupled_rows.append(a / pr.aspect_sigma_rel)
            elif name == DIST:
                prec[b : b + size] = 1 / pr.distortion_sigma**2
            elif name == READOUT:
                prec[b] = 1 / pr.readout_sigma_s**2
            elif name == CLOCK:  # present only when clock_sigma_s > 0 (solver._solve)
                prec[b] = 1 / clock_sigma_s**2
            elif name == BIAS:
                prec[b] = 1 / CORNER_BIAS_SIGMA_PX**2
            elif name == SCALE:
                prec[b] = 1 / prob.length_sigma_rel**2
    coupled_rows.extend(_gauge_rows(layout))
    A = np.array(coupled_rows) if coupled_rows else np.zeros((0, layout.n_static))
    return prec, A


def _gauge_rows(layout: _Layout) -> list[np.ndarray]:
    """Rows pinning what the data cannot see to its measurement: the rig's and the clocks' mean
    change over the cameras, held at zero."""
    rows: list[np.ndarray] = []
    sl = layout.static_slices()
    if RIG in sl:
        # A motion common to every camera of the rig (with the opposite motion of the bundle)
        # moves no camera, so the data cannot tell it - but the frame-time offsets between
        # cameras make it look weakly observable through the first pass's motion. Pin it to the
        # rig's measurement.
        o, n, _ = sl[RIG]
        for i in range(6):
            a = np.zeros(layout.n_static)
            a[o + i : o + 6 * n : 6] = 1.0 / n
            rows.append(a * 1e5)
    if CLOCK in sl:
        # A delay common to every camera moves every keyframe's pose along the walk, which the
        # keyframe poses absorb: the cameras' mean stays the sync's.
        o, n, _ = sl[CLOCK]
        a = np.zeros(layout.n_static)
        a[o : o + n] = 1.0 / n
        rows.append(a * 1e5)
    return rows


def _robust_weights(r: np.ndarray, k: float) -> np.ndarray:
    n = np.linalg.norm(r, axis=1)
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-12))


def _huber_cost(r: np.ndarray, k: float) -> np.ndarray:
    n = np.linalg.norm(r, axis=1)
    return np.where(n <= k, 0.5 * n * n, k * n - 0.5 * k * k)


class _LM:
    def __init__(
        self,
        prob: Problem,
        layout: _Layout,
        settings: RefineSettings,
        jacobian: Callable[[_Model, np.ndarray], tuple[np.ndarray, np.ndarray]] = analytic_jacobian,
    ) -> None:
        self.prob, self.L, self.s = prob, layout, settings
        self.jacobian = jacobian
        self.model = _Model(prob, layout)
        self.skip = np.zeros(layout.M, bool)
        self.sigma_px = 1.0
        self._priors()

    def _priors(self, floors: np.ndarray | None = None) -> None:
        self.prec, self.A = _prior_precision(
            self.prob, self.L, self.model, self.skip, floors, self.s.clock_sigma_s
        )
        self.aspect_prec = 1.0  # the rows of A carry their own weights

    def cost(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        uv, z = self.model.predict(x)
        r = (uv - self.prob.obs.uv) / self.sigma_px
        data = float(np.sum(self.prob.obs.weight * _huber_cost(r, self.s.huber_px / self.sigma_px)))
        xs = x[self.L.n_pose :]
        prior = 0.5 * float(np.sum(self.prec * xs * xs)) + 0.5 * self.aspect_prec * float(
            np.sum((self.A @ xs) ** 2)
        )
        bad = np.count_nonzero(z <= 0)
        return data + prior + 1e6 * bad, uv

    def normal_equations(self, x: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, ...]:
        L, o = self.L, self.prob.obs
        Jp, Js = self.jacobian(self.model, x)
        r = (uv - o.uv) / self.sigma_px
        w = o.weight * _robust_weights(r, self.s.huber_px / self.sigma_px) / self.sigma_px**2
        rr = uv - o.uv  # pixels; w carries 1/sigma^2
        # Pose blocks.
        JpT = np.swapaxes(Jp, 1, 2) * w[:, None, None]  # (N, 6, 2), weighted
        kf = o.keyframe[:, None]
        Hpp = np.bincount(
            (36 * kf + np.arange(36)).ravel(), (JpT @ Jp).ravel(), minlength=36 * L.K
        ).reshape(L.K, 6, 6)
        gp = np.bincount(
            (6 * kf + np.arange(6)).ravel(), (JpT @ rr[:, :, None]).ravel(), minlength=6 * L.K
        ).reshape(L.K, 6)
        # Pose-static and static-static, from each corner's own columns (StaticSlots): the corners
        # of one marker seen by one camera share theirs.
        slots = StaticSlots.of(self.model)
        S = L.n_static
        wr = w[:, None] * rr  # (N, 2)
        gs = np.bincount(slots.columns.ravel(), (wr[:, None, :] @ Js)[:, 0].ravel(), minlength=S)
        at = (6 * o.keyframe[:, None, None] + np.arange(6)[:, None]) * S + slots.columns[:, None]
        Hps = np.bincount(at.ravel(), (JpT @ Js).ravel(), minlength=L.n_pose * S).reshape(
            L.n_pose, S
        )
        Hss = np.zeros((S, S))
        bounds = np.r_[slots.starts, len(slots.order)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            rows = slots.order[a:b]
            J = Js[rows].reshape(-1, Js.shape[2])
            cols = slots.columns[rows[0]]
            Hss[np.ix_(cols, cols)] += J.T @ (np.repeat(w[rows], 2)[:, None] * J)
        xs = x[L.n_pose :]
        Hss += np.diag(self.prec) + self.aspect_prec * self.A.T @ self.A
        gs += self.prec * xs + self.aspect_prec * self.A.T @ (self.A @ xs)
        return Hpp, gp, Hps, Hss, gs

    def step(
        self,
        Hpp: np.ndarray,
        gp: np.ndarray,
        Hps: np.ndarray,
        Hss: np.ndarray,
        gs: np.ndarray,
        lam: float,
    ) -> np.ndarray | None:
        L = self.L
        D = np.einsum("kii->ki", Hpp)
        Hd = Hpp + lam * np.einsum("ki,ij->kij", np.maximum(D, 1e-9), np.eye(6))
        try:
            Hinv = np.linalg.inv(Hd)  # (K, 6, 6)
        except np.linalg.LinAlgError:
            return None
        B = Hps.reshape(L.K, 6, -1)  # (K, 6, S)
        HinvB = Hinv @ B
        Hinvg = (Hinv @ gp[:, :, None])[:, :, 0]
        Bf = B.reshape(-1, B.shape[2])
        S = Hss + lam * np.diag(np.maximum(np.diag(Hss), 1e-9)) - Bf.T @ HinvB.reshape(Bf.shape)
        rhs = gs - Bf.T @ Hinvg.ravel()
        try:
            dxs = -np.linalg.solve(S, rhs)
        except np.linalg.LinAlgError:
            return None
        dxp = -(Hinvg + HinvB @ dxs)
        return np.concatenate([dxp.ravel(), dxs])

    def static_covariance(
        self, Hpp: np.ndarray, Hps: np.ndarray, Hss: np.ndarray, stretch: float = 1.0
    ) -> np.ndarray:
        """Covariance of the static parameters: the inverse of the reduced normal matrix, its data
        part divided by ``stretch`` (>= 1: the corners' errors are correlated, see
        _correlation_stretch), the priors' part as it is."""
        L = self.L
        Hinv = np.linalg.inv(Hpp + 1e-12 * np.eye(6))
        B = Hps.reshape(L.K, 6, -1)
        Bf = B.reshape(-1, B.shape[2])
        S = Hss - Bf.T @ (Hinv @ B).reshape(Bf.shape)
        if stretch != 1.0:
            prior = np.diag(self.prec) + self.aspect_prec * self.A.T @ self.A
            S = (S - prior) / stretch + prior
        return np.linalg.pinv(S)

    def solve(self, x: np.ndarray, iterations: int) -> tuple[np.ndarray, int]:
        lam = 1e-3
        cost, uv = self.cost(x)
        it = 0
        while it < iterations:
            it += 1
            Hpp, gp, Hps, Hss, gs = self.normal_equations(x, uv)
            improved = False
            for _ in range(8):
                dx = self.step(Hpp, gp, Hps, Hss, gs, lam)
                if dx is None:
                    lam *= 10
                    continue
                c2, uv2 = self.cost(x + dx)
                if c2 < cost:
                    rel = (cost - c2) / max(cost, 1e-12)
                    x, cost, uv = x + dx, c2, uv2
                    lam = max(lam / 3, 1e-7)
                    improved = True
                    break
                lam *= 10
            if not improved or rel < 1e-5:
                break
        return x, it
