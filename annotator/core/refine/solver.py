"""The self-calibration's solver: priors, Jacobian, Levenberg-Marquardt with a Schur complement
on the pose blocks, the gate, and the covariance handed to the uncertainty propagation."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from annotator.core.priors import ParameterCovariance
from annotator.core.refine.model import (
    _FD_STEP,
    BIAS,
    CORNER_BIAS_SIGMA_PX,
    DIST,
    INTR,
    READOUT,
    RIG,
    CameraParams,
    Observations,
    Problem,
    RefineSettings,
    Solution,
    _Layout,
    _Model,
    supported_lens,
)

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)

# --- the solver -------------------------------------------------------------------------------


def _prior_precision(
    prob: Problem,
    layout: _Layout,
    model: _Model,
    skip_marker_prior: np.ndarray,
    floors: np.ndarray | None = None,
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
            elif name == BIAS:
                prec[b] = 1 / CORNER_BIAS_SIGMA_PX**2
    if RIG in sl:
        # The gauge: a motion common to every camera of the rig (with the opposite motion of the
        # bundle) moves no camera, so the data cannot tell it - but the frame-time offsets between
        # cameras make it look weakly observable through the first pass's motion. Pin it to the
        # rig's measurement: the mean change over the cameras is held at zero.
        o, n, _ = sl[RIG]
        for i in range(6):
            a = np.zeros(layout.n_static)
            a[o + i : o + 6 * n : 6] = 1.0 / n
            coupled_rows.append(a * 1e5)
    A = np.array(coupled_rows) if coupled_rows else np.zeros((0, layout.n_static))
    return prec, A


def _jacobian(model: _Model, x: np.ndarray, uv0: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
    """Pose part (N, 2, 6) and static part (2N x S sparse) by forward differences on the deltas."""
    L = model.L
    o = model.p.obs
    N = len(o.keyframe)
    Jp = np.zeros((N, 2, 6))
    for i in range(6):
        xp = x.copy()
        xp[i : L.n_pose : 6] += _FD_STEP["pose"]
        Jp[:, :, i] = (model.predict(xp)[0] - uv0) / _FD_STEP["pose"]
    rows, cols, vals = [], [], []
    row_idx = np.arange(2 * N).reshape(N, 2)
    inst = {
        "marker": o.marker,
        RIG: o.camera,
        INTR: o.camera,
        DIST: o.camera,
        READOUT: o.camera,
        BIAS: o.camera,
    }
    for name, (off, n, size) in L.static_slices().items():
        h = _FD_STEP[name]
        which = inst[name]
        free = L.free_markers[which] if name == "marker" else np.ones(N, bool)
        for i in range(size):
            xp = x.copy()
            xp[L.n_pose + off + i : L.n_pose + off + n * size : size] += h
            d = (model.predict(xp)[0] - uv0) / h  # (N, 2)
            col = off + which * size + i
            rows.append(row_idx[free].ravel())
            cols.append(np.repeat(col[free], 2))
            vals.append(d[free].ravel())
    Js = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(2 * N, L.n_static),
    )
    return Jp, Js


def _robust_weights(r: np.ndarray, k: float) -> np.ndarray:
    n = np.linalg.norm(r, axis=1)
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-12))


def _huber_cost(r: np.ndarray, k: float) -> np.ndarray:
    n = np.linalg.norm(r, axis=1)
    return np.where(n <= k, 0.5 * n * n, k * n - 0.5 * k * k)


class _LM:
    def __init__(self, prob: Problem, layout: _Layout, settings: RefineSettings) -> None:
        self.prob, self.L, self.s = prob, layout, settings
        self.model = _Model(prob, layout)
        self.skip = np.zeros(layout.M, bool)
        self.sigma_px = 1.0
        self._priors()

    def _priors(self, floors: np.ndarray | None = None) -> None:
        self.prec, self.A = _prior_precision(self.prob, self.L, self.model, self.skip, floors)
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
        Jp, Js = _jacobian(self.model, x, uv)
        r = (uv - o.uv) / self.sigma_px
        w = o.weight * _robust_weights(r, self.s.huber_px / self.sigma_px) / self.sigma_px**2
        rr = uv - o.uv  # pixels; w carries 1/sigma^2
        # Pose blocks.
        Hpp = np.zeros((L.K, 6, 6))
        np.add.at(Hpp, o.keyframe, np.einsum("nai,naj,n->nij", Jp, Jp, w))
        gp = np.zeros((L.K, 6))
        np.add.at(gp, o.keyframe, np.einsum("nai,na,n->ni", Jp, rr, w))
        # Pose-static and static-static.
        N = len(o.keyframe)
        wr = np.repeat(w, 2)
        Jp_sp = sp.csr_matrix(
            (
                Jp.reshape(-1),
                (
                    np.repeat(np.arange(2 * N), 6),
                    (6 * o.keyframe[:, None, None] + np.arange(6)).repeat(2, 1).reshape(-1),
                ),
            ),
            shape=(2 * N, L.n_pose),
        )
        WJs = sp.diags(wr) @ Js
        Hps = (Jp_sp.T @ WJs).toarray()  # (6K, S)
        Hss = (Js.T @ WJs).toarray()
        xs = x[L.n_pose :]
        Hss += np.diag(self.prec) + self.aspect_prec * self.A.T @ self.A
        gs = Js.T @ (wr * rr.ravel()) + self.prec * xs + self.aspect_prec * self.A.T @ (self.A @ xs)
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
    gated = _gate(x, cov, layout, s, has_prior)
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
        cov = cov + np.outer(held, held)
    _, uv = lm.cost(x)
    v = lm.model.static_values(x)
    u = lm.model.unpack(x)
    rejected = [prob.markers[m] for m in np.flatnonzero(lm.skip)]
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
    )


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
    x: np.ndarray, cov: np.ndarray, layout: _Layout, s: RefineSettings, has_prior: np.ndarray
) -> list[int]:
    """Static indices of the blocks whose correction is within noise of their prior.

    Per-camera blocks: no component beyond ``gate_sigma`` posterior sigmas. The rig as a whole
    (its gauge is pinned to the mean of the cameras, so one camera cannot be judged alone).
    Surveyed markers: the correction's Mahalanobis distance per degree of freedom below
    ``marker_gate_sigma``.
    """
    out: list[int] = []
    if s.gate_sigma <= 0:
        return out
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-30))
    xs = x[layout.n_pose :]
    for name, (off, n, size) in layout.static_slices().items():
        if name == "marker":
            for m in range(n):
                i = off + 6 * m
                if not (layout.free_markers[m] and has_prior[m]):
                    continue
                d = xs[i : i + 6]
                floor = np.diag(
                    [math.radians(s.marker_floor_deg) ** 2] * 3 + [s.marker_floor_m**2] * 3
                )
                if _mahalanobis(d, cov[i : i + 6, i : i + 6] + floor) < s.marker_gate_sigma:
                    out.extend(range(i, i + 6))
            continue
        if name == RIG:
            z = np.abs(xs[off : off + n * size]) / sd[off : off + n * size]
            if z.max() < s.gate_sigma:
                log.info(
                    "refine: rig change not significant (max %.1f sigma); the measured rig kept",
                    z.max(),
                )
                out.extend(range(off, off + n * size))
            continue
        for c in range(n):
            i = off + c * size
            z = np.abs(xs[i : i + size]) / sd[i : i + size]
            if z.max() < s.gate_sigma:
                log.info(
                    "refine: %s of camera %d not significant (max %.1f sigma); prior kept",
                    name,
                    c,
                    z.max(),
                )
                out.extend(range(i, i + size))
    return out


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
