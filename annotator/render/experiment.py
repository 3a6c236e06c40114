"""Render a whole simulated experiment: two rig videos along a known trajectory plus the files
`annotator track` reads (experiment.yaml, rig.yaml, calibrations, marker map) and truth.csv."""

from __future__ import annotations

import logging
import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from queue import Queue

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.render.camera import (
    RIG_EXTRINSICS,
    CameraModel,
    build_distortion_map,
    camera_pose,
    default_cameras,
    rig_yaml,
    write_calibration,
)
from annotator.render.effects import (
    NoiseBank,
    apply_cover,
    cover_fraction,
    flicker_gain,
    motion_kernel,
)
from annotator.render.errors import (
    FileErrors,
    perturb_cameras,
    perturb_markers,
    perturb_rig,
    perturbation_record,
    surveyed_subset,
)
from annotator.render.scene import MarkerScene
from annotator.render.textures import (
    MarkerTextures,
    aruco_dictionary,
    background_panorama,
    skin_texture,
)
from annotator.render.trajectory import PolylineTrajectory
from bgt_core.formats.markers import MarkerPose, format_dat, read_marker_map
from bgt_core.sites import site_dir

log = logging.getLogger(__name__)

PoseAt = Callable[[np.ndarray], tuple[np.ndarray, Rotation]]
# progress(camera, frames_done, frames_total)
Progress = Callable[[str, int, int], None]
TRUTH_HEADER = "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33"
# A rolling-shutter frame is drawn as horizontal bands, each at the pose of its middle row's
# time; bands span at most this long, so a row's pose is off by at most half of it.
BAND_S = 0.0005


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
    band_rows: tuple[int, ...] = ()  # rolling shutter: output row boundaries of the bands (B+1)
    r_wc_bands: np.ndarray | None = None  # (N, B, 3, 3) at each band's middle-row time
    c_w_bands: np.ndarray | None = None  # (N, B, 3)
    gains: np.ndarray | None = None  # (N, height) brightness factor of each row (flicker)


@dataclass(frozen=True)
class RenderResult:
    out_dir: Path
    experiment: Path
    truth: Path
    videos: dict[str, Path]
    frames: dict[str, int]


