"""The parameters' covariance through each frame's pose: per-frame Jacobians of the corner
residuals w.r.t. the pose (J) and the parameters (B), ``A = (J^T W J)^-1 J^T W B``, and
``Cov(d) = A Sigma A^T``, jointly over the blocks when a refinement's record allows; the rest on a
jig conditions it."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from annotator.core.experiment import CameraCalibration, Experiment
from annotator.core.priors import PRINTED_SCALE, ParameterCovariance
from annotator.core.rolling_shutter import row_delay
from annotator.core.uncertainty.records import BLOCKS, UncertaintySettings, VideoFrames
from annotator.core.uncertainty.views import FrameView, trajectory_twist, views_at
from annotator.vision.geometry import MarkerRoom, marker_corners_local, skew
from annotator.vision.lens import undistort_points

if TYPE_CHECKING:
    pass


def parameter_covariance(
    exp: Experiment, params: ParameterCovariance | None = None
) -> ParameterCovariance:
    """``params`` if given (e.g. from refinement), else the experiment's priors."""
    if params is not None:
        return params
    cams = {name: cam.calibration.camera_matrix for name, cam in exp.rig.cameras.items()}
    return ParameterCovariance.from_priors(exp.priors, sorted(exp.markers.markers), cams)


def _distortion(params: ParameterCovariance) -> dict[str, np.ndarray]:
    """Distortion covariances per camera when the record has them (refinement), else none."""
    return dict(getattr(params, "distortion", None) or {})


def _readout(params: ParameterCovariance) -> dict[str, np.ndarray]:
    """(1, 1) readout variances (s^2) per camera when the record has them (refinement), else none."""
    return dict(getattr(params, "readout", None) or {})


