"""Render a whole simulated experiment: two rig videos along a known trajectory plus the files
`annotator track` reads (experiment.yaml, rig.yaml, calibrations, marker map) and truth.csv."""

from __future__ import annotations

import logging
import multiprocessing
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.render.camera import (
    RIG_YAML,
    CameraModel,
    build_distortion_map,
    camera_pose,
    default_cameras,
    write_calibration,
)
from annotator.render.effects import NoiseBank, apply_cover, cover_fraction, motion_kernel
from annotator.render.scene import MarkerScene
from annotator.render.textures import (
    MarkerTextures,
    aruco_dictionary,
    background_panorama,
    skin_texture,
)
from annotator.render.trajectory import PolylineTrajectory
from ble_groundtruth.formats.markers import MarkerPose, read_marker_map
from ble_groundtruth.sites import site_dir

log = logging.getLogger(__name__)

PoseAt = Callable[[np.ndarray], tuple[np.ndarray, Rotation]]
# progress(camera, frames_done, frames_total)
Progress = Callable[[str, int, int], None]
TRUTH_HEADER = "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33"


@dataclass(frozen=True)
class CameraJob:
    """Everything one worker needs to render one camera's video; plain arrays, so it pickles."""

    name: str
    camera: CameraModel
    path: str
    fps: float
    times: np.ndarray  # wall time of each frame
    r_wc: np.ndarray  # (N, 3, 3) at the frame times
    c_w: np.ndarray  # (N, 3)
    r_wc_open: np.ndarray  # at the start of the exposure, for motion blur
    c_w_open: np.ndarray
    r_wc_close: np.ndarray  # at its end
    c_w_close: np.ndarray
    markers: dict[int, MarkerPose]
    marker_length: float
    dictionary: str
    covers: tuple[tuple[float, float], ...]  # (wall start, duration)
    noise_sigma: float
    seed: int


@dataclass(frozen=True)
class RenderResult:
    out_dir: Path
    experiment: Path
    truth: Path
    videos: dict[str, Path]
    frames: dict[str, int]


