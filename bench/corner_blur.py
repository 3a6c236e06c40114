"""Corner bias of the three corner estimates on small blurred markers, across prints and blur.

    python bench/corner_blur.py                 # quiet zones 1 and 2 cells, blur 0-1.2 px
    python bench/corner_blur.py --seeds 4

Each scene holds fifteen markers, 18-60 px on a side, some turned 30-65 deg from the camera. They
are printed black 25 on white 230 with a quiet zone one or two cells wide, on a grey wall (120),
drawn 4x supersampled and area-averaged. The scene is then blurred (Gaussian) and given noise
1.5. OpenCV's window corners are the start. The edge fit (`annotator.vision.corners`) and the
profile model (`annotator.vision.profile_corners`) finish them. Per condition the bench prints
the mean radial error (positive: the square looks larger) over the markers the profile model
fitted, on small (< 30 px) and larger markers, and the CPU cost of the profile fit per marker.
This renderer is not the one the field matrix uses (`annotator.render`), so agreement between
them is not a renderer's habit.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration
from annotator.vision.corners import refine_corners_by_edges
from annotator.vision.profile_corners import marker_bits, profile_corners

W, H = 960, 540
CAL = CameraCalibration(
    np.array([[700.0, 0, 479.5], [0, 700.0, 269.5], [0, 0, 1]]), np.zeros(5), W, H
)
DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50)


def paste(img: np.ndarray, marker_id: int, corners: np.ndarray, quiet_cells: float) -> None:
    """A printed marker (black 25, white 230) with a quiet zone ``quiet_cells`` wide, its square
    on ``corners`` (pixel centres at integers), drawn 4x supersampled and area-averaged."""
    ss, side = 4, 160
    margin = int(quiet_cells * side // 8)
    tex = np.full((side + 2 * margin,) * 2, 230, np.uint8)
    code = cv2.aruco.generateImageMarker(DICT, marker_id, side).astype(np.float32)
    tex[margin : margin + side, margin : margin + side] = 25 + code * (205 / 255)
    e = margin - 0.5, margin + side - 0.5
    src = np.array([[e[0], e[0]], [e[1], e[0]], [e[1], e[1]], [e[0], e[1]]], np.float32)
    dst = (np.asarray(corners, np.float32) * ss + (ss - 1) / 2).astype(np.float32)
    hom = cv2.getPerspectiveTransform(src, dst)
    size = (W * ss, H * ss)
    warped = cv2.warpPerspective(tex, hom, size, flags=cv2.INTER_LINEAR)
    mask = cv2.warpPerspective(np.full_like(tex, 255), hom, size, flags=cv2.INTER_LINEAR)
    warped = cv2.resize(warped, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32)
    alpha = cv2.resize(mask, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    img[:] = img * (1 - alpha) + warped * alpha


def scene(
    quiet: float, blur: float, seed: int, sides: tuple[float, float] = (18, 32), count: int = 10
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """``count`` markers ``sides`` px on a side, some seen at 30-65 deg, on a grey wall; blurred
    by ``blur`` px and noise 1.5."""
    rng = np.random.default_rng(seed)
    img = np.full((H, W), 120.0, np.float32)
    truth = {}
    per_row = 5 if count <= 10 else 6
    for k in range(count):
        centre = np.array([90 + 150 * (k % per_row), 90 + 180 * (k // per_row)], float)
        half = rng.uniform(*sides) / 2
        square = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
        yaw = (0, 30, 55, 65)[k % 4] if count > 10 else (0, 30, 55)[k % 3]
        turn = Rotation.from_euler("yz", [yaw, rng.uniform(-30, 30)], degrees=True)
        cam = turn.apply(square) + [0, 0, 700.0]
        px = cam[:, :2] / cam[:, 2:] * 700 + centre + rng.uniform(-0.5, 0.5, 2)
        paste(img, k, px, quiet)
        truth[k] = px
    blurred = cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img
    return np.clip(blurred + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8), truth


def radial(corners: np.ndarray, truth: np.ndarray) -> float:
    """Mean corner error along the square's diagonals (positive: the square looks larger)."""
    out = truth - truth.mean(axis=0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return float(((corners - truth) * out).sum(axis=1).mean())


def window_corners(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's detection with its corner window (cornerSubPix): corners (n, 4, 2) and ids."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(DICT, params).detectMarkers(img)
    if ids is None:
        return np.zeros((0, 4, 2)), np.zeros(0, int)
    return np.asarray(corners, float).reshape(-1, 4, 2), ids.reshape(-1)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", type=int, default=3, help="scenes per condition (default 3)")
    args = ap.parse_args()
    print(
        f"{'quiet':>5} {'blur':>4} {'fitted':>7}   {'window':>14} {'edge fit':>14} {'profile':>14}"
    )
    print(
        f"{'':>5} {'':>4} {'':>7}   {'small / large':>14} {'small / large':>14} {'small / large':>14}"
    )
    spent, fitted_markers = 0.0, 0
    for quiet in (1.0, 2.0):
        for blur in (0.0, 0.5, 0.8, 1.2):
            rows: list[tuple[float, float, float, float]] = []
            seen = 0
            for seed in range(args.seeds):
                img, truth = scene(quiet, blur, seed, (18, 60), 15)
                start, ids = window_corners(img)
                keep = np.array([int(i) in truth for i in ids], bool)
                start, ids = start[keep], ids[keep]
                seen += len(ids)
                edge = refine_corners_by_edges(img, start, CAL)
                bits = np.stack([marker_bits(DICT, int(i)) for i in ids])
                t0 = time.process_time()
                model, ok = profile_corners(img, edge, bits, CAL)
                spent += time.process_time() - t0
                fitted_markers += int(ok.sum())
                for i, mid in enumerate(ids):
                    if ok[i]:
                        t = truth[int(mid)]
                        side = float(np.linalg.norm(t - np.roll(t, -1, axis=0), axis=1).min())
                        rows.append(
                            (side, radial(start[i], t), radial(edge[i], t), radial(model[i], t))
                        )
            a = np.array(rows)
            small = a[:, 0] < 30
            cells = [f"{a[small, k].mean():+.3f} / {a[~small, k].mean():+.3f}" for k in (1, 2, 3)]
            print(
                f"{quiet:5.0f} {blur:4.1f} {len(a):3d}/{seen:<3d}   "
                + " ".join(f"{c:>14}" for c in cells)
            )
    print(f"profile fit: {1000 * spent / max(fitted_markers, 1):.2f} CPU ms per marker fitted")


if __name__ == "__main__":
    main()
