"""The rolling-shutter readout measured by `annotator calibrate --readout` across conditions.

    python bench/readout_calibration.py                 # readouts 0/10/15/30 ms, seeds 0-4
    python bench/readout_calibration.py --seeds 0,1 --readouts 15

Each cell renders 3 s of a ChArUco board (5x7, 6 cm squares) waved 0.7 m in front of a 960x540
camera (`annotator.render.charuco.waving_board`: peak turns of about 90 deg/s, a few cm of sway)
with the given readout, finds its corners in every frame, and fits the readout with the lens
calibrated from 14 still views of the board (the field procedure), its uncertainty
propagated into the readout's sigma. Lenses: the renderer's mild
and wide ones. Prints per cell the mean and worst |found - true| (ms), the mean stated sigma,
and the share of seeds within 2.8 sigma; last, the mean over cells and the worst cell.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from annotator.core.calibration import CharucoSpec, calibrate_charuco, detect_board
from annotator.core.readout import BoardView, estimate_readout
from annotator.io.video import iter_frames
from annotator.render.camera import default_cameras
from annotator.render.charuco import (
    random_board_poses,
    render_charuco_video,
    render_charuco_views,
    waving_board,
)


def one(lens: str, readout: float, seed: int, work: Path) -> tuple[float, float]:
    cam = default_cameras(960, 540, lens)["back"]
    spec = CharucoSpec((5, 7), 0.0598, 0.0299, "DICT_6X6_50")
    board = spec.board()
    rng = np.random.default_rng(seed)
    stills = render_charuco_views(cam, board, random_board_poses(14, board, cam, rng), seed=seed)
    lens_cal = calibrate_charuco(stills, spec)
    video = work / f"board-{lens}-{seed}.mp4"
    render_charuco_video(
        str(video), cam, board, waving_board(board, seed=seed), np.arange(90) / 30.0, readout,
        seed=seed,
    )  # fmt: skip
    detector = cv2.aruco.CharucoDetector(board)
    views = []
    for t, frame in iter_frames(video, gray=True):
        found = detect_board(frame, detector, board)
        if found is not None:
            views.append(BoardView(t, found[0], found[1]))
    est = estimate_readout(
        views,
        lens_cal.camera_matrix,
        lens_cal.dist_coeffs,
        cam.height,
        intrinsics_sigma=lens_cal.intrinsics_sigma,
    )
    return est.readout_s - readout, est.sigma_s


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--readouts", default="0,10,15,30", help="true readouts, ms")
    ap.add_argument("--lenses", default="mild,wide")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    readouts = [float(r) / 1000 for r in args.readouts.split(",")]
    lenses = args.lenses.split(",")
    print(f"{'lens':6} {'true ms':>7} {'mean |err| ms':>13} {'worst ms':>8} {'sigma ms':>8} "
          f"{'<2.8sig':>7} {'time':>6}")  # fmt: skip
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for lens in lenses:
            for readout in readouts:
                t = time.perf_counter()
                res = [one(lens, readout, s, Path(tmp)) for s in seeds]
                err = np.abs([e for e, _ in res]) * 1000
                sig = np.array([s for _, s in res]) * 1000
                within = float(np.mean(err < 2.8 * sig))
                cells.append((f"{lens} {readout * 1000:g} ms", float(err.mean()), float(err.max())))
                print(
                    f"{lens:6} {readout * 1000:7.1f} {err.mean():13.2f} {err.max():8.2f} "
                    f"{sig.mean():8.2f} {100 * within:6.0f}% {time.perf_counter() - t:5.0f}s",
                    flush=True,
                )
    worst = max(cells, key=lambda c: c[1])
    print(
        f"\nmean over cells {np.mean([c[1] for c in cells]):.2f} ms; worst cell {worst[0]} "
        f"({worst[1]:.2f} ms mean, {worst[2]:.2f} ms worst seed)"
    )


if __name__ == "__main__":
    main()
