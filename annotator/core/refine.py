"""Self-calibration from the capture: a bundle adjustment over keyframes of a first tracking pass.

Jointly refines, under a Huber loss on marker-corner reprojection residuals (pixels):

- the bundle pose at each keyframe (free);
- every marker's pose (the survey as a prior weighted by its sigma; markers the surveyor skipped,
  or marked ``unknown``, are free and start from frames where they are seen with surveyed ones);
- each camera's pose in the rig (the measured rig as a prior);
- each camera's intrinsics fx, fy, cx, cy and distortion (the calibration as a prior, plus a tight
  prior on fx/fy - the aspect ratio of a pixel is a property of the sensor, well known);
- each camera's rolling-shutter readout time (prior: the calibration's value).

A keyframe is one frame of the first camera plus the other cameras' nearest frames; those are
held to the keyframe's pose by the first pass's relative motion (known far better than absolute
poses over a few ms), and every corner is seen at its frame time + row / height x readout, with
the bundle moving at the first pass's velocity meanwhile.

All parameters are deltas from their starting values (rotations as world- or bundle-frame rotation
vectors, as in `annotator.core.priors`), so the Jacobian is taken by forward differences on the deltas:
a perturbation of component i of every instance of a block at once gives that column for every
residual, since each residual depends on one instance of each block only (28 evaluations for the
whole Jacobian). The solver is our own Levenberg-Marquardt with a Schur complement on the pose
blocks (6x6 each), so each step solves a dense system the size of the static parameters only;
the inverse of that reduced system is the covariance of the static parameters (what
`priors.ParameterCovariance` carries to the uncertainty propagation). See docs/annotator.md for
why not scipy's least_squares.

Gauge: a rotation or translation common to every camera of the rig, with the opposite change of
the bundle poses, moves no camera; the rig prior alone fixes it, so the bundle's orientation is
only as good as the rig's measurement (per camera 1 deg -> ~0.7 deg per axis for two cameras).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from annotator.core.priors import ParameterCovariance, Priors
from annotator.vision.geometry import marker_corners_local

if TYPE_CHECKING:
    from annotator.core.experiment import CameraCalibration, Experiment, RigCamera
    from annotator.core.uncertainty import VideoFrames

log = logging.getLogger(__name__)

# Block order in the static part of the parameter vector, per camera after the markers.
RIG, INTR, DIST, READOUT, BIAS = "rig", "intr", "dist", "readout", "bias"
# Prior sigma of the detector's corner bias: ArUco corners sit a fraction of a pixel off the true
# corner along the square's diagonal (threshold, blur, print bleed), the same way for every marker.
# Unmodelled, it makes each small marker look a few per cent too small, i.e. too far away.
CORNER_BIAS_SIGMA_PX = 1.0
_FD_STEP = {
    "pose": 1e-6,
    "marker": 1e-6,
    RIG: 1e-6,
    INTR: 1e-3,
    DIST: 1e-6,
    READOUT: 1e-6,
    BIAS: 1e-3,
}


@dataclass(frozen=True, slots=True)
class RefineSettings:
    """How the refinement runs (what it may change, how many keyframes, robust loss, gates)."""

    mode: str = "all"  # map: markers only; all: markers, rig, intrinsics, distortion, readout
    max_keyframes: int = 240
    min_markers: int = 2  # markers a keyframe must show (over all its cameras)
    iterations: int = 25
    huber_px: float = 1.5
    min_sigma_px: float = (
        0.5  # floor on the corner noise: corner errors are correlated (blur, print)
    )
    moved_sigma: float = 6.0  # a surveyed marker this many sigma from the data loses its prior
    flag_sigma: float = 3.0  # ... and one that moved more than this is reported
    # Corrections of a static block smaller than this many of its posterior sigma are not applied:
    # on an exact capture the data move nothing beyond noise, and the prior is kept.
    gate_sigma: float = 3.0
    marker_gate_sigma: float = 1.0  # the same for a surveyed marker (Mahalanobis, per dof) ...
    # ... against its posterior widened by these floors: corner errors that are the same in every
    # frame (a bias that depends on the marker's size in the image, print flaws) move a marker by a
    # few mm with a confidence the data do not have.
    marker_floor_m: float = 0.005
    marker_floor_deg: float = 0.3
    # A marker's distance along the line of sight comes from its size in the image, and an error
    # in that size common to all its frames (corner bias varying with the size, blur, print) is not
    # averaged away: a size error of this many pixels is a depth error of depth x this / side (px),
    # 9 cm for a 32 px marker at 9.6 m (measured on the field renders: ~0.3 px).
    marker_size_floor_px: float = 0.3
    exposure_s: float = 0.008  # assumed exposure for the motion-blur measure
    max_smear_px: float = 3.0  # keyframes whose predicted smear exceeds this are not used

    def validate(self) -> RefineSettings:
        if self.mode not in ("map", "all"):
            raise ValueError(f"refine mode must be 'map' or 'all', not {self.mode!r}")
        if self.max_keyframes < 1 or self.iterations < 1 or self.huber_px <= 0:
            raise ValueError("refine: need max_keyframes >= 1, iterations >= 1 and huber_px > 0")
        return self


@dataclass(frozen=True, eq=False)
class CameraParams:
    """A camera as the refinement sees it: rig pose, pinhole intrinsics, lens and readout."""

    name: str
    R_bc: np.ndarray
    t_bc: np.ndarray
    K: np.ndarray  # 3x3
    dist: np.ndarray  # radtan: k1 k2 p1 p2 [k3]; fisheye: k1..k4
    model: str
    readout_s: float
    height: int
    corner_bias_px: float = (
        0.0  # detected corners sit this far outward (+) / inward (-) along the diagonal
    )


@dataclass(frozen=True, eq=False)
class Observations:
    """Every corner the refinement uses, flattened (N corners)."""

    keyframe: np.ndarray  # (N,) int
    camera: np.ndarray  # (N,) int
    marker: np.ndarray  # (N,) int: index into the marker list
    corner: np.ndarray  # (N,) int 0..3
    uv: np.ndarray  # (N, 2) measured, distorted pixels
    R_D: np.ndarray  # (N, 3, 3) bundle at the frame time, seen from the bundle at the keyframe
    t_D: np.ndarray  # (N, 3)
    omega: np.ndarray  # (N, 3) angular velocity, keyframe-bundle frame, rad/s
    vel: np.ndarray  # (N, 3) linear velocity, keyframe-bundle frame, m/s
    weight: np.ndarray  # (N,) a-priori weight (motion blur)


@dataclass(frozen=True, eq=False)
class Problem:
    markers: list[int]  # ids
    R_m: np.ndarray  # (M, 3, 3) start / prior mean
    t_m: np.ndarray  # (M, 3)
    marker_sigma: np.ndarray  # (M, 2): (rad, m) survey sigma; inf = no prior
    length: float
    cameras: list[CameraParams]
    R_k: np.ndarray  # (K, 3, 3) keyframe bundle poses (start)
    p_k: np.ndarray  # (K, 3)
    obs: Observations
    priors: Priors


@dataclass(frozen=True, eq=False)
class Solution:
    R_m: np.ndarray
    t_m: np.ndarray
    marker_sigma_m: np.ndarray  # (M,) posterior position sigma (per axis, rms)
    moved: list[int]  # ids whose survey disagrees with the data by > flag_sigma
    cameras: list[CameraParams]
    R_k: np.ndarray
    p_k: np.ndarray
    covariance: ParameterCovariance
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    sigma_px: float
    iterations: int
    seconds: float
    rejected_priors: list[int] = field(default_factory=list)


# --- projection -------------------------------------------------------------------------------


def _mv(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R[n] @ v[n] for stacks of 3x3 matrices and 3-vectors."""
    return (R @ v[:, :, None])[:, :, 0]