class FrameRenderer:
    """Draws frames of one camera; holds the per-camera precomputed maps and textures."""

    def __init__(
        self,
        camera: CameraModel,
        markers: dict[int, MarkerPose],
        marker_length: float,
        dictionary: str,
        noise_sigma: float,
        seed: int,
    ) -> None:
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
        return self.pano[y0 : y0 + ch, x0 : x0 + cw].copy()

    def image_motion(
        self, r_open: np.ndarray, c_open: np.ndarray, r_close: np.ndarray, c_close: np.ndarray
    ) -> np.ndarray:
        """Median pixel displacement during the exposure of the marker corners in view.

        Falls back to points on a wall 3 m ahead when no marker is in the picture.
        """
        scene, cam = self.scene, self.camera
        vis = scene.visible(r_open, c_open)
        world = (
            np.vstack([m.centre + scene.inner @ m.rotation.T for m in vis])
            if vis
            else np.zeros((0, 3))
        )
        grid = np.array([[x, y, 3.0] for x in (-1.0, 0.0, 1.0) for y in (-0.6, 0.0, 0.6)])
        k = cam.K

        def proj(pts: np.ndarray, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            pc = (pts - c) @ r
            uv = (pc @ k.T)[:, :2] / np.maximum(pc[:, 2:3], 1e-6)
            ok = (
                (pc[:, 2] > 0.05)
                & (uv[:, 0] >= 0)
                & (uv[:, 0] < cam.width)
                & (uv[:, 1] >= 0)
                & (uv[:, 1] < cam.height)
            )
            return uv, ok

        a, ok = proj(world, r_open, c_open)
        if not ok.any():
            world = c_open + grid @ r_open.T
            a, ok = proj(world, r_open, c_open)
        b, _ = proj(world, r_close, c_close)
        # The median: one marker sliding past the image border must not blur the whole frame.
        return np.median(b[ok] - a[ok], axis=0)

    def render_bands(
        self,
        r_wc: np.ndarray,
        c_w: np.ndarray,
        band_rows: Sequence[int],
        r_bands: np.ndarray,
        c_bands: np.ndarray,
    ) -> np.ndarray:
        """The distorted gray picture of a rolling-shutter frame: output rows
        band_rows[b]:band_rows[b+1] seen from pose (r_bands[b], c_bands[b]).

        Each band draws only the strip of the canvas its rows sample from, so a frame costs
        little more than a global-shutter one. Visibility and the background come from the
        frame's own pose (they do not change in a few milliseconds).
        """
        canvas = self._background(r_wc)
        order = self.scene.paint_order(r_wc, c_w)
        out = np.empty((self.camera.height, self.camera.width), np.uint8)
        span = self.dmap.row_span
        for b in range(len(band_rows) - 1):
            r0, r1 = band_rows[b], band_rows[b + 1]
            if r1 <= r0:
                continue
            lo, hi = int(span[r0:r1, 0].min()), int(span[r0:r1, 1].max())
            strip = canvas[lo:hi].copy()
            k = self.dmap.canvas_K.copy()
            k[1, 2] -= lo  # the strip's own pinhole matrix
            self.scene.draw(strip, k, r_bands[b], c_bands[b], self.textures, order=order)
            map1 = self.dmap.map1[r0:r1].copy()
            map1[..., 1] -= lo  # integer part of the sampled canvas row
            out[r0:r1] = cv2.remap(
                strip,
                map1,
                self.dmap.map2[r0:r1],
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        return out

    def render(
        self,
        r_wc: np.ndarray,
        c_w: np.ndarray,
        motion: np.ndarray | tuple[float, float] = (0.0, 0.0),
        cover: float = 0.0,
        bands: tuple[Sequence[int], np.ndarray, np.ndarray] | None = None,
        gain: np.ndarray | None = None,
    ) -> np.ndarray:
        """One BGR frame: markers on the background, lens distortion, blur, brightness, cover,
        noise. `bands` = (row boundaries, rotations, centres) renders a rolling shutter; `gain`
        is a brightness factor per row (flicker)."""
        if bands is None:
            canvas = self._background(r_wc)
            self.scene.draw(canvas, self.dmap.canvas_K, r_wc, c_w, self.textures)
            img = cv2.remap(
                canvas,
                self.dmap.map1,
                self.dmap.map2,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        else:
            img = self.render_bands(r_wc, c_w, *bands)
        kernel = motion_kernel(np.asarray(motion))
        if kernel is not None:
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        if gain is not None:
            img = np.clip(img * np.asarray(gain, np.float32)[:, None] + 0.5, 0, 255).astype(
                np.uint8
            )
        # Luminance noise on the gray picture: a third of the work of per-channel noise.
        img = cv2.cvtColor(self.noise.apply(img), cv2.COLOR_GRAY2BGR)
        return apply_cover(img, cover, self.skin)


def render_camera(
    job: CameraJob,
    progress: Progress | None = None,
    queue: Queue[tuple[str, int, int]] | None = None,
) -> int:
    """Render and encode one camera's video (mp4v); returns the number of frames written."""
    fr = FrameRenderer(
        job.camera, job.markers, job.marker_length, job.dictionary, job.noise_sigma, job.seed
    )
    size = (job.camera.width, job.camera.height)
    writer = cv2.VideoWriter(job.path, cv2.VideoWriter.fourcc(*"mp4v"), job.fps, size)
    if not writer.isOpened():
        raise OSError(f"cannot open a video writer for {job.path} (mp4v)")
    n = len(job.times)
    try:
        for i in range(n):
            motion = fr.image_motion(
                job.r_wc_open[i], job.c_w_open[i], job.r_wc_close[i], job.c_w_close[i]
            )
            cover = cover_fraction(float(job.times[i]), list(job.covers))
            bands = None
            if job.r_wc_bands is not None and job.c_w_bands is not None:
                bands = (job.band_rows, job.r_wc_bands[i], job.c_w_bands[i])
            gain = None if job.gains is None else job.gains[i]
            writer.write(fr.render(job.r_wc[i], job.c_w[i], motion, cover, bands, gain))
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


def rolling_bands(height: int, readout: float) -> tuple[int, ...]:
    """Row boundaries of the bands a frame is drawn in (none for a global shutter)."""
    if readout <= 0:
        return ()
    n = int(np.clip(np.ceil(readout / BAND_S), 2, height))
    return tuple(int(v) for v in np.round(np.linspace(0, height, n + 1)))


def row_time_offsets(band_rows: Sequence[int], height: int, readout: float) -> np.ndarray:
    """Time after the frame stamp at which each band's middle row is seen: row v at readout*v/height."""
    rows = np.asarray(band_rows, float)
    return readout * ((rows[:-1] + rows[1:] - 1) / 2) / height


def frame_times(start: float, t_end: float, fps: float) -> np.ndarray:
    """Wall times of the frames of a constant-rate video starting at `start`, all before t_end."""
    n = int(np.floor((t_end - start) * fps + 1e-9))
    return start + np.arange(max(n, 0)) / fps


def format_truth(times: np.ndarray, pos: np.ndarray, rot: Rotation) -> str:
    mats = rot.as_matrix().reshape(-1, 9)
    lines = [TRUTH_HEADER]
    for t, p, m in zip(times, pos, mats, strict=True):
        lines.append(
            f"{t:.6f}," + ",".join(f"{v:.9f}" for v in p) + "," + ",".join(f"{v:.12f}" for v in m)
        )
    return "\n".join(lines) + "\n"


def experiment_yaml(
    video_start: dict[str, float],
    dictionary: str,
    length: float,
    media: str = "",
    rssi_dir: str = "rssi",
) -> str:
    """experiment.yaml of a render; `media` is the folder of the videos and of `rssi_dir` (the
    RSSI readings' folder) relative to it."""
    starts = ", ".join(f"{k}: {v!r}" for k, v in video_start.items())
    return (
        "# Rendered by `annotator simulate`: a synthetic experiment with known truth (truth.csv).\n"
        f"markers: {{file: marker_positions.dat, dictionary: {dictionary}, length: {length!r}}}\n"
        "rig: rig.yaml\n"
        f"videos: {{front: {media}front.mp4, back: {media}back.mp4}}\n"
        f"rssi: {media}{rssi_dir}\n"
        "sync:\n"
        "  mode: manual\n"
        f"  video_start: {{{starts}}}\n"
    )


def path_yaml(waypoints: Sequence[Sequence[float]]) -> str:
    """The planned path in the YAML `annotator evaluate --path` reads."""
    pts = ", ".join(f"[{float(x)!r}, {float(y)!r}]" for x, y in waypoints)
    return (
        "# Planned path of this render (room xy, m): `annotator evaluate TRAJ.csv --path path.yaml`.\n"
        f"waypoints: [{pts}]\n"
    )


def write_experiment_files(
    out_dir: str | Path,
    cameras: dict[str, CameraModel],
    markers: dict[int, MarkerPose],
    video_start: dict[str, float],
    *,
    dictionary: str = "DICT_6X6_50",
    marker_length: float = 0.298,
    readout: float = 0.0,
    exposure: float | None = None,
    errors: FileErrors | None = None,
    settings: dict[str, object] | None = None,
    rssi_dir: str = "rssi",
) -> dict[str, object]:
    """Write what the annotator reads (experiment.yaml, rig.yaml, calibrations, marker map, an
    empty `rssi_dir` folder for the readings) with `errors` applied, the exact files under
    true/ (with a true/experiment.yaml that uses the same videos), and perturbation.yaml (true vs written values). `exposure` (s),
    when given, goes into every calibration as the camera's known setting (`exposure_s`). The
    videos are not touched: a render's folder can be given other errors without rendering again.
    Returns the perturbation record."""
    out = Path(out_dir)
    errors = errors or FileErrors()
    written_markers = surveyed_subset(
        perturb_markers(markers, errors.survey_m, errors.survey_deg, errors.seed),
        errors.surveyed,
        errors.seed,
    )
    true_rig = {name: RIG_EXTRINSICS[name] for name in cameras}
    written_rig = perturb_rig(true_rig, errors.rig_m, errors.rig_deg, errors.seed)
    written_cams = perturb_cameras(
        cameras, errors.focal_rel, errors.principal_px, errors.distortion, errors.seed
    )
    written_readout = readout if errors.write_readout else 0.0

    (out / "true").mkdir(parents=True, exist_ok=True)
    (out / rssi_dir).mkdir(exist_ok=True)
    for folder, cams, rig, mk, ro, media in (
        (out, written_cams, written_rig, written_markers, written_readout, ""),
        (out / "true", cameras, true_rig, markers, readout, "../"),
    ):
        for name, cam in cams.items():
            write_calibration(str(folder / f"{name}.yaml"), cam, ro, exposure)
        (folder / "rig.yaml").write_text(rig_yaml(rig), encoding="utf-8")
        (folder / "marker_positions.dat").write_text(format_dat(mk), encoding="utf-8")
        (folder / "experiment.yaml").write_text(
            experiment_yaml(video_start, dictionary, marker_length, media, rssi_dir),
            encoding="utf-8",
        )
    record = perturbation_record(
        {**(settings or {}), **asdict(errors), "readout_s": float(readout)},
        markers,
        written_markers,
        cameras,
        written_cams,
        true_rig,
        written_rig,
        readout,
        written_readout,
    )
    from bgt_core.safe_yaml import dump

    text = (
        "# What `annotator simulate` changed in the files handed to the annotator: true vs written\n"
        "# values (offsets are written - true; rotation offsets are rotation vectors, degrees, taking\n"
        "# the true orientation to the written one, world frame for markers, bundle frame for the rig).\n"
    )
    (out / "perturbation.yaml").write_text(text + dump(record, sort_keys=False), encoding="utf-8")
    return record


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
    lens: str = "mild",
    k1: float | None = None,
    readout: float = 0.0,
    flicker: float = 0.0,
    flicker_hz: float = 100.0,
    errors: FileErrors | None = None,
    progress: Progress | None = None,
    rssi_dir: str = "rssi",
) -> RenderResult:
    """Render the rig's two videos along `pose_at` over wall times `t_span` and write the experiment.

    The front video starts at t_span[0], the back one `start_offset` s later; every frame lies
    inside t_span. `covers` are (start, duration) in seconds after t_span[0]: both lenses are
    covered by a hand at the same wall time. A `PolylineTrajectory` also gets its planned path
    written to path.yaml. Returns the paths written.

    The video is always exact: `cameras` (or the `lens` of `default_cameras`, `k1` overriding its
    first coefficient), a rolling shutter whose row v of a frame stamped t is seen at
    t + readout*v/height, and a brightness `flicker` (relative amplitude at `flicker_hz`, seen per
    row). `errors` only change the files written for the annotator (see `write_experiment_files`).
    experiment.yaml's `rssi:` names `rssi_dir`, created empty here.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker_src = (
        Path(marker_file) if marker_file is not None else site_dir("tetam") / "marker_positions.dat"
    )
    markers = read_marker_map(marker_src)
    aruco_dictionary(dictionary)  # fail early on a bad name
    cams = cameras or default_cameras(width, height, lens, k1)
    if not 0 <= readout < 1 / fps:
        raise ValueError(
            f"readout {readout} s must be between 0 and the frame interval {1 / fps:.4f} s"
        )
    t0, t1 = float(t_span[0]), float(t_span[1])
    starts = {"front": t0, "back": t0 + start_offset}
    wall_covers = tuple((t0 + s, d) for s, d in covers)
    errors = errors or FileErrors(seed=seed)
    flicker_phase = float(
        np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 4])).uniform(0, 2 * np.pi)
    )

    job_list = []
    for idx, name in enumerate(("front", "back")):
        cam = cams[name]
        times = frame_times(starts[name], t1, fps)
        if not len(times):
            raise ValueError(f"time span {t1 - t0:.3f} s leaves no frames for the {name} camera")
        band_rows = rolling_bands(cam.height, readout)
        # Global shutter: the frame is seen at its stamp; rolling: at its middle row's time.
        mid = readout * (cam.height - 1) / (2 * cam.height)
        r, c = _camera_poses(pose_at, times, name)
        ro, co = _camera_poses(pose_at, times + mid - exposure / 2, name)
        rc, cc = _camera_poses(pose_at, times + mid + exposure / 2, name)
        rb = cb = None
        if band_rows:
            offs = row_time_offsets(band_rows, cam.height, readout)
            rb, cb = _camera_poses(pose_at, (times[:, None] + offs[None, :]).ravel(), name)
            rb, cb = rb.reshape(len(times), len(offs), 3, 3), cb.reshape(len(times), len(offs), 3)
        gains = None
        if flicker > 0:
            row_t = times[:, None] + readout * np.arange(cam.height)[None, :] / cam.height
            gains = flicker_gain(row_t, flicker, flicker_hz, flicker_phase).astype(np.float32)
        job_list.append(
            CameraJob(
                name,
                cam,
                str(out / f"{name}.mp4"),
                fps,
                times,
                r,
                c,
                ro,
                co,
                rc,
                cc,
                markers,
                marker_length,
                dictionary,
                wall_covers,
                noise_sigma,
                seed * 1000 + idx,
                band_rows,
                rb,
                cb,
                gains,
            )
        )

    settings: dict[str, object] = {
        "lens": lens if cameras is None else "custom",
        "k1": k1,
        "exposure_s": float(exposure),
        "flicker": float(flicker),
        "flicker_hz": float(flicker_hz),
        "flicker_phase_rad": flicker_phase,
        "render_seed": int(seed),
    }
    write_experiment_files(
        out,
        cams,
        markers,
        starts,
        dictionary=dictionary,
        marker_length=marker_length,
        readout=readout,
        exposure=exposure,
        errors=errors,
        settings=settings,
        rssi_dir=rssi_dir,
    )

    all_t = np.unique(np.concatenate([j.times for j in job_list]))
    pos, rot = pose_at(all_t)
    (out / "truth.csv").write_text(
        format_truth(all_t, np.asarray(pos, float), rot), encoding="utf-8"
    )
    if isinstance(pose_at, PolylineTrajectory):
        (out / "path.yaml").write_text(path_yaml(pose_at.waypoints), encoding="utf-8")
    else:  # a path.yaml left by an earlier render into the same folder would not belong to this one
        (out / "path.yaml").unlink(missing_ok=True)

    frames = _run_jobs(job_list, jobs, progress)
    log.info("rendered %s into %s", frames, out)
    return RenderResult(
        out,
        out / "experiment.yaml",
        out / "truth.csv",
        {j.name: Path(j.path) for j in job_list},
        frames,
    )


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