def _sqrt_psd(cov: np.ndarray) -> np.ndarray:
    """A square root S of a covariance (S S^T = cov), tolerant of singular ones."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    return vecs * np.sqrt(np.maximum(vals, 0.0))[None, :]


def block_diag(*mats: np.ndarray) -> np.ndarray:
    """The matrices on the diagonal of one zero matrix (scipy's block_diag without its checks:
    it runs for every row of a trajectory)."""
    rows = sum(m.shape[0] for m in mats)
    cols = sum(m.shape[1] for m in mats)
    out = np.zeros((rows, cols))
    r = c = 0
    for m in mats:
        out[r : r + m.shape[0], c : c + m.shape[1]] = m
        r += m.shape[0]
        c += m.shape[1]
    return out


@dataclass(frozen=True, eq=False)
class ViewBlock:
    """One view's residuals and Jacobians (rows: its corners' x, y in order)."""

    camera: str
    r: np.ndarray  # (2m,)
    J: np.ndarray  # (2m, 6)
    markers: list[
        tuple[int, int, np.ndarray]
    ]  # (marker id, first row, (8, 6) block) of mapped markers
    Br: np.ndarray  # (2m, 6)
    Bi: np.ndarray  # (2m, 4)
    Bro: np.ndarray  # (2m,)
    Bb: np.ndarray  # (2m,) w.r.t. the detector's corner bias (px along each square's diagonal)
    Bs: np.ndarray  # (2m,) w.r.t. the markers' printed size (relative; every mapped marker's)
    inner: np.ndarray  # (n,) per marker: residual energy left after its own rigid motion
    speed: np.ndarray  # (m,) image speed, px/s
    n_markers: int


@dataclass(eq=False)
class JacobianCache:
    """What ``frame_jacobians`` keeps between the rows of one capture, which share views and the
    one parameter record: each view's blocks, each covariance's square root, and each lens with
    one distortion coefficient moved."""

    views: dict[int, ViewBlock | None] = field(default_factory=dict)  # by id() of the view
    # by id() of the covariance, which is kept with its root so that the id cannot be reused
    roots: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    lenses: dict[tuple[int, int, float], tuple[CameraCalibration, CameraCalibration]] = field(
        default_factory=dict
    )

    def root(self, cov: np.ndarray) -> np.ndarray:
        """``_sqrt_psd(cov)``, worked out once per covariance array."""
        held = self.roots.get(id(cov))
        if held is None or held[0] is not cov:
            held = (cov, _sqrt_psd(cov))
            self.roots[id(cov)] = held
        return held[1]

    def moved_lens(self, cal: CameraCalibration, j: int, step: float) -> CameraCalibration:
        """``cal`` with distortion coefficient ``j`` moved by ``step``, made once per capture."""
        key = (id(cal), j, step)
        held = self.lenses.get(key)
        if held is None or held[0] is not cal:
            coeffs = cal.dist_coeffs.astype(float)
            coeffs[j] += step
            held = (cal, replace(cal, dist_coeffs=coeffs))
            self.lenses[key] = held
        return held[1]


def _view_block(
    v: FrameView, room: MarkerRoom, params: ParameterCovariance, cache: JacobianCache
) -> ViewBlock | None:
    idx = room.index(v.ids)
    keep = idx >= 0
    if not keep.any():
        return None
    ids, pix, idx = v.ids[keep], v.pixels[keep], idx[keep]
    bias = float(getattr(v.cal, "corner_bias_px", 0.0) or 0.0)
    d_c = pix - pix.mean(axis=1, keepdims=True)
    diag = d_c / np.maximum(np.linalg.norm(d_c, axis=2, keepdims=True), 1e-9)
    if bias:  # a refined detector corner bias: each corner back along its square's diagonal
        pix = pix - bias * diag
    K = v.cal.camera_matrix
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    # One undistortion for every set of pixels this lens is asked about: the corners; the corners
    # as each of fx, fy, cx, cy moved by +-step sees them (a camera matrix K' reads pixel p as
    # K'^-1 p, which K reads from the pixel K K'^-1 p); the corners moved +-h along their
    # square's diagonal (the corner bias; only a refinement's joint record correlates it).
    sets = [pix]
    k_steps = None
    if v.camera in params.intrinsics:
        k_steps = np.sqrt(np.maximum(np.diag(params.intrinsics[v.camera]), 1e-12)) * 0.1
        Ks = np.repeat(K[None].astype(float), 8, axis=0)
        for j, (r_, c_) in enumerate(((0, 0), (1, 1), (0, 2), (1, 2))):
            Ks[2 * j, r_, c_] += k_steps[j]
            Ks[2 * j + 1, r_, c_] -= k_steps[j]
        ph = np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], axis=-1)
        moved = np.einsum("sij,...j->s...i", K @ np.linalg.inv(Ks), ph)
        sets += list(moved[..., :2] / moved[..., 2:])
    h = 0.05
    with_bias = getattr(params, "joint", None) is not None
    if with_bias:
        sets += [pix + h * diag, pix - h * diag]
    undone = undistort_points(v.cal, np.stack(sets)).reshape(len(sets), -1, 2)
    xn = undone[0]
    Xw = room.corners_world[idx].reshape(-1, 3)
    d = Xw - v.t_wb
    e = d @ v.R_wb - v.t_bc  # bundle frame, from the camera centre
    Xc = e @ v.R_bc
    z = Xc[:, 2]
    if np.any(z <= 1e-6):
        return None
    proj = Xc[:, :2] / z[:, None]
    m = len(z)
    dp = np.zeros((m, 2, 3))
    dp[:, 0, 0] = 1 / z
    dp[:, 1, 1] = 1 / z
    dp[:, :, 2] = -proj / z[:, None]
    b_cam = focal * dp @ v.R_bc.T  # d pixels / d bundle-frame point
    a = b_cam @ v.R_wb.T  # d pixels / d world point
    J = np.concatenate([a @ skew(d), -a], axis=2)  # world-frame rotation, then position
    r = focal * (proj - xn)
    # Markers: corner = exp(w) (c - centre) + centre + dp -> d corner = -skew(c - centre) w + dp.
    rel = np.einsum(
        "mij,kj->mki", room.R_world_marker[idx], marker_corners_local(room.length)
    ).reshape(-1, 3)
    Bm = np.concatenate([-a @ skew(rel), a], axis=2)  # (m, 2, 6)
    # Corner noise: what is left of each square's residual after its own rigid motion (the map
    # error of one marker is exactly such a motion): 2 of its 8 degrees of freedom.
    Mk = Bm.reshape(len(ids), 8, 6)
    rk = r.reshape(len(ids), 8)
    G = np.einsum("kij,kil->kjl", Mk, Mk) + 1e-9 * np.eye(6)
    xk = np.linalg.solve(G, np.einsum("kij,ki->kj", Mk, rk)[..., None])[..., 0]
    inner = np.sum((rk - np.einsum("kij,kj->ki", Mk, xk)) ** 2, axis=1)
    markers = [(int(mid), 8 * k, Mk[k]) for k, mid in enumerate(ids) if int(mid) in params.markers]
    # Rig: R_bc = exp(w) R_bc0, t_bc + dt -> the corner moves by skew(e) w - dt in the camera's eyes.
    Br = np.concatenate([b_cam @ skew(e), -b_cam], axis=2).reshape(-1, 6)
    # Intrinsics (and distortion, when the record has it): the observation moves;
    # r = focal (proj - xn) -> dr = -focal dxn.
    dist_cov = _distortion(params).get(v.camera)
    nd = 0 if dist_cov is None else len(dist_cov)
    Bi = np.zeros((2 * m, 4 + nd))
    if k_steps is not None:
        for j in range(4):
            dxn = (undone[1 + 2 * j] - undone[2 + 2 * j]) / (2 * k_steps[j])
            Bi[:, j] = -focal * dxn.ravel()
    if dist_cov is not None and nd:
        steps = np.sqrt(np.maximum(np.diag(dist_cov), 1e-12)) * 0.1
        for j in range(min(nd, len(v.cal.dist_coeffs))):
            xp = undistort_points(cache.moved_lens(v.cal, j, steps[j]), pix)
            xm = undistort_points(cache.moved_lens(v.cal, j, -steps[j]), pix)
            Bi[:, 4 + j] = -focal * ((xp - xm).reshape(-1, 2) / (2 * steps[j])).ravel()
    # Readout: row v is seen readout * v / H later; dr/dreadout = -J twist * v / H.
    img_vel = J @ v.twist  # (m, 2) pixels per second
    rows_frac = row_delay(pix.reshape(-1, 2)[:, 1], v.cal.height, 1.0)
    Bro = -(img_vel * rows_frac[:, None]).reshape(-1)
    # Corner bias: a larger bias moves every corrected corner further towards its square's centre.
    # Only a refinement's joint record correlates the bias with the rest (see _row_joint).
    Bb = (
        (focal / (2 * h)) * (undone[-2] - undone[-1]).reshape(-1)
        if with_bias
        else np.zeros(pix.size)
    )
    # Printed size: a relative change s of every marker's side moves each corner by s times its
    # offset from the marker's centre (the map's markers only).
    Bs = np.einsum("mij,mj->mi", a, rel).reshape(-1)
    Bs[np.repeat(~np.isin(ids, list(params.markers)), 8)] = 0.0
    return ViewBlock(
        v.camera,
        r.reshape(-1),
        J.reshape(-1, 6),
        markers,
        Br,
        Bi,
        Bro,
        Bb,
        Bs,
        inner,
        np.linalg.norm(img_vel, axis=1),
        len(ids),
    )


@dataclass(frozen=True, eq=False)
class FrameJacobians:
    """Residuals, weights and the pose / parameter Jacobians of one output row's frames."""

    r: np.ndarray  # (m,) pixel residuals
    w: np.ndarray  # (m,) robust weights
    J: np.ndarray  # (m, 6) w.r.t. the bundle pose
    B: dict[str, np.ndarray]  # block -> (m, k) w.r.t. the block's parameters
    L: dict[str, np.ndarray]  # block -> (k, k) square root of the block's covariance
    image_speed: np.ndarray  # (m/2,) px/s
    noise2: float  # corner noise variance, px^2
    # Covariance over all blocks' columns (BLOCKS order, then the corner bias) when the record
    # correlates them (refinement); None: the blocks are independent, L alone describes them.
    joint: np.ndarray | None = None
    # For each of those columns its row in the record's joint covariance (-1: not in the record).
    joint_rows: np.ndarray | None = None


