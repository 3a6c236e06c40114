"""Marker corners from a model of the blurred image across each side, bits included.

The edge fit of :mod:`annotator.vision.corners` takes the centroid of the brightness gradient
across each side. That centroid lies on the edge only while the edge stands alone. On a small or
blurred marker it does not: one cell inside the outer edge the border meets the bits (white or
black, depending on the id), and one quiet-zone width outside it the paper meets the wall. Their
blur reaches the outer edge and pulls its centroid inward or outward by up to a few tenths of a
pixel, depending on the print, the blur and the bits (`bench/NOTES.md`, "Corner bias and the
profile model"). A bias that grows as markers shrink is what the self-calibration then reads as a
printed size, a focal length or a readout.

Here each side is described as what it is. Across the side, outward, the marker is a known
sequence of stripes one cell wide: the id's bits three cells deep, the black border, then the
white quiet zone, then the wall. Along the side, each bit cell is sampled at its centre, and the
blur along the side mixes in its neighbours' bits, which are known too. A Gaussian blur of width
sigma turns that into a sum of error functions. Per marker, a least-squares fit finds:
- the blur;
- the black and white levels;
- for each side, its offset and tilt, the cell width across it, and where the quiet zone ends and
  how bright the wall beyond it is.

Each side's fitted offsets are undistorted, a line is fitted through them, and adjacent lines
are intersected (:func:`annotator.vision.corners.corners_from_sides`).

Only the bits and a symmetric blur are assumed. No quiet-zone width, no contrast and no lighting
are assumed. A marker the model does not fit (too small to resolve its cells, cut by the frame, a
wrong id) is reported so, and the caller keeps the edge fit's corners for it.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.special import ndtr

from annotator.core.experiment import CameraCalibration
from annotator.vision.corners import (
    MARKER_CELLS,
    bilinear,
    corners_from_sides,
    fit_lines,
    in_frame,
)
from annotator.vision.lens import project_points, undistort_points

BITS = MARKER_CELLS - 2  # 6x6 data bits
_ACROSS = np.linspace(-2.5, 1.75, 29)  # profile across a side, in cells from its outer edge
_ALONG = (np.arange(1, BITS + 1) + 0.5) / MARKER_CELLS  # each bit cell's centre along a side
_DEPTH = 4  # stripes modelled inside the outer edge: the border and three rows of bits
_REACH = 3  # bit cells either side that the blur along a side mixes in
_NOISE = 3.0  # grey levels: the residual scale the priors below are weighed against
_ITERATIONS = (6, 3)  # Levenberg-Marquardt steps in the first and the second round
_MIN_CELL_PX = 1.6  # cells narrower than this across a side are not resolved: no fit
# Cells wider than this (on average over the marker) leave the outer edge alone at any blur the
# detector still reads: the edge fit is unbiased there, and the profile's samples would be too far
# apart to see a sharp edge (a 240 px marker came out 0.3 px inward). Those keep the edge fit.
_MAX_CELL_PX = 8.0
_MIN_CONTRAST = 20.0  # grey levels between the fitted black and white
_MAX_RMS = 0.2  # fitted residual RMS, as a share of that contrast, for the fit to count
_SQRT2PI = np.sqrt(2 * np.pi)


def marker_bits(dictionary: cv2.aruco.Dictionary, marker_id: int) -> np.ndarray:
    """(6, 6) bool, True where the marker's bit is white, in the marker's own orientation (row 0
    next to corner 0 -> 1, the side ArUco returns first)."""
    img = cv2.aruco.generateImageMarker(dictionary, int(marker_id), MARKER_CELLS)
    return np.asarray(img[1:-1, 1:-1] > 127)


def _side_stripes(bits: np.ndarray) -> np.ndarray:
    """(4, depth, 8) whiteness of the stripes inside each side: depth 0 is the border row, 1-3
    the bit rows behind it; along the side from corner i to corner i + 1, cells 0 and 7 being
    the border's."""
    full = np.zeros((MARKER_CELLS, MARKER_CELLS))
    full[1:-1, 1:-1] = bits
    # np.rot90(full, k)[d, a]: row d counted from side k inwards, column a along side k.
    return np.stack([np.rot90(full, k)[:_DEPTH] for k in range(4)])


