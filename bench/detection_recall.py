"""Detection recall against the truth: of the markers wholly in view and not hidden, how many
the tracker's detector finds, per imaging condition and per marker size in the image.

    python bench/detection_recall.py                     # every condition, 60 frames each
    python bench/detection_recall.py --frames 20 --conditions clean-540,real-540

Frames are rendered in memory along the default loop (the front camera, the field lens, 8 ms
exposure with its motion blur) with `annotator.render.frames.FrameRenderer`, so no video codec
stands between the renderer and the detector (the `real` imaging compresses every frame as JPEG
at quality 60 itself). The detector is `annotator.vision.detection.MarkerDetector` with the
tracker's defaults (half-size detection at 1080p). Expected markers come from the scene's own
projection (`MarkerScene.expected_corners`). Columns: recall overall and for markers whose side
is under 20 px, 20-40 px and over 40 px in the image; markers per frame expected and found;
median corner error of the found ones (px); detection time per frame.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from annotator.core.experiment import CameraCalibration
from annotator.render import LoopTrajectory
from annotator.render.camera import camera_pose, default_cameras
from annotator.render.conditions import IMAGING_NOISE, IMAGING_PRESETS
from annotator.render.effects import Imaging
from annotator.render.frames import FrameRenderer
from annotator.vision.detection import DetectorSettings, MarkerDetector
from annotator.vision.geometry import MarkerRoom
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir

T0 = 1_700_000_000.0
EXPOSURE_S = 0.008
SIZES = ((0.0, 20.0), (20.0, 40.0), (40.0, 1e9))


@dataclass(frozen=True)
class Condition:
    name: str
    width: int
    imaging: Imaging
    noise: float


def conditions() -> dict[str, Condition]:
    real = IMAGING_PRESETS["real"]
    out = [
        Condition("clean-540", 960, Imaging(), IMAGING_NOISE["clean"]),
        Condition("real-540", 960, real, IMAGING_NOISE["real"]),
        Condition("clean-1080", 1920, Imaging(), IMAGING_NOISE["clean"]),
        Condition("real-1080", 1920, real, IMAGING_NOISE["real"]),
        Condition("defocus-1080", 1920, Imaging(defocus_px=1.5), IMAGING_NOISE["clean"]),
        Condition("jpeg-1080", 1920, Imaging(jpeg_quality=60), IMAGING_NOISE["clean"]),
        Condition(
            "light-1080",
            1920,
            Imaging(vignetting=0.4, uneven_light=0.2, light_change=0.1, exposure_steps=0.08),
            IMAGING_NOISE["clean"],
        ),
        Condition("noise-1080", 1920, Imaging(), IMAGING_NOISE["real"]),
    ]
    return {c.name: c for c in out}


@dataclass
class Recall:
    expected: np.ndarray  # (n,) side in px of every expected marker
    found: np.ndarray  # (n,) bool
    errors: list[float]
    seconds: float
    frames: int

    def share(self, lo: float = 0.0, hi: float = 1e9) -> float:
        sel = (self.expected >= lo) & (self.expected < hi)
        return float(self.found[sel].mean()) if sel.any() else float("nan")


def measure(
    cond: Condition,
    frames: int,
    seed: int = 0,
    length: float = 0.298,
    settings: DetectorSettings | None = None,
) -> Recall:
    """Recall of the detector (the tracker's unless ``settings``) on ``frames`` frames of the
    loop under ``cond``."""
    height = cond.width * 9 // 16
    cam = default_cameras(cond.width, height, "wide")["front"]
    markers = read_marker_map(site_dir("tetam") / "marker_positions.dat")
    fr = FrameRenderer(cam, markers, length, "DICT_6X6_50", cond.noise, seed, cond.imaging)
    cal = CameraCalibration(
        cam.K, np.asarray(cam.dist, float), cam.width, cam.height, "render", cam.model
    )
    det = MarkerDetector(settings or DetectorSettings(), MarkerRoom.from_map(markers, length), cal)
    walk = LoopTrajectory(t0=T0)
    sides, found, errors, spent = [], [], [], 0.0
    for t in T0 + np.linspace(0.0, 60.0, frames, endpoint=False):
        poses = [walk(np.array([t + dt])) for dt in (0.0, -EXPOSURE_S / 2, EXPOSURE_S / 2)]
        (r, c), (ro, co), (rc, cc) = (
            (lambda rc_: (rc_[0].as_matrix(), np.asarray(rc_[1])))(
                camera_pose(rot[0], pos[0], "front")
            )
            for pos, rot in poses
        )
        expected = fr.scene.expected_corners(cam, r, c)
        img = fr.render(r, c, fr.image_motion(ro, co, rc, cc), t=float(t))
        start = time.perf_counter()
        d = det.detect(img)
        spent += time.perf_counter() - start
        got = {int(i): k for i, k in zip(d.ids, d.corners, strict=True)}
        for mid, uv in expected.items():
            side = float(np.mean(np.linalg.norm(np.roll(uv, -1, 0) - uv, axis=1)))
            sides.append(side)
            found.append(mid in got)
            if mid in got:
                errors.append(float(np.median(np.linalg.norm(got[mid] - uv, axis=1))))
    return Recall(np.array(sides), np.array(found, bool), errors, spent, frames)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=60, help="frames per condition (default 60)")
    ap.add_argument("--conditions", default=",".join(conditions()), help="comma-separated subset")
    ap.add_argument(
        "--downscale", type=float, default=None, help="detection scale (default: the tracker's)"
    )
    ap.add_argument(
        "--windows",
        default=None,
        help="adaptive-threshold windows MIN,MAX,STEP for every frame (default: the tracker's)",
    )
    args = ap.parse_args()
    table = conditions()
    names = [n.strip() for n in args.conditions.split(",") if n.strip()]
    unknown = [n for n in names if n not in table]
    if unknown:
        raise SystemExit(f"--conditions: unknown {', '.join(unknown)} (known: {', '.join(table)})")
    print(
        f"{'condition':13} {'recall':>7} {'<20px':>7} {'20-40':>7} {'>40px':>7} "
        f"{'exp/frame':>9} {'found/fr':>8} {'corner px':>9} {'ms/frame':>8}"
    )
    kw: dict[str, object] = {"downscale": args.downscale}
    if args.windows:
        kw["threshold_windows"] = tuple(int(v) for v in args.windows.split(","))
    settings = DetectorSettings(**kw)  # type: ignore[arg-type]
    for name in names:
        r = measure(table[name], args.frames, settings=settings)
        n = r.frames
        print(
            f"{name:13} {100 * r.share():6.1f}% "
            + " ".join(f"{100 * r.share(lo, hi):6.1f}%" for lo, hi in SIZES)
            + f" {len(r.expected) / n:9.2f} {r.found.sum() / n:8.2f} "
            f"{np.median(r.errors) if r.errors else float('nan'):9.2f} {1000 * r.seconds / n:8.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
