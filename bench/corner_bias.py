"""Marker corner error against a render's truth, per marker size in the image.

Projects every true marker corner into each frame (truth.csv bundle pose at the frame's time,
the rig and the calibration) and compares the detector's corners with it: mean radial error
(positive = outward from the marker's centre), median and p90 corner error, and how many corners
are off by more than 3 px (a wrong contour), in bins of the marker's side length in pixels; and
the outward error along image x and along image y (out-x, out-y; negative = the square looks
narrower / shorter), also in bins of the square's on-screen width / height (foreshortening).

    python bench/corner_bias.py RENDER/experiment.yaml [--downscale 1] [--edges | --no-edges]
        [--no-profile] [--step 3]

A render made with field errors keeps its true map, rig and lenses in true/: those are projected.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from annotator.io.experiment import load_experiment
from annotator.io.trajectory import read_trajectory
from annotator.vision.detection import DetectorSettings, MarkerDetector
from annotator.vision.geometry import MarkerRoom
from annotator.vision.lens import project_points

BINS = [(0, 35), (35, 60), (60, 1e9)]
ASPECTS = [(0.0, 0.6), (0.6, 0.8), (0.8, 0.95), (0.95, 1.05), (1.05, 10.0)]
FPS = 30.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment")
    ap.add_argument("--downscale", type=float, default=None)
    ap.add_argument(
        "--edges",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="edge-fit corners on / off (default: the detector's, on at downscaled detection)",
    )
    ap.add_argument(
        "--board-px", type=float, default=None, help="board_refine_px (default: the detector's)"
    )
    ap.add_argument("--step", type=int, default=3, help="use every n-th frame")
    ap.add_argument(
        "--profile",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="finish the edge corners with the profile model (default: on; the tracker only with --profile-corners)",
    )
    a = ap.parse_args()
    exp = load_experiment(a.experiment)
    truth = read_trajectory(Path(a.experiment).parent / "truth.csv")
    # A render with errors keeps the true map, rig and lenses in true/: project those.
    true_path = Path(a.experiment).parent / "true" / "experiment.yaml"
    geo = load_experiment(true_path) if true_path.exists() else exp
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    true_room = MarkerRoom.from_map(geo.markers.markers, geo.markers.length)
    assert geo.video_start is not None
    for name, cam in exp.rig.cameras.items():
        cal = cam.calibration
        settings = DetectorSettings(
            downscale=a.downscale,
            edge_corners=a.edges,
            board_refine_px=a.board_px,
            profile_corners=a.profile,
        )
        det = MarkerDetector(settings, room, cal)
        cap = cv2.VideoCapture(str(exp.videos[name]))
        rows: list[tuple[float, ...]] = []  # (side px, radial, error, out-x, out-y, aspect)
        spent = 0.0
        frames = 0
        i = -1
        while True:
            ok, img = cap.read()
            if not ok:
                break
            i += 1
            if i % a.step:
                continue
            gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            t0 = time.process_time()
            d = det.detect(gray)
            spent += time.process_time() - t0
            frames += 1
            if len(d.ids) == 0:
                continue
            t = geo.video_start[name] + i / FPS
            world = true_room.corners_world[true_room.index(d.ids)]  # (n, 4, 3)
            tcam = geo.rig.cameras[name]
            uv = _project(truth, t, tcam, world)
            readout = tcam.calibration.readout_s
            if readout > 0:  # rolling shutter: each corner at its row's time
                uv = _project(truth, t + readout * uv[..., 1:2] / cal.height, tcam, world)
            if not np.isfinite(uv).all():
                continue
            centre = uv.mean(axis=1, keepdims=True)
            out = uv - centre
            out /= np.linalg.norm(out, axis=2, keepdims=True)
            diff = d.corners - uv
            side = np.linalg.norm(uv - np.roll(uv, -1, axis=1), axis=2).mean(axis=1)
            radial = (diff * out).sum(axis=2)
            err = np.linalg.norm(diff, axis=2)
            # Outward error along image x and y, and the square's on-screen width / height.
            sign = np.sign(uv - centre)
            outx, outy = (diff * sign)[..., 0], (diff * sign)[..., 1]
            span = uv.max(axis=1) - uv.min(axis=1)
            aspect = span[:, 0] / np.maximum(span[:, 1], 1e-9)
            for k in range(len(d.ids)):
                for j in range(4):
                    rows.append(
                        (side[k], radial[k, j], err[k, j], outx[k, j], outy[k, j], aspect[k])
                    )
        r = np.array(rows)
        print(
            f"{name}: {frames} frames, detection {1000 * spent / max(frames, 1):.2f} ms CPU/frame"
        )
        for lo, hi in BINS:
            sel = r[(r[:, 0] >= lo) & (r[:, 0] < hi)]
            if (sel[:, 2] <= 3).sum() == 0:
                continue
            good = sel[sel[:, 2] <= 3]
            print(
                f"  side {lo:>3.0f}-{hi if hi < 1e9 else 'inf':>4} px: {len(sel) // 4:5d} markers"
                f"  radial {good[:, 1].mean():+.3f} px  median {np.median(good[:, 2]):.3f}"
                f"  p90 {np.percentile(good[:, 2], 90):.3f}  >3px {len(sel) - len(good)}"
                f"  out-x {good[:, 3].mean():+.3f} out-y {good[:, 4].mean():+.3f}"
            )
        good = r[r[:, 2] <= 3]
        for a_lo, a_hi in ASPECTS:
            sel = good[(good[:, 5] >= a_lo) & (good[:, 5] < a_hi)]
            if len(sel) == 0:
                continue
            print(
                f"  width/height {a_lo:.2f}-{a_hi:.2f}: {len(sel) // 4:5d} markers"
                f"  out-x {sel[:, 3].mean():+.3f} px  out-y {sel[:, 4].mean():+.3f} px"
                f"  (side {sel[:, 0].mean():.0f} px)"
            )


def _project(truth, t, cam, world: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """True pixel positions (n, 4, 2) of world corners at time(s) t (scalar or (n, 4, 1))."""
    times = np.broadcast_to(np.asarray(t, float), world.shape[:2] + (1,))[..., 0].reshape(-1)
    p, rot, ok = truth.interpolate(times)
    r_wc = rot @ cam.R_bundle_camera
    c_w = p + rot @ cam.t_bundle_camera
    x = world.reshape(-1, 3) - c_w
    xc = np.einsum("nji,nj->ni", r_wc, x)
    uv = project_points(cam.calibration, xc).reshape(world.shape[:2] + (2,))
    uv[~ok.reshape(world.shape[:2])] = np.nan
    return uv


if __name__ == "__main__":
    main()
