"""Corner error in x and in y on single rendered frames of one marker, factor by factor.

One marker is drawn by the renderer (annotator.render) at random small offsets around a chosen
view (distance, yaw or pitch of the marker), detected with the window corners and with the edge
corners, and compared with `MarkerScene.expected_corners`. Printed per configuration: the mean
outward error of the corners along image x and along image y (px; negative = the square looks
narrower / shorter than it is), the mean side of the square on screen and the mean shift of
the whole square (x, y).

    python bench/render_xy_bias.py [--frames 40] [--yaw 0] [--pitch 0] [--dist 3]
        [--level0] [--no-lens] [--mp4] [--supersample 4] [--noise 0] [--id 7]

--level0 forces the finest texture; --no-lens renders a distortion-free camera; --mp4 passes the
frames through the mp4v codec; --supersample N renders N times larger and area-averages down
(an ideal, pixel-integrating picture to compare with).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration
from annotator.render.camera import CameraModel, default_cameras
from annotator.render.frames import FrameRenderer
from annotator.render.textures import MarkerTextures
from annotator.vision.detection import DetectorSettings, MarkerDetector
from annotator.vision.geometry import MarkerRoom
from bgt_core.formats.markers import MarkerPose

MARKER_ID = 7


def views(a: argparse.Namespace) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R_world_camera, centre) around a camera at --dist looking along world +y."""
    rng = np.random.default_rng(a.seed)
    base = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    out = []
    for _ in range(a.frames):
        jitter = Rotation.from_euler(
            "xyz", [rng.uniform(-4, 4), rng.uniform(-4, 4), rng.uniform(-a.roll, a.roll)], True
        )
        r_wc = base @ jitter.as_matrix()
        c_w = np.array([rng.uniform(-0.05, 0.05), -a.dist, rng.uniform(-0.05, 0.05)])
        out.append((r_wc, c_w))
    return out


def render_frames(a: argparse.Namespace, cam: CameraModel, markers: dict[int, MarkerPose]):
    s = a.supersample
    big = cam
    if s > 1:
        off = (s - 1) / 2  # big pixel centre of small pixel u: s*u + (s-1)/2
        big = dataclasses.replace(
            cam,
            width=cam.width * s,
            height=cam.height * s,
            fx=cam.fx * s,
            fy=cam.fy * s,
            cx=cam.cx * s + off,
            cy=cam.cy * s + off,
        )
    fr = FrameRenderer(big, markers, a.length, "DICT_6X6_50", a.noise, 0)
    small_fr = FrameRenderer(cam, markers, a.length, "DICT_6X6_50", 0.0, 0)
    frames, truths = [], []
    for r_wc, c_w in views(a):
        truth = small_fr.scene.expected_corners(cam, r_wc, c_w)
        if a.id not in truth:
            continue
        img = fr.render(r_wc, c_w)
        if s > 1:
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        frames.append(img)
        truths.append(truth[a.id])
    if a.mp4:
        with tempfile.TemporaryDirectory() as tmp:
            path = str(Path(tmp) / "x.mp4")
            w = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"mp4v"), 30.0, frames[0].shape[1::-1])
            for f in frames:
                w.write(f)
            w.release()
            cap = cv2.VideoCapture(path)
            frames = [cap.read()[1] for _ in frames]
    return frames, truths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dist", type=float, default=3.0, help="camera to marker, m")
    ap.add_argument("--length", type=float, default=0.15, help="marker side, m")
    ap.add_argument("--yaw", type=float, default=0.0, help="marker turned about vertical, deg")
    ap.add_argument("--pitch", type=float, default=0.0, help="marker tilted about horizontal, deg")
    ap.add_argument("--roll", type=float, default=5.0, help="random camera roll range, deg")
    ap.add_argument("--level0", action="store_true", help="always the finest texture")
    ap.add_argument("--no-lens", action="store_true", help="a distortion-free camera")
    ap.add_argument("--mp4", action="store_true", help="through the mp4v codec")
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--id", type=int, default=MARKER_ID, help="marker id (its bit pattern)")
    a = ap.parse_args()
    if a.level0:
        MarkerTextures.level_for = staticmethod(lambda side_px: 0)  # type: ignore[method-assign]
    cam = default_cameras(960, 540)["front"]
    if a.no_lens:
        cam = dataclasses.replace(cam, dist=(0.0,) * 5)
    euler = (np.pi / 2 + np.radians(a.pitch), 0.0, np.radians(a.yaw))
    markers = {a.id: MarkerPose(a.id, (0.0, 0.0, 0.0), euler)}
    cal = CameraCalibration(cam.K, cam.dist_array, cam.width, cam.height)
    room = MarkerRoom.from_map(markers, a.length)
    frames, truths = render_frames(a, cam, markers)
    print(
        f"yaw {a.yaw:g} pitch {a.pitch:g} dist {a.dist:g} level0 {a.level0} lens {not a.no_lens}"
        f" mp4 {a.mp4} supersample {a.supersample} noise {a.noise:g}: {len(frames)} frames"
    )
    for label, edges in (("window", False), ("edges", True)):
        det = MarkerDetector(DetectorSettings(downscale=1.0, edge_corners=edges), room, cal)
        ex, ey, sides, shift = [], [], [], []
        for img, uv in zip(frames, truths, strict=True):
            d = det.detect(img)
            if a.id not in d.ids:
                continue
            got = d.corners[list(d.ids).index(a.id)]
            sign = np.sign(uv - uv.mean(axis=0))
            err = (got - uv) * sign
            ex.append(err[:, 0].mean())
            ey.append(err[:, 1].mean())
            shift.append((got - uv).mean(axis=0))
            span = uv.max(axis=0) - uv.min(axis=0)
            sides.append(span)
        ex_a, ey_a, sd, sh = np.array(ex), np.array(ey), np.array(sides), np.array(shift)
        print(
            f"  {label:6s} n={len(ex_a):3d} outward x {ex_a.mean():+.3f} (sd {ex_a.std():.3f})"
            f"  y {ey_a.mean():+.3f} (sd {ey_a.std():.3f})  square {sd[:, 0].mean():.1f} x"
            f" {sd[:, 1].mean():.1f} px  shift {sh[:, 0].mean():+.3f}, {sh[:, 1].mean():+.3f}"
        )


if __name__ == "__main__":
    main()