def _along_mix(stripes: np.ndarray, blur_cells: np.ndarray) -> np.ndarray:
    """(n, 4, m, depth): each stripe's whiteness at each bit cell's centre after a Gaussian blur
    of ``blur_cells`` (n,) cells along the side; beyond the square's ends is the quiet zone."""
    pad = np.pad(stripes, ((0, 0),) * 3 + ((_REACH, _REACH),), constant_values=1.0)
    d = np.arange(-_REACH, _REACH + 1)
    s = np.maximum(blur_cells, 1e-3)[:, None]
    w = ndtr((d + 0.5) / s) - ndtr((d - 0.5) / s)  # (n, 2R+1)
    w /= w.sum(axis=1, keepdims=True)
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * _REACH + 1, axis=3)
    # win: (n, 4, depth, 8, 2R+1); the bit cells are 1..6 along the side.
    cells = np.ascontiguousarray(win[:, :, :, 1 : BITS + 1]).reshape(len(w), -1, w.shape[1])
    mixed = (cells @ w[:, :, None]).reshape(stripes.shape[:3] + (BITS,))
    return np.moveaxis(mixed, 2, 3)


class _Profiles:
    """The sampled profiles of n markers and the model that is fitted to them."""

    def __init__(self, obs: np.ndarray, xs: np.ndarray, stripes: np.ndarray, cell: np.ndarray):
        self.obs, self.xs, self.stripes = obs, xs, stripes  # obs/xs (n, 4, m, K)
        self.cell = cell[..., None]  # (n, 4, m, 1): a cell's width across the side, px
        self.mean_cell = cell.mean(axis=(1, 2))
        self.t = _ALONG - 0.5  # along-side coordinate of the samples (m,)

    def evaluate(self, P: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Model minus observation (n, 4, m, K) and, per side, its Jacobian (n, 4, m*K, 8) with
        respect to the marker's blur, black and white (3) and that side's own five parameters
        (every other parameter leaves a side's samples alone)."""
        n = len(P)
        sig = P[:, 0, None, None, None]
        Ld = P[:, 1, None, None, None]
        Lw = P[:, 2, None, None, None]
        S = P[:, 3:].reshape(n, 4, 5)
        e = (S[..., 0, None] + S[..., 1, None] * self.t)[..., None]  # (n,4,m,1)
        c = S[..., 2, None, None] * self.cell  # the side's scale times each sample's cell
        Lb = S[..., 3, None, None]
        q = S[..., 4, None, None]
        frac = _along_mix(self.stripes, P[:, 0] / np.maximum(self.mean_cell, 1e-6))
        L = [Ld + (Lw - Ld) * frac[..., k : k + 1] for k in range(_DEPTH)]  # border, bit rows
        # Boundaries from the inside out: bits 3|2, 2|1, 1|border, border|quiet, quiet|wall.
        bounds = (e - 3 * c, e - 2 * c, e - c, e, e + q * c)
        jumps = (L[2] - L[3], L[1] - L[2], L[0] - L[1], Lw - L[0], Lb - Lw)
        z = [(self.xs - b) / sig for b in bounds]
        F = [ndtr(zk) for zk in z]
        model = L[3] + sum(j * f for j, f in zip(jumps, F, strict=True))
        r = model - self.obs
        if not jacobian:
            return r, None
        phi = [np.exp(-0.5 * zk * zk) / _SQRT2PI for zk in z]
        J = np.empty(r.shape + (8,))
        # The blur also sets how much of the neighbouring bits each sample sees along the side:
        # its column is a difference.
        bumped = P.copy()
        bumped[:, 0] += 1e-4
        J[..., 0] = (self.evaluate(bumped, False)[0] - r) / 1e-4
        shares = (1 - F[0], F[0] - F[1], F[1] - F[2], F[2] - F[3])  # of rows 3, 2, 1, border
        J[..., 1] = sum((1 - frac[..., 3 - k : 4 - k]) * w for k, w in enumerate(shares))
        J[..., 2] = sum(frac[..., 3 - k : 4 - k] * w for k, w in enumerate(shares)) + F[3] - F[4]
        d_e = -sum(j * p for j, p in zip(jumps, phi, strict=True)) / sig
        d_c = 3 * jumps[0] * phi[0] + 2 * jumps[1] * phi[1] + jumps[2] * phi[2]
        J[..., 3] = d_e
        J[..., 4] = d_e * self.t[:, None]
        J[..., 5] = (d_c - q * jumps[4] * phi[4]) * self.cell / sig
        J[..., 6] = F[4]
        J[..., 7] = -jumps[4] * phi[4] * c / sig
        return r, J.reshape(n, 4, -1, 8)


def _normal_equations(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T J (n, 23, 23) and J^T r (n, 23) from the per-side Jacobians (n, 4, R, 8)."""
    n = len(J)
    Jt = J.transpose(0, 1, 3, 2)
    B = Jt @ J  # (n, 4, 8, 8)
    b = (Jt @ r.reshape(n, 4, -1, 1))[..., 0]  # (n, 4, 8)
    H = np.zeros((n, 23, 23))
    g = np.zeros((n, 23))
    H[:, :3, :3] = B[:, :, :3, :3].sum(axis=1)
    g[:, :3] = b[:, :, :3].sum(axis=1)
    for k in range(4):
        cols = slice(3 + 5 * k, 8 + 5 * k)
        H[:, cols, cols] = B[:, k, 3:, 3:]
        H[:, :3, cols] = B[:, k, :3, 3:]
        H[:, cols, :3] = B[:, k, 3:, :3]
        g[:, cols] = b[:, k, 3:]
    return H, g


def _prior(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weak priors, as (mean, precision) per parameter (n, 23) in units of _NOISE: each side's
    cells as wide as the corners say (10 %), the quiet zone about a cell or more wide, the wall
    anything near the white."""
    mean, prec = np.zeros_like(P), np.zeros_like(P)
    mean[:, 5::5], prec[:, 5::5] = 1.0, 1 / 0.1**2  # per side: e0 e1 scale Lb q from index 3
    mean[:, 6::5], prec[:, 6::5] = P[:, 2, None], 1 / 200.0**2
    mean[:, 7::5], prec[:, 7::5] = 1.5, 1 / 2.0**2
    return mean, prec * _NOISE**2


def _fit(prof: _Profiles, P: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every marker at once; returns the parameters and the residual RMS."""
    lam = np.full(len(P), 1e-2)
    r, J = prof.evaluate(P, True)
    mean, prec = _prior(P)

    def cost(P: np.ndarray, r: np.ndarray) -> np.ndarray:
        data = np.square(r).reshape(len(P), -1).sum(axis=1)
        return data + (prec * np.square(P - mean)).sum(axis=1)

    current = cost(P, r)
    eye = np.eye(P.shape[1])
    for _ in range(iterations):
        assert J is not None
        H, g = _normal_equations(J, r)
        H += prec[:, :, None] * eye
        g += prec * (P - mean)
        damp = lam[:, None, None] * np.maximum(np.einsum("nii->ni", H), 1e-9)[:, :, None] * eye
        try:
            step = -np.linalg.solve(H + damp, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        trial = P + step
        trial[:, 0] = np.clip(trial[:, 0], 0.2, 8.0)
        trial[:, 7::5] = np.clip(trial[:, 7::5], 0.3, 6.0)  # each side's quiet zone, cells
        r_new, J_new = prof.evaluate(trial, True)
        new = cost(trial, r_new)
        better = new < current
        P = np.where(better[:, None], trial, P)
        r = np.where(better[:, None, None, None], r_new, r)
        assert J_new is not None
        J = np.where(better[:, None, None, None], J_new, J)
        current = np.where(better, new, current)
        lam = np.where(better, lam / 3, lam * 10)
    rms = np.sqrt(np.square(r).reshape(len(P), -1).mean(axis=1))
    return P, rms


# Each side's bit cells in the marker's plane (cells, u right and v down from corner 0): the point
# on the outer edge at the cell's centre, and the direction into the marker.
_CENTRES = np.arange(BITS) + 1.5
_EDGE_UV = np.stack(
    [
        np.stack([_CENTRES, np.zeros(BITS)], axis=1),
        np.stack([np.full(BITS, 8.0), _CENTRES], axis=1),
        np.stack([8.0 - _CENTRES, np.full(BITS, 8.0)], axis=1),
        np.stack([np.zeros(BITS), 8.0 - _CENTRES], axis=1),
    ]
)  # (4, m, 2)
_INWARD = np.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]])  # (4, 2)
_SQUARE = np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]], np.float32)


def _to_image(H: np.ndarray, uv: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """Marker-plane points (n, ..., 2) through each marker's homography (n, 3, 3) into distorted
    pixels."""
    flat = uv.reshape(len(H), -1, 2)
    ray = np.einsum("nij,nkj->nki", H, np.concatenate([flat, np.ones(flat.shape[:-1] + (1,))], -1))
    return project_points(cal, ray / ray[..., 2:3]).reshape(uv.shape)


def _one_round(
    gray: np.ndarray,
    pts: np.ndarray,
    stripes: np.ndarray,
    cal: CameraCalibration,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    n = len(pts)
    ua = undistort_points(cal, pts).astype(np.float32)
    H = np.stack([cv2.getPerspectiveTransform(_SQUARE, q) for q in ua])  # cells -> normalised
    edge_uv = np.broadcast_to(_EDGE_UV, (n,) + _EDGE_UV.shape)
    base = _to_image(H, edge_uv, cal)  # (n, 4, m, 2) px
    inner = _to_image(H, edge_uv + _INWARD[None, :, None, :], cal)
    ahead = _to_image(H, edge_uv + 1e-3 * np.roll(_INWARD, 1, axis=0)[None, :, None, :], cal)
    tangent = ahead - base
    tangent /= np.maximum(np.linalg.norm(tangent, axis=-1, keepdims=True), 1e-12)
    normal = np.stack([-tangent[..., 1], tangent[..., 0]], axis=-1)
    out = np.einsum("nkmj,nkmj->nkm", base - inner, normal)
    normal *= np.where(out < 0, -1.0, 1.0)[..., None]
    cell = np.abs(out)  # (n, 4, m): a cell's width across the side at each sample, px
    xs = _ACROSS * cell[..., None]  # (n, 4, m, K)
    grid = base[:, :, :, None, :] + xs[..., None] * normal[:, :, :, None, :]
    inside = in_frame(grid, gray.shape).all(axis=(1, 2, 3))
    obs = bilinear(gray, grid.reshape(-1, 2)).reshape(xs.shape)
    flat = obs.reshape(n, -1)
    S = np.zeros((n, 4, 5))  # per side: offset, tilt, cell scale, wall level, quiet zone
    S[..., 2] = 1.0
    S[..., 3] = obs[..., -3:].mean(axis=(2, 3))
    S[..., 4] = 1.0
    start = [0.3 * cell.mean(axis=(1, 2)) + 0.5, np.percentile(flat, 5, axis=1)]
    start.append(np.percentile(flat, 95, axis=1))
    P = np.concatenate([np.stack(start, axis=1), S.reshape(n, 20)], axis=1)
    P, rms = _fit(_Profiles(obs, xs, stripes, cell), P, iterations)
    S = P[:, 3:].reshape(n, 4, 5)
    offset = S[..., 0, None] + S[..., 1, None] * (_ALONG - 0.5)  # (n, 4, m) px
    xy = undistort_points(cal, base + offset[..., None] * normal)
    nrm, c, _ = fit_lines(xy, np.ones(xy.shape[:3]))
    out, met = corners_from_sides(nrm, c, cal)
    contrast = P[:, 2] - P[:, 1]
    good = (
        met
        & inside
        & (cell.min(axis=(1, 2)) >= _MIN_CELL_PX)
        & (contrast > _MIN_CONTRAST)
        & (rms < _MAX_RMS * np.maximum(contrast, 1e-9))
        & (np.abs(offset).max(axis=(1, 2)) < np.maximum(1.0, cell.min(axis=(1, 2))))
    )
    return np.where(good[:, None, None], out, pts), good


def profile_corners(
    gray: np.ndarray, corners: np.ndarray, bits: np.ndarray, cal: CameraCalibration
) -> tuple[np.ndarray, np.ndarray]:
    """Corners (n, 4, 2), distorted pixels, of markers whose bits are ``bits`` (n, 6, 6), fitted
    from ``corners`` as a start; and which markers the model fitted (n,) (the others keep their
    start)."""
    start = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    if len(start) == 0:
        return start.copy(), np.zeros(0, bool)
    img = gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    length = np.linalg.norm(np.roll(start, -1, axis=1) - start, axis=2).mean(axis=1)
    ok = length / MARKER_CELLS <= _MAX_CELL_PX
    if not ok.any():
        return start.copy(), ok
    stripes = np.stack([_side_stripes(b) for b in np.asarray(bits, bool)[ok]])
    pts = start[ok]
    fitted = np.ones(len(pts), bool)
    for iterations in _ITERATIONS:
        new, good = _one_round(img, pts, stripes, cal, iterations)
        fitted &= good
        pts = np.where(good[:, None, None], new, pts)
    out = start.copy()
    out[ok] = np.where(fitted[:, None, None], pts, start[ok])
    ok[ok] = fitted
    return out, ok