def _mtv(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R[n]^T @ v[n]."""
    return (np.swapaxes(R, 1, 2) @ v[:, :, None])[:, :, 0]


def _rot(rv: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(*rv.shape[:-1], 3, 3)


def distort_normalised(xy: np.ndarray, dist: np.ndarray, model: str) -> np.ndarray:
    """Normalised pinhole coordinates (N, 2) -> distorted normalised coordinates; dist (N, nd)."""
    x, y = xy[:, 0], xy[:, 1]
    if model == "fisheye":
        r = np.sqrt(x * x + y * y)
        th = np.arctan(r)
        th2 = th * th
        thd = th * (
            1 + th2 * (dist[:, 0] + th2 * (dist[:, 1] + th2 * (dist[:, 2] + th2 * dist[:, 3])))
        )
        s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
        return xy * s[:, None]
    k1, k2, p1, p2 = dist[:, 0], dist[:, 1], dist[:, 2], dist[:, 3]
    k3 = dist[:, 4] if dist.shape[1] > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def supported_lens(model: str, dist: np.ndarray) -> bool:
    """Lenses the refinement's own projection handles (OpenCV radtan up to k3, fisheye)."""
    return model == "fisheye" or (model == "radtan" and not np.any(np.asarray(dist)[5:]))


# --- parameter layout -------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    K: int
    M: int
    C: int
    nd: int
    free_markers: np.ndarray  # (M,) bool: markers that are parameters
    cam_blocks: tuple[str, ...]  # which per-camera blocks are free

    @property
    def n_pose(self) -> int:
        return 6 * self.K

    def static_slices(self) -> dict[str, tuple[int, int, int]]:
        """name -> (offset into static vector, count of instances, size of one)."""
        out, off = {}, 0
        out["marker"] = (off, self.M, 6)
        off += 6 * self.M
        for b in self.cam_blocks:
            size = {RIG: 6, INTR: 4, DIST: self.nd, READOUT: 1, BIAS: 1}[b]
            out[b] = (off, self.C, size)
            off += size * self.C
        return out

    @property
    def n_static(self) -> int:
        return sum(n * s for _, n, s in self.static_slices().values())


class _Model:
    """Predicted pixels of every corner for a parameter vector (deltas from the start)."""

    def __init__(self, prob: Problem, layout: _Layout) -> None:
        self.p, self.L = prob, layout
        o = prob.obs
        self.local = marker_corners_local(prob.length)[o.corner]  # (N, 3)
        cams = prob.cameras
        self.R_bc0 = np.array([c.R_bc for c in cams])
        self.t_bc0 = np.array([c.t_bc for c in cams])
        self.K0 = np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]] for c in cams])
        self.d0 = np.array(
            [
                np.resize(np.asarray(c.dist, float), layout.nd)
                if len(c.dist)
                else np.zeros(layout.nd)
                for c in cams
            ]
        )
        self.r0 = np.array([c.readout_s for c in cams])
        self.b0 = np.array([c.corner_bias_px for c in cams])
        # Each marker's four corners are consecutive rows: the unit vector from the measured
        # square's centre to each corner is the direction of the detector's corner bias.
        quad = o.uv.reshape(-1, 4, 2)
        d = quad - quad.mean(axis=1, keepdims=True)
        self.diag = (d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-9)).reshape(-1, 2)
        self.row = o.uv[:, 1] / np.array([c.height for c in cams])[o.camera]
        self.models = sorted({c.model for c in cams})
        self.cam_model = np.array([c.model for c in cams])
        self._cache: dict[str, tuple[bytes, Any]] = {}

    def unpack(self, x: np.ndarray) -> dict[str, np.ndarray]:
        L = self.L
        out = {"pose": x[: L.n_pose].reshape(L.K, 6)}
        s = x[L.n_pose :]
        for name, (off, n, size) in L.static_slices().items():
            out[name] = s[off : off + n * size].reshape(n, size)
        return out

    def static_values(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Absolute parameter values for a parameter vector (markers, rig, intrinsics ...)."""
        u = self.unpack(x)
        C = self.L.C
        d_rig = u.get(RIG, np.zeros((C, 6)))
        return {
            "R_m": _rot(u["marker"][:, :3]) @ self.p.R_m,
            "t_m": self.p.t_m + u["marker"][:, 3:],
            "R_bc": _rot(d_rig[:, :3]) @ self.R_bc0,
            "t_bc": self.t_bc0 + d_rig[:, 3:],
            "K": self.K0 + u.get(INTR, np.zeros((C, 4))),
            "dist": self.d0 + u.get(DIST, np.zeros((C, self.L.nd))),
            "readout": self.r0 + u.get(READOUT, np.zeros((C, 1)))[:, 0],
            "bias": self.b0 + u.get(BIAS, np.zeros((C, 1)))[:, 0],
            "R_k": _rot(u["pose"][:, :3]) @ self.p.R_k,
            "p_k": self.p.p_k + u["pose"][:, 3:],
        }

    def _stage(self, name: str, key: np.ndarray, compute: Callable[[], Any]) -> Any:
        """The last result of a stage, recomputed only when its inputs changed: a forward
        difference changes one block, so most evaluations reuse most stages."""
        k = key.tobytes()
        hit = self._cache.get(name)
        if hit is not None and hit[0] == k:
            return hit[1]
        value = compute()
        self._cache[name] = (k, value)
        return value

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels and (N,) depth."""
        v = self.static_values(x)
        o = self.p.obs
        Yk = self._stage(
            "Yk",
            np.concatenate(
                [v["R_m"].ravel(), v["t_m"].ravel(), v["R_k"].ravel(), v["p_k"].ravel()]
            ),
            lambda: _mtv(
                v["R_k"][o.keyframe],
                _mv(v["R_m"][o.marker], self.local) + v["t_m"][o.marker] - v["p_k"][o.keyframe],
            ),
        )  # R_k^T (X - p_k)

        def motion() -> tuple[np.ndarray, np.ndarray]:
            tau = v["readout"][o.camera] * self.row
            return _rot(o.omega * tau[:, None]) @ o.R_D, o.t_D + o.vel * tau[:, None]

        R_D, t_D = self._stage("motion", v["readout"], motion)
        Y = _mtv(R_D, Yk - t_D)
        c = o.camera
        Xc = _mtv(v["R_bc"][c], Y - v["t_bc"][c])
        z = Xc[:, 2]
        zs = np.where(np.abs(z) < 1e-6, 1e-6, z)
        xy = Xc[:, :2] / zs[:, None]
        xyd = np.empty_like(xy)
        dist = v["dist"][c]
        for model in self.models:
            sel = self.cam_model[c] == model
            xyd[sel] = distort_normalised(xy[sel], dist[sel], model)
        Kc = v["K"][c]
        uv = np.stack([Kc[:, 0] * xyd[:, 0] + Kc[:, 2], Kc[:, 1] * xyd[:, 1] + Kc[:, 3]], axis=1)
        return uv + v["bias"][c][:, None] * self.diag, z


# --- the solver -------------------------------------------------------------------------------


def _prior_precision(
    prob: Problem, layout: _Layout, model: _Model, skip_marker_prior: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal precision of the static priors and the rows A of the coupled priors (cost |A x|^2 / 2):
    each camera's aspect ratio, the rig's gauge."""
    pr = prob.priors
    prec = np.zeros(layout.n_static)
    sl = layout.static_slices()
    off = sl["marker"][0]
    for m in range(layout.M):
        sr, sm = prob.marker_sigma[m]
        if skip_marker_prior[m] or not np.isfinite(sr):
            prec[off + 6 * m : off + 6 * m + 6] = 1e-6  # keeps a marker no keyframe sees well-posed
            continue
        prec[off + 6 * m : off + 6 * m + 3] = 1 / sr**2
        prec[off + 6 * m + 3 : off + 6 * m + 6] = 1 / sm**2
    aspect_rows = []
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
                aspect_rows.append(a / pr.aspect_sigma_rel)
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
            aspect_rows.append(a * 1e5)
    A = np.array(aspect_rows) if aspect_rows else np.zeros((0, layout.n_static))
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

    def _priors(self) -> None:
        self.prec, self.A = _prior_precision(self.prob, self.L, self.model, self.skip)
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
    # terms (the map's datum is common to every marker), its data part widened by the correlation
    # of the keyframes' corner errors over time, plus what the gate held back and the rig's gauge.
    # The markers' floors stay out: they are errors common to all of a marker's frames, and the
    # tracker sees the same frames (docs/annotator.md, "What sigma_m means").
    stretch = _correlation_stretch(prob, uv, lm.sigma_px)
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


def _rigid_rows(prob: Problem, layout: _Layout, markers: Sequence[int]) -> np.ndarray:
    """Rows A (cost |A x|^2 / 2, stiff) that hold the deltas of ``markers`` to one common small
    rigid motion (a world rotation w about their centre and a shift t): per marker the rotation
    delta is w and the position delta t + w x (p - centre). Fewer than two markers: no rows."""
    if len(markers) < 2:
        return np.zeros((0, layout.n_static))
    p = prob.t_m[list(markers)]
    d = p - p.mean(axis=0)
    basis = np.zeros((6 * len(markers), 6))
    for k, dk in enumerate(d):
        basis[6 * k : 6 * k + 3, :3] = np.eye(3)
        # w x d = -[d]x w
        basis[6 * k + 3 : 6 * k + 6, :3] = -np.array(
            [[0, -dk[2], dk[1]], [dk[2], 0, -dk[0]], [-dk[1], dk[0], 0]]
        )
        basis[6 * k + 3 : 6 * k + 6, 3:] = np.eye(3)
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
    shift W x (t_c - mean t) + T. It moves the beacon (the bundle's origin) in the world.
    """
    out = np.zeros((layout.n_static, layout.n_static))
    sl = layout.static_slices()
    if RIG not in sl:
        return out
    o, n, _ = sl[RIG]
    pr = prob.priors
    G = np.zeros((layout.n_static, 6))
    centre = t_bc.mean(axis=0)
    for c in range(n):
        b = o + 6 * c
        G[b : b + 3, :3] = np.eye(3)
        d = t_bc[c] - centre
        G[b + 3 : b + 6, :3] = -np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
        G[b + 3 : b + 6, 3:] = np.eye(3)
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


# --- building a problem from detections -------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FrameView:
    """One camera frame of a keyframe: its detections and the bundle's motion at its time."""

    camera: int
    ids: np.ndarray  # (n,)
    corners: np.ndarray  # (n, 4, 2) distorted pixels
    R_D: np.ndarray = field(
        default_factory=lambda: np.eye(3)
    )  # bundle at this frame, from the keyframe's
    t_D: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))  # keyframe-bundle frame, rad/s
    vel: np.ndarray = field(default_factory=lambda: np.zeros(3))  # keyframe-bundle frame, m/s
    weight: float = 1.0


