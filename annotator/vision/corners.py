"""Sub-pixel marker corners as intersections of the square's four fitted border edges.

A corner detector (cornerSubPix) looks at a window around the corner, and what it sees there
depends on the marker's size: the inner bits come into a fixed window on small markers, the
blur of the corner itself biases it on large ones. The edges carry no such bias: across the
square's outer edge the image goes from the black border to the white quiet zone, and with a
symmetric blur the gradient's centroid along the normal lies on the edge. Each side is sampled
away from its corners, the edge points are undistorted, a line is fitted per side and adjacent
lines are intersected, then the corner is distorted back into the image.
"""

from __future__ import annotations

import cv2
import numpy as np

from annotator.core.experiment import CameraCalibration
from annotator.vision.lens import project_points, undistort_points

MARKER_CELLS = 8  # 6x6 bits plus a one-cell black border on each side
_ALONG = np.linspace(0.15, 0.85, 16)  # sample positions along a side, clear of its corners
_ACROSS = np.linspace(-1.0, 1.0, 17)  # profile across the edge, in units of the half-width
_MIN_CONTRAST = 12.0  # grey levels across an edge for its point to count
_MIN_POINTS = 5  # per side


def refine_corners_by_edges(
    gray: np.ndarray, corners: np.ndarray, cal: CameraCalibration, iterations: int = 1
) -> np.ndarray:
    """Corners (n, 4, 2) in distorted pixels of ``gray`` moved onto the fitted border edges.

    A marker whose edges cannot be measured (too little contrast, a side cut by the frame) or
    whose corners would move by more than a cell keeps its input corners.
    """
    start = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    if len(start) == 0:
        return start.copy()
    img = gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    pts = start.copy()
    ok = np.ones(len(pts), bool)
    for _ in range(iterations):
        new, good = _one_pass(img, pts, cal)
        ok &= good
        pts = np.where(good[:, None, None], new, pts)
    side = np.linalg.norm(start - np.roll(start, -1, axis=1), axis=2).min(axis=1)
    moved = np.linalg.norm(pts - start, axis=2).max(axis=1)
    ok &= moved < np.maximum(1.5, side / MARKER_CELLS)
    return np.where(ok[:, None, None], pts, start)


