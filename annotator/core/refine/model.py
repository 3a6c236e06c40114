"""The self-calibration's problem: settings, parameter blocks, projection and the model that
predicts every corner from the parameter deltas."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.priors import ParameterCovariance, Priors
from annotator.core.rolling_shutter import row_delay
from annotator.vision.geometry import marker_corners_local

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


# Block order in the static part of the parameter vector, per camera after the markers; then
# one block for all markers: their printed size relative to the length the experiment states.
RIG, INTR, DIST, READOUT, BIAS = "rig", "intr", "dist", "readout", "bias"
# Each camera's clock against the others' (with two or more cameras): the sync puts every video
# on the RSSI clock on its own, a few ms apart (a slate read to within a refresh, a cover edge).
# A frame seen this much later than its stamp looks, to the corners, like a readout that starts
# late: unmodelled it leans on the readout (on fast field walks 20-26 ms found for 15 true).
CLOCK = "clock"
SCALE = "scale"
# Prior sigma of a camera's clock offset from the mean of the cameras' (s) where each video was
# synchronised on its own by the clock slate: read to within a refresh (+-8.3 ms at 60 Hz).
CLOCK_SIGMA_S = 0.01
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
    CLOCK: 1e-6,
    BIAS: 1e-3,
    SCALE: 1e-6,
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
    # Each component of a camera's rig pose, lens, readout and corner bias the capture did not
    # show is held at its prior: its posterior sigma at least this share of its prior sigma (the
    # rig's mean over the cameras, which no image shows, is pinned by the gauge besides). What the
    # capture did show takes the data's estimate, significant or not: holding every correction
    # under 3 posterior sigmas kept a focal length 0.27 % off and readouts 6-8 ms off on a
    # straight push (2.12 -> 1.51 cm median; docs/annotator.md, "Self-calibration", the gate).
    observable_ratio: float = 0.5
    # These blocks also keep their prior unless the correction exceeds gate_sigma posterior
    # sigmas: the lens distortion (a walk shows it, but its corrections follow the corners'
    # errors at the image's edge, and a board calibration knows it better: a push-real render
    # 1.12 -> 0.90 cm with it gated), the cameras' clocks (the slate reads them to a frame; free,
    # they trade with the readouts) and the markers' printed size (a constant corner bias and the
    # size trade on exact prints: 0.15-0.6 % found for 0, about 2 sigma).
    gate_sigma: float = 3.0
    gate_blocks: tuple[str, ...] = (DIST, CLOCK, SCALE)
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
    # Divide the data's information in the joint record by the keyframes' corner-error correlation
    # time (solver._correlation_stretch). Off: with two refinement rounds it made sigma_m cautious
    # on every field walk (rms of error / sigma_m 0.78-0.88 over 5-30 s walks, 1.0 when honest);
    # without it 0.86-1.04 (docs/annotator.md, "What sigma_m means").
    keyframe_correlation: bool = False
    # When the walk maps markers the survey skipped, the joint record the trajectory inherits is
    # computed as if each seen surveyed marker's prior also held its floors: a mapped marker's
    # pose is the data's view of the surveyed ones carried over, so a few far surveyed markers pass
    # their size and slant floors on to it (12 s walks with 8 markers surveyed: rows within 2.8
    # sigma_m 78.4 -> 94.9 %). With every seen marker surveyed each is held by its own survey and
    # the floors only made sigma_m cautious (30 s: 99.5 -> 100 %, rms z 0.91 -> 0.82), so they stay
    # out there. The estimate keeps the survey's prior either way (docs/annotator.md).
    floors_in_record: bool = True
    exposure_s: float = 0.008  # assumed exposure for the motion-blur measure
    # Prior sigma of each camera's clock against the cameras' mean, s; 0 holds the clocks at the
    # sync's. Only where each video was synchronised on its own (the slate): with the hands cover
    # the cameras' errors are shared, and a free clock trades against the readout on short walks
    # (a 6 s walk on exact clocks: 13.4 / 19.9 ms found for 15).
    clock_sigma_s: float = 0.0
    max_smear_px: float = 3.0  # most keyframes are sharper than this (predicted smear) ...
    # ... and up to this share of them may be frames of a moving picture (turns: what shows the
    # readout), smeared up to max_turn_smear_px and weighted down by their smear.
    turn_share: float = 0.25
    min_turn_smear_px: float = 1.0
    max_turn_smear_px: float = 15.0

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
    clock_s: float = 0.0  # the camera's frames were seen this much later than their stamps


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
    # 1-sigma of the markers' printed size relative to ``length`` (a printer's scaling); 0: the
    # size is taken as exact and not estimated.
    length_sigma_rel: float = 0.0


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
    # The markers' printed size / the stated length as the data found it, its posterior 1-sigma
    # (NaN: not estimated), and whether the capture determined it (False: within noise of 1, the
    # stated length was kept; the map and lenses were then refined with it).
    length_scale: float = 1.0
    length_scale_sigma: float = float("nan")
    length_scale_determined: bool = False
    # Per camera and block (rig, intr, dist, readout, clock, bias): True when the capture determined
    # it (the correction was applied), False when it was within noise of its prior (kept).
    determined: dict[str, dict[str, bool]] = field(default_factory=dict)
    # Per camera: the posterior 1-sigma of its clock offset (s), where it was estimated.
    clock_sigma_s: dict[str, float] = field(default_factory=dict)


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


@dataclass(frozen=True, eq=False)
class Forward:
    """The stages of ``_Model.forward`` for N corners: the parameters' values, the corner in the
    world (X), in the keyframe's bundle frame (Yk), the motion to the corner's row time (R_D, t_D)
    and the bundle then (Y), in the camera (Xc, depth zs, pinhole xy), through the lens (xyd), and
    the pixels (uv, bias included) with the raw depth z."""

    values: dict[str, np.ndarray]
    X: np.ndarray
    Yk: np.ndarray
    R_D: np.ndarray
    t_D: np.ndarray
    Y: np.ndarray
    Xc: np.ndarray
    zs: np.ndarray
    xy: np.ndarray
    dist: np.ndarray
    xyd: np.ndarray
    uv: np.ndarray
    z: np.ndarray


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
            if b == SCALE:  # one for all markers
                out[b] = (off, 1, 1)
                off += 1
                continue
            size = {RIG: 6, INTR: 4, DIST: self.nd, READOUT: 1, CLOCK: 1, BIAS: 1}[b]
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
        # Each corner's delay after its frame stamp per second of readout (its row's share).
        self.row = row_delay(o.uv[:, 1], np.array([c.height for c in cams])[o.camera], 1.0)
        self.models = sorted({c.model for c in cams})
        self.cam_model = np.array([c.model for c in cams])
        self._cache: dict[str, tuple[bytes, Any]] = {}
        # What the Jacobian derives once from the observations' layout (refine/jacobian.StaticSlots).
        self.patterns: dict[str, Any] = {}

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
            "clock": u.get(CLOCK, np.zeros((C, 1)))[:, 0],
            "bias": self.b0 + u.get(BIAS, np.zeros((C, 1)))[:, 0],
            "scale": 1.0 + u.get(SCALE, np.zeros((1, 1)))[:, 0],
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
        f = self.forward(x)
        return f.uv, f.z

    def forward(self, x: np.ndarray) -> Forward:
        """Every stage of the projection of every corner (``predict``'s pixels and depth with the
        values the analytic Jacobian differentiates)."""
        v = self.static_values(x)
        o = self.p.obs
        X = self._stage(
            "X",
            np.concatenate([v["R_m"].ravel(), v["t_m"].ravel(), v["scale"]]),
            lambda: _mv(v["R_m"][o.marker], self.local * v["scale"][0]) + v["t_m"][o.marker],
        )  # the corner in the world
        Yk = self._stage(
            "Yk",
            np.concatenate([X.ravel(), v["R_k"].ravel(), v["p_k"].ravel()]),
            lambda: _mtv(v["R_k"][o.keyframe], X - v["p_k"][o.keyframe]),
        )  # R_k^T (X - p_k)

        def motion() -> tuple[np.ndarray, np.ndarray]:
            # row_delay(row, height, readout), after the camera's clock offset
            tau = v["readout"][o.camera] * self.row + v["clock"][o.camera]
            return _rot(o.omega * tau[:, None]) @ o.R_D, o.t_D + o.vel * tau[:, None]

        R_D, t_D = self._stage("motion", np.concatenate([v["readout"], v["clock"]]), motion)
        Y = _mtv(R_D, Yk - t_D)
        c = o.camera
        Xc = _mtv(v["R_bc"][c], Y - v["t_bc"][c])
        z = Xc[:, 2]
        zs = np.where(np.abs(z) < 1e-6, 1e-6, z)
        xy = Xc[:, :2] / zs[:, None]
        dist = v["dist"][c]
        xyd = self.distort(xy, dist)
        Kc = v["K"][c]
        uv = np.stack([Kc[:, 0] * xyd[:, 0] + Kc[:, 2], Kc[:, 1] * xyd[:, 1] + Kc[:, 3]], axis=1)
        uv = uv + v["bias"][c][:, None] * self.diag
        return Forward(v, X, Yk, R_D, t_D, Y, Xc, zs, xy, dist, xyd, uv, z)

    def distort(self, xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """Each corner's normalised coordinates through its own camera's lens (dist: (N, nd))."""
        c = self.p.obs.camera
        xyd = np.empty_like(xy)
        for model in self.models:
            sel = self.cam_model[c] == model
            xyd[sel] = distort_normalised(xy[sel], dist[sel], model)
        return xyd
