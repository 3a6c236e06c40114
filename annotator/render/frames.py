"""Drawing one camera's video: the picture of each frame (markers, lens, rolling shutter, blur,
brightness, hands, noise) and its encoding. `annotator.render.experiment` assembles the jobs."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from queue import Queue

import cv2
import numpy as np

from annotator.core.rolling_shutter import row_delay
from annotator.render.camera import CameraModel, build_distortion_map
from annotator.render.effects import (
    CameraImaging,
    Imaging,
    NoiseBank,
    apply_cover,
    cover_fraction,
    motion_kernel,
)
from annotator.render.scene import MarkerScene
from annotator.render.slate import SlateShot, slate_frame
from annotator.render.textures import (
    MarkerTextures,
    aruco_dictionary,
    background_panorama,
    skin_texture,
)
from bgt_core.formats.markers import MarkerPose

# progress(camera, frames_done, frames_total)
Progress = Callable[[str, int, int], None]
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
    imaging: Imaging = Imaging()  # what a real camera adds (defocus, light, compression)
    marker_scales: dict[int, float] | None = None  # printed side / nominal length, per marker
    # The clock slate: frames stamped before slate_span[0] or after slate_span[1] film it.
    slate: SlateShot | None = None
    slate_span: tuple[float, float] = (-np.inf, np.inf)
    readout: float = 0.0
    exposure: float = 0.0


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
        imaging: Imaging | None = None,
        marker_scales: dict[int, float] | None = None,
    ) -> None:
        self.camera = camera
        self.scene = MarkerScene(markers, marker_length, marker_scales)
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
        self.imaging = (
            CameraImaging(imaging, camera.width, camera.height, seed)
            if imaging is not None and imaging.active
            else None
        )

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
            np.vstack([m.centre + (m.scale * scene.inner) @ m.rotation.T for m in vis])
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
        t: float = 0.0,
    ) -> np.ndarray:
        """One BGR frame: markers on the background, lens distortion, blur, brightness, cover,
        noise. `bands` = (row boundaries, rotations, centres) renders a rolling shutter; `gain`
        is a brightness factor per row (flicker); `t` the frame's wall time, for the imaging
        effects that change with time (light, exposure)."""
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
        return self.finish(img, cover, gain, t)

    def finish(
        self, img: np.ndarray, cover: float = 0.0, gain: np.ndarray | None = None, t: float = 0.0
    ) -> np.ndarray:
        """What the camera adds to the gray picture (flicker, imaging, noise, a covering hand)
        and its compression; a BGR frame."""
        if gain is not None:
            img = np.clip(img * np.asarray(gain, np.float32)[:, None] + 0.5, 0, 255).astype(
                np.uint8
            )
        if self.imaging is not None:
            img = self.imaging.optics(img, t)
        # Luminance noise on the gray picture: a third of the work of per-channel noise.
        img = cv2.cvtColor(self.noise.apply(img), cv2.COLOR_GRAY2BGR)
        img = apply_cover(img, cover, self.skin)
        return img if self.imaging is None else self.imaging.compress(img)


def render_camera(
    job: CameraJob,
    progress: Progress | None = None,
    queue: Queue[tuple[str, int, int]] | None = None,
) -> int:
    """Render and encode one camera's video (mp4v); returns the number of frames written."""
    fr = FrameRenderer(
        job.camera,
        job.markers,
        job.marker_length,
        job.dictionary,
        job.noise_sigma,
        job.seed,
        job.imaging,
        job.marker_scales,
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
            t = float(job.times[i])
            if job.slate is not None and not job.slate_span[0] <= t <= job.slate_span[1]:
                cam = job.camera
                picture = slate_frame(
                    job.slate, t, cam.width, cam.height, job.readout, job.exposure
                )
                writer.write(fr.finish(picture, 0.0, gain, t))
            else:
                writer.write(fr.render(job.r_wc[i], job.c_w[i], motion, cover, bands, gain, t))
            if (i + 1) % 10 == 0 or i + 1 == n:
                if progress is not None:
                    progress(job.name, i + 1, n)
                if queue is not None:
                    queue.put((job.name, i + 1, n))
    finally:
        writer.release()
    return n


def rolling_bands(height: int, readout: float) -> tuple[int, ...]:
    """Row boundaries of the bands a frame is drawn in (none for a global shutter)."""
    if readout <= 0:
        return ()
    n = int(np.clip(np.ceil(readout / BAND_S), 2, height))
    return tuple(int(v) for v in np.round(np.linspace(0, height, n + 1)))


def row_time_offsets(band_rows: Sequence[int], height: int, readout: float) -> np.ndarray:
    """Time after the frame stamp at which each band's middle row is seen: row v at readout*v/height."""
    rows = np.asarray(band_rows, float)
    return row_delay((rows[:-1] + rows[1:] - 1) / 2, height, readout)