class FrameRenderer:
    """Draws frames of one camera; holds the per-camera precomputed maps and textures."""

    def __init__(self, camera: CameraModel, markers: dict[int, MarkerPose], marker_length: float,
                 dictionary: str, noise_sigma: float, seed: int) -> None:
        self.camera = camera
        self.scene = MarkerScene(markers, marker_length)
        self.textures = MarkerTextures(aruco_dictionary(dictionary))
        self.dmap = build_distortion_map(camera)
        rng = np.random.default_rng(seed)
        cw, ch = self.dmap.canvas_size
        self.margin = int(0.4 * camera.fy)
        pano = background_panorama(ch + 2 * self.margin, camera.fx, rng)
        self.pano = np.hstack([pano, pano[:, :cw]])  # wrap-around without modular indexing
        self.pano_width = pano.shape[1]
        self.noise = NoiseBank((camera.height, camera.width), noise_sigma, rng)
        self.skin = skin_texture(camera.height, camera.width, rng)

    def _background(self, r_wc: np.ndarray) -> np.ndarray:
        cw, ch = self.dmap.canvas_size
        fwd = r_wc[:, 2]
        yaw = np.arctan2(fwd[1], fwd[0])
        pitch = np.arcsin(np.clip(fwd[2], -1, 1))
        x0 = int(round(-yaw * self.camera.fx)) % self.pano_width
        y0 = int(np.clip(round(self.margin - pitch * self.camera.fy), 0, 2 * self.margin))
        return self.pano[y0:y0 + ch, x0:x0 + cw].copy()

    def image_motion(self, r_open: np.ndarray, c_open: np.ndarray, r_close: np.ndarray,
                     c_close: np.ndarray) -> np.ndarray:
        """Median pixel displacement during the exposure of the marker corners in view.

        Falls back to points on a wall 3 m ahead when no marker is in the picture.
        """
        scene, cam = self.scene, self.camera
        vis = scene.visible(r_open, c_open)
        world = np.vstack([m.centre + scene.inner @ m.rotation.T for m in vis]) if vis else np.zeros((0, 3))
        grid = np.array([[x, y, 3.0] for x in (-1.0, 0.0, 1.0) for y in (-0.6, 0.0, 0.6)])
        k = cam.K

        def proj(pts: np.ndarray, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            pc = (pts - c) @ r
            uv = (pc @ k.T)[:, :2] / np.maximum(pc[:, 2:3], 1e-6)
            ok = (pc[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            return uv, ok

        a, ok = proj(world, r_open, c_open)
        if not ok.any():
            world = c_open + grid @ r_open.T
            a, ok = proj(world, r_open, c_open)
        b, _ = proj(world, r_close, c_close)
        # The median: one marker sliding past the image border must not blur the whole frame.
        return np.median(b[ok] - a[ok], axis=0)

    def render(self, r_wc: np.ndarray, c_w: np.ndarray, motion: np.ndarray = (0.0, 0.0),
               cover: float = 0.0) -> np.ndarray:
        """One BGR frame: markers on the background, lens distortion, blur, cover, noise."""
        canvas = self._background(r_wc)
        self.scene.draw(canvas, self.dmap.canvas_K, r_wc, c_w, self.textures)
        img = cv2.remap(canvas, self.dmap.map1, self.dmap.map2, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        kernel = motion_kernel(np.asarray(motion))
        if kernel is not None:
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        # Luminance noise on the gray picture: a third of the work of per-channel noise.
        img = cv2.cvtColor(self.noise.apply(img), cv2.COLOR_GRAY2BGR)
        return apply_cover(img, cover, self.skin)


def render_camera(job: CameraJob, progress: Progress | None = None, queue: object = None) -> int:
    """Render and encode one camera's video (mp4v); returns the number of frames written."""
    fr = FrameRenderer(job.camera, job.markers, job.marker_length, job.dictionary,
                       job.noise_sigma, job.seed)
    size = (job.camera.width, job.camera.height)
    writer = cv2.VideoWriter(job.path, cv2.VideoWriter.fourcc(*"mp4v"), job.fps, size)
    if not writer.isOpened():
        raise OSError(f"cannot open a video writer for {job.path} (mp4v)")
    n = len(job.times)
    try:
        for i in range(n):
            motion = fr.image_motion(job.r_wc_open[i], job.c_w_open[i], job.r_wc_close[i], job.c_w_close[i])
            cover = cover_fraction(float(job.times[i]), list(job.covers))
            writer.write(fr.render(job.r_wc[i], job.c_w[i], motion, cover))
            if (i + 1) % 10 == 0 or i + 1 == n:
                if progress is not None:
                    progress(job.name, i + 1, n)
                if queue is not None:
                    queue.put((job.name, i + 1, n))
    finally:
        writer.release()
    return n


def _camera_poses(pose_at: PoseAt, times: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    pos, rot = pose_at(times)
    r_wc, c_w = camera_pose(rot, np.asarray(pos, float), name)
    return r_wc.as_matrix().reshape(-1, 3, 3), np.asarray(c_w).reshape(-1, 3)


def frame_times(start: float, t_end: float, fps: float) -> np.ndarray:
    """Wall times of the frames of a constant-rate video starting at `start`, all before t_end."""
    n = int(np.floor((t_end - start) * fps + 1e-9))
    return start + np.arange(max(n, 0)) / fps


def format_truth(times: np.ndarray, pos: np.ndarray, rot: Rotation) -> str:
    mats = rot.as_matrix().reshape(-1, 9)
    lines = [TRUTH_HEADER]
    for t, p, m in zip(times, pos, mats, strict=True):
        lines.append(f"{t:.6f}," + ",".join(f"{v:.9f}" for v in p) + ","
                     + ",".join(f"{v:.12f}" for v in m))
    return "\n".join(lines) + "\n"


def experiment_yaml(video_start: dict[str, float], dictionary: str, length: float) -> str:
    starts = ", ".join(f"{k}: {v!r}" for k, v in video_start.items())
    return (
        "# Rendered by `annotator simulate`: a synthetic experiment with known truth (truth.csv).\n"
        f"markers: {{file: marker_positions.dat, dictionary: {dictionary}, length: {length!r}}}\n"
        "rig: rig.yaml\n"
        "videos: {front: front.mp4, back: back.mp4}\n"
        "rssi: rssi\n"
        "sync:\n"
        "  mode: manual\n"
        f"  video_start: {{{starts}}}\n"
    )


def path_yaml(waypoints: Sequence[Sequence[float]]) -> str:
    """The planned path in the YAML `annotator evaluate --path` reads."""
    pts = ", ".join(f"[{float(x)!r}, {float(y)!r}]" for x, y in waypoints)
    return ("# Planned path of this render (room xy, m): `annotator evaluate TRAJ.csv --path path.yaml`.\n"
            f"waypoints: [{pts}]\n")


def render_experiment(
    out_dir: str | Path,
    pose_at: PoseAt,
    t_span: tuple[float, float],
    *,
    width: int = 960,
    height: int = 540,
    fps: float = 30.0,
    start_offset: float = 0.41,
    covers: Sequence[tuple[float, float]] = (),
    seed: int = 0,
    noise_sigma: float = 2.0,
    exposure: float = 1 / 120,
    jobs: int = 1,
    marker_file: str | Path | None = None,
    dictionary: str = "DICT_6X6_50",
    marker_length: float = 0.298,
    cameras: dict[str, CameraModel] | None = None,
    progress: Progress | None = None,
) -> RenderResult:
    """Render the rig's two videos along `pose_at` over wall times `t_span` and write the experiment.

    The front video starts at t_span[0], the back one `start_offset` s later; every frame lies
    inside t_span. `covers` are (start, duration) in seconds after t_span[0]: both lenses are
    covered by a hand at the same wall time. A `PolylineTrajectory` also gets its planned path
    written to path.yaml. Returns the paths written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker_src = Path(marker_file) if marker_file is not None else site_dir("tetam") / "marker_positions.dat"
    markers = read_marker_map(marker_src)
    aruco_dictionary(dictionary)  # fail early on a bad name
    cams = cameras or default_cameras(width, height)
    t0, t1 = float(t_span[0]), float(t_span[1])
    starts = {"front": t0, "back": t0 + start_offset}
    wall_covers = tuple((t0 + s, d) for s, d in covers)

    job_list = []
    for idx, name in enumerate(("front", "back")):
        times = frame_times(starts[name], t1, fps)
        if not len(times):
            raise ValueError(f"time span {t1 - t0:.3f} s leaves no frames for the {name} camera")
        r, c = _camera_poses(pose_at, times, name)
        ro, co = _camera_poses(pose_at, times - exposure / 2, name)
        rc, cc = _camera_poses(pose_at, times + exposure / 2, name)
        job_list.append(CameraJob(name, cams[name], str(out / f"{name}.mp4"), fps, times, r, c, ro, co,
                                  rc, cc, markers, marker_length, dictionary, wall_covers,
                                  noise_sigma, seed * 1000 + idx))

    for name, cam in cams.items():
        write_calibration(str(out / f"{name}.yaml"), cam)
    (out / "rig.yaml").write_text(RIG_YAML, encoding="utf-8")
    shutil.copyfile(marker_src, out / "marker_positions.dat")
    (out / "rssi").mkdir(exist_ok=True)
    (out / "experiment.yaml").write_text(experiment_yaml(starts, dictionary, marker_length), encoding="utf-8")

    all_t = np.unique(np.concatenate([j.times for j in job_list]))
    pos, rot = pose_at(all_t)
    (out / "truth.csv").write_text(format_truth(all_t, np.asarray(pos, float), rot), encoding="utf-8")
    if isinstance(pose_at, PolylineTrajectory):
        (out / "path.yaml").write_text(path_yaml(pose_at.waypoints), encoding="utf-8")
    else:  # a path.yaml left by an earlier render into the same folder would not belong to this one
        (out / "path.yaml").unlink(missing_ok=True)

    frames = _run_jobs(job_list, jobs, progress)
    log.info("rendered %s into %s", frames, out)
    return RenderResult(out, out / "experiment.yaml", out / "truth.csv",
                        {j.name: Path(j.path) for j in job_list}, frames)


def _run_jobs(job_list: list[CameraJob], jobs: int, progress: Progress | None) -> dict[str, int]:
    if jobs <= 1 or len(job_list) == 1:
        return {j.name: render_camera(j, progress) for j in job_list}
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe with OpenCV's and rich's threads
    with ctx.Manager() as manager:
        queue = manager.Queue()
        with ProcessPoolExecutor(max_workers=min(jobs, len(job_list)), mp_context=ctx) as pool:
            futures = {j.name: pool.submit(render_camera, j, None, queue) for j in job_list}
            pending = set(futures)
            while pending:
                try:
                    name, done, total = queue.get(timeout=0.2)
                    if progress is not None:
                        progress(name, done, total)
                except Exception:  # noqa: BLE001 - queue.Empty from a manager proxy
                    pass
                pending = {n for n in pending if not futures[n].done()}
            return {n: f.result() for n, f in futures.items()}