def frame_jacobians(
    views: Sequence[FrameView],
    room: MarkerRoom,
    params: ParameterCovariance,
    readout_sigma_s: float,
    settings: UncertaintySettings,
    cache: JacobianCache | None = None,
) -> FrameJacobians | None:
    """Residuals, weights and the pose / parameter Jacobians of one output row's frames.

    Returns None without usable corners. ``cache`` keeps what rows share (pass one per capture
    and parameter record).
    """
    cache = cache or JacobianCache()
    blocks = []
    for v in views:
        if id(v) in cache.views:
            vb = cache.views[id(v)]
        else:
            vb = _view_block(v, room, params, cache)
            cache.views[id(v)] = vb
        if vb is not None:
            blocks.append(vb)
    starts = np.cumsum([0] + [len(b.r) for b in blocks])
    n0 = int(starts[-1])
    if n0 < 8:
        return None
    r = np.concatenate([b.r for b in blocks])
    J = np.concatenate([b.J for b in blocks])
    # Robust weights: Huber on each corner, no weight for a marker far off the others.
    corner_norm = np.linalg.norm(r.reshape(-1, 2), axis=1)
    marker_of = np.repeat(np.arange(sum(b.n_markers for b in blocks)), 4)
    n_mk = int(marker_of.max()) + 1
    mk_rms = np.sqrt(np.bincount(marker_of, corner_norm**2, n_mk) / 4.0)
    limit = max(settings.marker_gate_px, 4.0 * float(np.median(mk_rms)))
    wc = np.where(
        corner_norm <= settings.huber_px, 1.0, settings.huber_px / np.maximum(corner_norm, 1e-12)
    )
    good_mk = mk_rms <= limit
    wc = wc * good_mk[marker_of]
    e_inner = np.concatenate([b.inner for b in blocks])[good_mk]
    w = np.repeat(wc, 2)
    B: dict[str, np.ndarray] = {}
    L: dict[str, np.ndarray] = {}
    mids = sorted({mid for b in blocks for mid, _, _ in b.markers})
    if mids:
        col = {mid: c for c, mid in enumerate(mids)}
        Bmk = np.zeros((n0, 6 * len(mids)))
        for b, a0 in zip(blocks, starts, strict=False):
            for mid, first, blk in b.markers:
                Bmk[a0 + first : a0 + first + 8, 6 * col[mid] : 6 * col[mid] + 6] = blk
        B["markers"] = Bmk
        L["markers"] = block_diag(*[cache.root(params.markers[mid]) for mid in mids])
    cams = sorted({b.camera for b in blocks})
    Brig = np.zeros((n0, 6 * len(cams)))
    width = {c: next(b.Bi.shape[1] for b in blocks if b.camera == c) for c in cams}
    col0 = dict(zip(cams, np.cumsum([0] + [width[c] for c in cams])[:-1], strict=True))
    Bint = np.zeros((n0, sum(width.values())))
    readouts = _readout(params)
    Bro = np.zeros((n0, len(cams) if readouts else 1))
    for b, a0 in zip(blocks, starts, strict=False):
        c = cams.index(b.camera)
        a1 = a0 + len(b.r)
        Brig[a0:a1, 6 * c : 6 * c + 6] = b.Br
        Bint[a0:a1, col0[b.camera] : col0[b.camera] + width[b.camera]] = b.Bi
        Bro[a0:a1, c if readouts else 0] = b.Bro
    B["rig"] = Brig
    L["rig"] = block_diag(
        *[cache.root(params.rig[c]) if c in params.rig else np.zeros((6, 6)) for c in cams]
    )
    B["intrinsics"] = Bint
    dist = _distortion(params)
    L["intrinsics"] = block_diag(
        *[
            block_diag(
                cache.root(params.intrinsics[c]) if c in params.intrinsics else np.zeros((4, 4)),
                cache.root(dist[c]) if width[c] > 4 else np.zeros((0, 0)),
            )
            for c in cams
        ]
    )
    # Readout: refined per camera when the record has it; otherwise one error shared by all
    # cameras (a rig's cameras are usually the same model, their readout unknown alike).
    B["readout"] = Bro
    L["readout"] = (
        np.diag(
            [math.sqrt(float(np.ravel(readouts[c])[0])) if c in readouts else 0.0 for c in cams]
        )
        if readouts
        else np.array([[readout_sigma_s]])
    )
    speeds = np.concatenate([b.speed for b in blocks])
    joint, rows = None, None
    if settings.joint_covariance and getattr(params, "joint", None) is not None:
        joint, rows = _row_joint(params, B, L, blocks, starts, mids, cams, width, n0)
    noise2 = float(e_inner.sum()) / max(2 * len(e_inner), 1)
    return FrameJacobians(r, w, J, B, L, speeds, noise2, joint, rows)