@dataclass(frozen=True, eq=False)
class Keyframe:
    R_wb: np.ndarray  # start pose (first pass)
    t_wb: np.ndarray
    views: list[FrameView]


def _calibration(cam: CameraParams) -> CameraCalibration:
    from annotator.core.experiment import CameraCalibration

    return CameraCalibration(
        cam.K, np.asarray(cam.dist, float), 0, cam.height, "", cam.model, cam.readout_s
    )


def _medoid_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    rots = Rotation.from_matrix(np.array(Rs))
    if len(Rs) == 1:
        return Rs[0]
    sample = rots if len(Rs) <= 60 else rots[np.linspace(0, len(Rs) - 1, 60).astype(int)]
    cost = [np.sum((sample.inv() * r).magnitude()) for r in sample]
    best = sample[int(np.argmin(cost))]
    near = rots[(best.inv() * rots).magnitude() < np.radians(5)]
    return near.mean().as_matrix()


def marker_views(
    keyframes: list[Keyframe], cameras: list[CameraParams], length: float
) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Each marker's world pose (R, centre) as each keyframe view sees it (IPPE of its square)."""
    from annotator.vision.geometry import ippe_square
    from annotator.vision.lens import undistort_points

    cals = [_calibration(c) for c in cameras]
    out: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for kf in keyframes:
        for v in kf.views:
            if not len(v.ids):
                continue
            cam = cameras[v.camera]
            R_b, t_b = kf.R_wb @ v.R_D, kf.R_wb @ v.t_D + kf.t_wb  # bundle at the frame time
            R_wc, c_w = R_b @ cam.R_bc, R_b @ cam.t_bc + t_b
            xn = undistort_points(cals[v.camera], v.corners)
            for mid, pts in zip(v.ids, xn, strict=True):
                sols = ippe_square(pts, length, np.eye(3), None)
                if not sols:
                    continue
                R_cm, t_cm, _ = sols[0]
                if len(sols) > 1 and sols[1][2] < 2 * sols[0][2] + 1e-4:
                    continue  # ambiguous square: no vote
                out.setdefault(int(mid), []).append((R_wc @ R_cm, R_wc @ t_cm + c_w))
    return out