def _one_pass(
    img: np.ndarray, pts: np.ndarray, cal: CameraCalibration
) -> tuple[np.ndarray, np.ndarray]:
    a = pts
    d = np.roll(pts, -1, axis=1) - a  # side i runs from corner i to corner i+1
    length = np.linalg.norm(d, axis=2)  # (n, 4)
    # Sample along the side as the lens bends it: straight between the undistorted corners.
    ua = undistort_points(cal, a)
    ud = np.roll(ua, -1, axis=1) - ua
    eps = 1e-3
    along = np.concatenate([_ALONG, _ALONG + eps])
    ray = ua[:, :, None, :] + along[None, None, :, None] * ud[:, :, None, :]
    ray3 = np.concatenate([ray, np.ones(ray.shape[:-1] + (1,))], axis=-1)
    proj = project_points(cal, ray3)
    m = len(_ALONG)
    base, ahead = proj[:, :, :m], proj[:, :, m:]  # (n, 4, m, 2)
    u = ahead - base
    u /= np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
    normal = np.stack([-u[..., 1], u[..., 0]], axis=-1)  # (n, 4, m, 2)
    outward = np.einsum("nkmj,nkmj->nkm", base - pts.mean(axis=1)[:, None, None, :], normal)
    normal *= np.where(outward < 0, -1.0, 1.0)[..., None]
    # Half-width of the profile: within the one-cell border inside and quiet zone outside.
    half = np.clip(0.6 * length / MARKER_CELLS, 1.0, 8.0)  # (n, 4)
    offs = half[..., None] * _ACROSS  # (n, 4, k)
    grid = base[:, :, :, None, :] + offs[:, :, None, :, None] * normal[:, :, :, None, :]
    n, k = len(pts), len(_ACROSS)
    flat = grid.reshape(-1, k, 2)
    inside = in_frame(flat, img.shape).all(axis=1)
    prof = bilinear(img, flat).reshape(n, 4, m, k)
    grad = np.clip(np.diff(prof, axis=3), 0, None)
    centres = (_ACROSS[1:] + _ACROSS[:-1]) / 2  # (k-1,)
    total = grad.sum(axis=3)
    offset = (grad * centres).sum(axis=3) / np.maximum(total, 1e-9) * half[..., None]
    contrast = prof[..., k // 2 + 1 :].mean(axis=3) - prof[..., : k // 2].mean(axis=3)
    valid = (contrast > _MIN_CONTRAST) & inside.reshape(n, 4, m)
    edge = base + offset[..., None] * normal
    xy = undistort_points(cal, edge)  # (n, 4, m, 2) normalised
    nrm, c, wsum = fit_lines(xy, valid.astype(float))
    # Robust pass: drop points far off their first line.
    res = np.abs(np.einsum("nkmj,nkj->nkm", xy, nrm) - c[..., None])
    ranked = np.sort(np.where(valid, res, np.inf), axis=2)
    middle = np.minimum(valid.sum(axis=2, keepdims=True) // 2, m - 1)
    scale = np.take_along_axis(ranked, middle, axis=2)  # median residual of the valid points
    keep = valid & (res <= np.maximum(3 * np.where(np.isfinite(scale), scale, 0), 1e-6))
    nrm, c, wsum = fit_lines(xy, keep.astype(float))
    good = (keep.sum(axis=2) >= _MIN_POINTS).all(axis=1)
    out, met = corners_from_sides(nrm, c, cal)
    good &= met
    return np.where(good[:, None, None], out, pts), good


def corners_from_sides(
    nrm: np.ndarray, c: np.ndarray, cal: CameraCalibration
) -> tuple[np.ndarray, np.ndarray]:
    """Each square's corners (n, 4, 2), distorted pixels, from its four side lines n . p = c in
    normalised coordinates (corner i is where side i-1 meets side i); and which squares' sides
    all meet at a clear angle and project to finite pixels (n,)."""
    n1, c1 = np.roll(nrm, 1, axis=1), np.roll(c, 1, axis=1)
    det = n1[..., 0] * nrm[..., 1] - n1[..., 1] * nrm[..., 0]
    good = (np.abs(det) > 0.05).all(axis=1)
    det = np.where(np.abs(det) > 1e-12, det, 1.0)
    x = (c1 * nrm[..., 1] - n1[..., 1] * c) / det
    y = (n1[..., 0] * c - c1 * nrm[..., 0]) / det
    out = project_points(cal, np.stack([x, y, np.ones_like(x)], axis=-1))
    return out, good & np.isfinite(out).all(axis=(1, 2))


def in_frame(xy: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Which sub-pixel points (..., 2) lie inside an image of ``shape`` (rows, columns, ...)."""
    h, w = shape[:2]
    x, y = xy[..., 0], xy[..., 1]
    return (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)


def bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Image values at sub-pixel points (..., 2), bilinear, clamped to the frame."""
    h, w = img.shape[:2]
    x = np.clip(xy[..., 0], 0, w - 1.001)
    y = np.clip(xy[..., 1], 0, h - 1.001)
    x0 = x.astype(np.intp)
    y0 = y.astype(np.intp)
    fx = x - x0
    fy = y - y0
    v00 = img[y0, x0].astype(np.float64)
    v01 = img[y0, x0 + 1].astype(np.float64)
    v10 = img[y0 + 1, x0].astype(np.float64)
    v11 = img[y0 + 1, x0 + 1].astype(np.float64)
    top = v00 + fx * (v01 - v00)
    return top + fy * (v10 + fx * (v11 - v10) - top)


def fit_lines(xy: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares lines n . p = c through weighted points (..., m, 2)."""
    wsum = w.sum(axis=-1)
    mean = (xy * w[..., None]).sum(axis=-2) / np.maximum(wsum, 1e-12)[..., None]
    dx = xy - mean[..., None, :]
    sxx = (w * dx[..., 0] ** 2).sum(axis=-1)
    syy = (w * dx[..., 1] ** 2).sum(axis=-1)
    sxy = (w * dx[..., 0] * dx[..., 1]).sum(axis=-1)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the line
    nrm = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
    c = np.einsum("...j,...j->...", mean, nrm)
    return nrm, c, wsum