def _joint_rows(
    params: ParameterCovariance, kind: str, keys: Sequence[int | str], size: Sequence[int]
) -> np.ndarray:
    """Rows of the joint record for each key's block in turn (-1 where the record has none)."""
    out = [np.zeros(0, int)]
    for key, n in zip(keys, size, strict=True):
        idx = params.joint_index.get((kind, key))
        out.append(
            np.asarray(idx[:n], int) if idx is not None and len(idx) >= n else np.full(n, -1)
        )
    return np.concatenate(out)


def _row_joint(
    params: ParameterCovariance,
    B: dict[str, np.ndarray],
    L: dict[str, np.ndarray],
    blocks: Sequence[ViewBlock],
    starts: np.ndarray,
    mids: Sequence[int],
    cams: Sequence[str],
    width: Mapping[str, int],
    n0: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The row's parameter covariance over the columns of B (BLOCKS order, then the corner bias and
    the printed size, added to B here): each block's own L L^T, overwritten wherever the joint
    record has the rows (cross-block terms included); and each column's row in the record (-1:
    none)."""
    assert params.joint is not None
    where = [
        _joint_rows(params, "markers", mids, [6] * len(mids)),
        _joint_rows(params, "rig", cams, [6] * len(cams)),
        np.concatenate(
            [
                np.concatenate(
                    [
                        _joint_rows(params, "intrinsics", [c], [4]),
                        _joint_rows(params, "distortion", [c], [width[c] - 4]),
                    ]
                )
                for c in cams
            ]
        ),
        _joint_rows(params, "readout", cams, [1] * len(cams))
        if B["readout"].shape[1] == len(cams) and _readout(params)
        else np.full(B["readout"].shape[1], -1),
    ]
    roots = [L[b] if b in L else np.zeros((0, 0)) for b in BLOCKS]
    bias_at = _joint_rows(params, "bias", cams, [1] * len(cams))
    if (bias_at >= 0).any():
        Bb = np.zeros((n0, len(cams)))
        for b, a0 in zip(blocks, starts, strict=False):
            Bb[a0 : a0 + len(b.r), list(cams).index(b.camera)] = b.Bb
        B["bias"] = Bb
        roots.append(np.zeros((len(cams), len(cams))))
        where.append(bias_at)
    scale_at = params.joint_index.get(PRINTED_SCALE)
    if scale_at is not None and len(scale_at) == 1:
        B["scale"] = np.concatenate([b.Bs for b in blocks])[:, None]
        roots.append(np.zeros((1, 1)))
        where.append(np.asarray(scale_at, int))
    cov = block_diag(*[Lk @ Lk.T for Lk in roots])
    idx = np.concatenate(
        [np.zeros(0, int)] + [w for w, Lk in zip(where, roots, strict=True) if Lk.shape[0]]
    )
    idx = idx.astype(int)
    have = np.flatnonzero(idx >= 0)
    cov[np.ix_(have, have)] = params.joint[np.ix_(idx[have], idx[have])]
    return cov, idx


def propagate(jac: FrameJacobians) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """(4,) per-axis position variance per block, (4,) predicted residual energy per block, the
    observed residual energy after a per-frame fit beyond the corner noise's share, and the noise's
    degrees of freedom."""
    r, w, J = jac.r, jac.w, jac.J
    sw = np.sqrt(w)
    Jw = J * sw[:, None]
    H = Jw.T @ Jw
    try:
        Hinv = np.linalg.inv(H + 1e-12 * np.eye(6))
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(Hinv)):
        return None
    rw = r * sw
    proj = Jw @ (Hinv @ (Jw.T @ rw))
    e_obs = float(np.sum((rw - proj) ** 2))
    dof = float(np.sum(w) - 6)
    var = np.zeros(4)
    q = np.zeros(4)
    for k, name in enumerate(BLOCKS):
        Bk = jac.B.get(name)
        if Bk is None or Bk.shape[1] == 0:
            continue
        BL = (Bk * sw[:, None]) @ jac.L[name]
        A = Hinv @ (Jw.T @ BL)  # (6, k) pose change per unit-sigma parameter
        var[k] = float(np.sum(A[3:] ** 2)) / 3
        resid = BL - Jw @ A
        q[k] = float(np.sum(resid**2))
    if jac.joint is not None:
        # Correlated blocks (refinement): the pose error is A theta over all parameters at once,
        # so errors the refinement tied together cancel or add. Each block keeps its share of the
        # joint total (the cross terms spread in proportion to the blocks' own variances).
        A, Bw = _joint_sensitivity(jac, sw, Jw, Hinv)
        resid = Bw - Jw @ A
        tot_var = max(float(np.trace(A[3:] @ jac.joint @ A[3:].T)) / 3, 0.0)
        tot_q = max(float(np.sum((resid @ jac.joint) * resid)), 0.0)  # trace(X C X^T)
        var = var * (tot_var / var.sum()) if var.sum() > 0 else np.array([tot_var, 0, 0, 0])
        q = q * (tot_q / q.sum()) if q.sum() > 0 else np.array([tot_q, 0, 0, 0])
    return var, q, e_obs - jac.noise2 * dof, dof


def _joint_sensitivity(
    jac: FrameJacobians, sw: np.ndarray, Jw: np.ndarray, Hinv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(6, k) pose change (rotation, position) per unit error of each column of jac.joint, and
    those columns' weighted residual Jacobian (m, k)."""
    extra = ("bias", "scale")  # columns only a joint record has (_row_joint)
    names = [b for b in (*BLOCKS, *extra) if b in jac.B and (b in extra or b in jac.L)]
    Bw = np.concatenate([jac.B[b] for b in names], axis=1) * sw[:, None]
    return Hinv @ (Jw.T @ Bw), Bw