def build_problem(
    survey: dict[int, tuple[np.ndarray, np.ndarray]],
    length: float,
    cameras: list[CameraParams],
    keyframes: list[Keyframe],
    priors: Priors,
    moved_m: float = 0.05,
    initial: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[Problem, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """The problem over every marker seen in the keyframes (surveyed or not) and the start values.

    ``survey`` maps marker id -> (R_world_marker, centre). Markers not in it, or marked unknown in
    the priors, are free; they start from the median of their views. A surveyed marker whose views
    put it more than ``moved_m`` (and 5 sigma) away from the survey starts from the views too.
    ``initial`` gives start poses for free markers (an earlier refinement's) instead.
    Returns the problem and the start poses that differ from the survey.
    """
    views = marker_views(keyframes, cameras, length)
    starts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for mid, vs in views.items():
        pos = np.median(np.array([c for _, c in vs]), axis=0)
        R = _medoid_rotation([r for r, _ in vs])
        starts[mid] = (R, pos)
    seen_ids = {int(i) for kf in keyframes for v in kf.views for i in v.ids}
    for mid, pose in (initial or {}).items():
        if mid not in survey and mid in seen_ids:
            starts[mid] = pose
    ids = sorted(set(survey) | set(starts))
    R_m, t_m, sig, start_moved, kept = [], [], [], {}, []
    for mid in ids:
        p = priors.marker(mid)
        known = mid in survey and p.known
        if known:
            R0, c0 = survey[mid]
            kept.append(mid)
            R_m.append(R0)
            t_m.append(c0)
            sig.append((math.radians(p.sigma_deg), p.sigma_m))
            if mid in starts and len(views[mid]) >= 5:
                centres = np.array([c for _, c in views[mid]])
                spread = float(np.linalg.norm(np.median(np.abs(centres - starts[mid][1]), axis=0)))
                d = np.linalg.norm(starts[mid][1] - c0)
                if d > max(moved_m, 5 * p.sigma_m * math.sqrt(3), 4 * spread):
                    start_moved[mid] = starts[mid]
        else:
            if mid not in starts:
                continue
            kept.append(mid)
            R_m.append(starts[mid][0])
            t_m.append(starts[mid][1])
            sig.append((math.inf, math.inf))
    ids = kept
    index = {mid: i for i, mid in enumerate(ids)}
    cols: dict[str, list[np.ndarray]] = {
        k: [] for k in ("kf", "cam", "mk", "corner", "uv", "R_D", "t_D", "om", "vel", "w")
    }
    for k, kf in enumerate(keyframes):
        for v in kf.views:
            keep = np.array([int(i) in index for i in v.ids], bool)
            n = int(keep.sum())
            if not n:
                continue
            mk = np.array([index[int(i)] for i in v.ids[keep]])
            cols["kf"].append(np.full(4 * n, k))
            cols["cam"].append(np.full(4 * n, v.camera))
            cols["mk"].append(np.repeat(mk, 4))
            cols["corner"].append(np.tile(np.arange(4), n))
            cols["uv"].append(v.corners[keep].reshape(-1, 2))
            cols["R_D"].append(np.repeat(v.R_D[None], 4 * n, 0))
            cols["t_D"].append(np.repeat(v.t_D[None], 4 * n, 0))
            cols["om"].append(np.repeat(v.omega[None], 4 * n, 0))
            cols["vel"].append(np.repeat(v.vel[None], 4 * n, 0))
            cols["w"].append(np.full(4 * n, v.weight))
    if not cols["kf"]:
        raise ValueError("no marker corners in the keyframes")
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    obs = Observations(
        cat["kf"],
        cat["cam"],
        cat["mk"],
        cat["corner"],
        cat["uv"],
        cat["R_D"],
        cat["t_D"],
        cat["om"],
        cat["vel"],
        cat["w"],
    )
    prob = Problem(
        ids,
        np.array(R_m),
        np.array(t_m),
        np.array(sig, float).reshape(-1, 2),
        length,
        cameras,
        np.array([kf.R_wb for kf in keyframes]),
        np.array([kf.t_wb for kf in keyframes], float),
        obs,
        priors,
    )
    return prob, start_moved


# --- a capture: keyframes from the first tracking pass, the refined experiment ---------------------


def motion_at(
    times: np.ndarray, t_grid: np.ndarray, pos: np.ndarray, R: np.ndarray, dt: float = 1 / 60
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bundle pose and velocity at ``times`` from a trajectory: (R, p, omega_world, v_world, ok)."""
    from annotator.core.trajectory import Trajectory

    times = np.asarray(times, float)
    traj = Trajectory(np.asarray(t_grid, float), pos, R)
    p0, R0, ok0 = traj.interpolate(times)
    pa, Ra, oka = traj.interpolate(times - dt)
    pb, Rb, okb = traj.interpolate(times + dt)
    ok = ok0 & oka & okb
    omega = np.zeros((len(times), 3))
    vel = np.zeros((len(times), 3))
    if ok.any():
        # R(t + dt) = exp(w dt) R(t): world-frame angular velocity.
        omega[ok] = Rotation.from_matrix(Rb[ok] @ np.transpose(Ra[ok], (0, 2, 1))).as_rotvec() / (
            2 * dt
        )
        vel[ok] = (pb[ok] - pa[ok]) / (2 * dt)
    return R0, p0, omega, vel, ok


def predicted_smear_px(
    world: np.ndarray,
    R_wb: np.ndarray,
    p_wb: np.ndarray,
    omega: np.ndarray,
    vel: np.ndarray,
    R_bc: np.ndarray,
    t_bc: np.ndarray,
    focal: float,
    exposure_s: float,
) -> float:
    """How far (px) the fastest of these world points smears across the image during one exposure.

    The motion-blur measure: the bundle moving at (omega, vel) for ``exposure_s`` moves each point's
    pinhole image by this much (a lens' distortion changes it by a few per cent only).
    """
    pts = np.asarray(world, float).reshape(-1, 3)
    if not len(pts) or exposure_s <= 0:
        return 0.0

    def image(Rw: np.ndarray, pw: np.ndarray) -> np.ndarray:
        Xc = ((pts - pw) @ Rw @ R_bc) - t_bc @ R_bc  # R_bc^T (R_wb^T (X - p) - t_bc)
        z = np.maximum(Xc[:, 2], 1e-3)
        return Xc[:, :2] / z[:, None]

    R1 = Rotation.from_rotvec(omega * exposure_s).as_matrix() @ R_wb
    d = image(R1, p_wb + vel * exposure_s) - image(R_wb, p_wb)
    return float(focal * np.max(np.linalg.norm(d, axis=1)))


def blur_weight(smear_px: float, scale_px: float = 2.0) -> float:
    """Weight of a frame's corners given its predicted smear: 1 when sharp, ~(scale/smear)^2 when not."""
    return 1.0 / (1.0 + (smear_px / scale_px) ** 2)


def camera_params(rig_cam: RigCamera) -> CameraParams:
    cal = rig_cam.calibration
    return CameraParams(
        rig_cam.name,
        rig_cam.R_bundle_camera,
        rig_cam.t_bundle_camera,
        cal.camera_matrix,
        np.asarray(cal.dist_coeffs, float),
        cal.model,
        cal.readout_s,
        cal.height,
        cal.corner_bias_px,
    )


def select_keyframes(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_grid: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    settings: RefineSettings,
) -> list[Keyframe]:
    """Keyframes over the capture: frames of the first camera with the other cameras' nearest
    frames, where the first pass has a pose, enough markers are seen and blur is small."""
    base = frames[0]
    if not len(base.t):
        return []
    cams = [exp.rig.cameras[cf.camera] for cf in frames]
    focal = [
        float(np.sqrt(c.calibration.camera_matrix[0, 0] * c.calibration.camera_matrix[1, 1]))
        for c in cams
    ]
    Rk, pk, om, vel, ok = motion_at(base.t, t_grid, pos, R)
    counts = np.array([len(d.ids) for d in base.detections])
    partner: list[list[tuple[int, int]]] = [[(0, k)] for k in range(len(base.t))]
    for ci, cf in enumerate(frames[1:], 1):
        if not len(cf.t):
            continue
        order = np.argsort(cf.t, kind="stable")  # each base frame's nearest frame of this camera
        ts = cf.t[order]
        right = np.searchsorted(ts, base.t).clip(0, len(ts) - 1)
        left = (right - 1).clip(0)
        near = np.where(np.abs(ts[left] - base.t) <= np.abs(ts[right] - base.t), left, right)
        for k in np.flatnonzero(np.abs(ts[near] - base.t) <= 0.5 * base.frame_interval).tolist():
            j = int(order[near[k]])
            partner[k].append((ci, j))
            counts[k] += len(cf.detections[j].ids)
    cand = np.flatnonzero(ok & (counts >= settings.min_markers))
    if not len(cand):
        return []
    # The keyframes are spread over the whole capture: scoring the blur of an evenly spread subset
    # of 8 candidates per keyframe keeps a long capture's cost flat and still leaves sharp ones.
    if len(cand) > 8 * settings.max_keyframes:
        cand = cand[
            np.unique(np.linspace(0, len(cand) - 1, 8 * settings.max_keyframes).round().astype(int))
        ]
    # Prefer sharp frames: drop the candidates whose predicted smear is too large.
    room_centres = {int(m): np.asarray(p.position, float) for m, p in exp.markers.markers.items()}
    sharp = []
    for k in cand.tolist():
        det = base.detections[k]
        pts = np.array([room_centres[int(i)] for i in det.ids if int(i) in room_centres]).reshape(
            -1, 3
        )
        smear = predicted_smear_px(
            pts,
            Rk[k],
            pk[k],
            om[k],
            vel[k],
            cams[0].R_bundle_camera,
            cams[0].t_bundle_camera,
            focal[0],
            settings.exposure_s,
        )
        if smear <= settings.max_smear_px:
            sharp.append((k, smear))
    if len(sharp) < max(10, len(cand) // 5):  # a fast walk throughout: take the sharpest fifth
        sharp = []
        for k in cand.tolist():
            sharp.append((k, 0.0))
    pick = (
        np.linspace(0, len(sharp) - 1, min(settings.max_keyframes, len(sharp))).round().astype(int)
    )
    chosen = [sharp[i] for i in np.unique(pick)]
    times = np.array([frames[ci].t[j] for k, _ in chosen for ci, j in partner[k]])
    Rj, pj, omj, velj, okj = motion_at(times, t_grid, pos, R)
    out, n = [], 0
    for k, smear in chosen:
        kf_views = []
        R0, p0 = Rk[k], pk[k]
        for ci, j in partner[k]:
            i, n = n, n + 1
            if not okj[i]:
                continue
            det = frames[ci].detections[j]
            kf_views.append(
                FrameView(
                    ci,
                    det.ids,
                    det.corners,
                    R0.T @ Rj[i],
                    R0.T @ (pj[i] - p0),
                    R0.T @ omj[i],
                    R0.T @ velj[i],
                    blur_weight(smear),
                )
            )
        out.append(Keyframe(R0, p0, kf_views))
    return out


@dataclass(frozen=True, eq=False)
class Refinement:
    """What refining a capture produced: the experiment to track with, the record, covariances."""

    experiment: Experiment  # with the refined map, rig and calibrations
    solution: Solution
    covariance: ParameterCovariance
    report: dict[str, Any]
    mapped: list[int]  # markers the survey did not give, now mapped from the video


def refine_capture(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_grid: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    settings: RefineSettings | None = None,
    initial: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Refinement | None:
    """Refine the experiment's map (mode map) and rig, lenses, readouts (mode all) from a first pass.

    ``initial``: start poses (R_world_marker, centre) of markers the survey lacks, from an
    earlier round."""
    from dataclasses import replace

    from annotator.core.experiment import MarkerSetup, Rig
    from annotator.vision.geometry import MarkerRoom
    from bgt_core.formats.markers import MarkerPose

    s = (settings or RefineSettings()).validate()
    t0 = time.perf_counter()
    keyframes = select_keyframes(frames, exp, t_grid, pos, R, s)
    if len(keyframes) < 5:
        log.warning(
            "refine: only %d usable keyframes; the given map, rig and lenses are kept",
            len(keyframes),
        )
        return None
    cams = [camera_params(exp.rig.cameras[cf.camera]) for cf in frames]
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    survey = {
        int(m): (room.R_world_marker[i], room.t_world_marker[i]) for i, m in enumerate(room.ids)
    }
    prob, starts = build_problem(
        survey, exp.markers.length, cams, keyframes, exp.priors, initial=initial
    )
    sol = solve(prob, s, starts)
    euler = Rotation.from_matrix(sol.R_m).as_euler("xyz")
    markers = dict(exp.markers.markers)
    mapped = []
    for m, mid in enumerate(prob.markers):
        if mid not in markers:
            mapped.append(mid)
        markers[mid] = MarkerPose.from_values(mid, sol.t_m[m], euler[m])
    rig = dict(exp.rig.cameras)
    for c, cf in enumerate(frames):
        rc, new = rig[cf.camera], sol.cameras[c]
        # The corner bias is estimated (it keeps small markers from looking too far away in the
        # adjustment) and reported, but not applied to the final pass: its frames see several
        # markers each, where a constant correction of a bias that varies with a marker's size
        # in the image removes no more error than it adds (measured on the renders).
        cal = replace(
            rc.calibration, camera_matrix=new.K, dist_coeffs=new.dist, readout_s=new.readout_s
        )
        rig[cf.camera] = replace(
            rc, calibration=cal, R_bundle_camera=new.R_bc, t_bundle_camera=new.t_bc
        )
    refined = replace(
        exp,
        markers=MarkerSetup(markers, exp.markers.dictionary, exp.markers.length),
        rig=Rig(rig, exp.rig.source),
    )
    report = refinement_report(
        prob, sol, cams, exp, s, len(keyframes), mapped, time.perf_counter() - t0
    )
    return Refinement(refined, sol, sol.covariance, report, mapped)


def refinement_report(
    prob: Problem,
    sol: Solution,
    cams: list[CameraParams],
    exp: Experiment,
    s: RefineSettings,
    n_keyframes: int,
    mapped: list[int],
    seconds: float,
) -> dict[str, Any]:
    """report.json's ``refinement`` section."""
    cameras = {}
    for a, b in zip(cams, sol.cameras, strict=True):
        cov = sol.covariance
        ro = cov.readout.get(a.name)
        cameras[a.name] = {
            "rms_px_before": round(sol.rms_before[a.name], 3),
            "rms_px_after": round(sol.rms_after[a.name], 3),
            "rig_rotation_change_deg": [
                round(float(v), 4)
                for v in np.degrees(Rotation.from_matrix(b.R_bc @ a.R_bc.T).as_rotvec())
            ],
            "rig_position_change_m": [round(float(v), 5) for v in b.t_bc - a.t_bc],
            "focal_change_rel": [
                round(float(b.K[0, 0] / a.K[0, 0] - 1), 6),
                round(float(b.K[1, 1] / a.K[1, 1] - 1), 6),
            ],
            "principal_change_px": [
                round(float(b.K[0, 2] - a.K[0, 2]), 3),
                round(float(b.K[1, 2] - a.K[1, 2]), 3),
            ],
            "distortion_change": [
                round(float(v), 6) for v in np.asarray(b.dist) - np.asarray(a.dist)
            ],
            "readout_s": round(b.readout_s, 5),
            "corner_bias_px": round(b.corner_bias_px, 3),
            "readout_sigma_s": None if ro is None else round(float(np.sqrt(ro[0, 0])), 5),
        }
    moved = []
    for mid in sol.moved:
        m = prob.markers.index(mid)
        moved.append(
            {
                "id": int(mid),
                "offset_m": [round(float(v), 4) for v in sol.t_m[m] - prob.t_m[m]],
                "survey_sigma_m": float(prob.marker_sigma[m, 1]),
                "note": "moved since the survey?",
            }
        )
    seen = sorted(int(prob.markers[m]) for m in np.unique(prob.obs.marker))
    return {
        "mode": s.mode,
        "keyframes": n_keyframes,
        "corners": int(len(prob.obs.uv)),
        "markers_seen": seen,
        "iterations": sol.iterations,
        "seconds": round(seconds, 2),
        "corner_sigma_px": round(sol.sigma_px, 3),
        "cameras": cameras,
        "markers_mapped": [int(m) for m in mapped],
        "markers_moved": moved,
    }