def condition_on_rest(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_out: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    params: ParameterCovariance,
    rows: np.ndarray,
    variance: np.ndarray,
    settings: UncertaintySettings | None = None,
) -> ParameterCovariance:
    """``params`` after the bundle's pose over ``rows`` (a rest) was measured independently with
    per-axis ``variance`` (6,: rotation rad^2, then position m^2): a Kalman update of the record's
    joint covariance. The rest's mean pose error is H theta (H: the rows' mean sensitivity to the
    parameters); every parameter correlated with it (the rig's gauge, the map's datum and turn)
    loses what the rest pins down. Without a joint record, or no usable row, ``params`` as is."""
    s = settings or UncertaintySettings()
    P = params.joint
    if P is None or not s.joint_covariance or not rows.any():
        return params
    omega, vel = trajectory_twist(t_out, pos, R)
    sel = np.flatnonzero(rows)
    views = views_at(frames, exp, t_out[sel], pos[sel], R[sel], omega[sel], vel[sel])
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    H = np.zeros((6, P.shape[0]))
    used = 0
    cache = JacobianCache()
    for vs in views:
        jac = (
            frame_jacobians(vs, room, params, exp.priors.readout_sigma_s, s, cache) if vs else None
        )
        if jac is None or jac.joint_rows is None:
            continue
        sw = np.sqrt(jac.w)
        Jw = jac.J * sw[:, None]
        Hinv = np.linalg.pinv(Jw.T @ Jw)
        A, _ = _joint_sensitivity(jac, sw, Jw, Hinv)
        have = jac.joint_rows >= 0
        np.add.at(H.T, jac.joint_rows[have], A[:, have].T)
        used += 1
    if not used:
        return params
    H /= used
    PH = P @ H.T
    S = H @ PH + np.diag(variance)
    P_after = P - PH @ np.linalg.solve(S, PH.T)
    return replace(params, joint=0.5 * (P_after + P_after.T))
