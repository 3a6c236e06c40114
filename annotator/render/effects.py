"""Image degradations applied after projection: motion blur, sensor noise, the hands-cover, and
what a real camera adds (defocus, light, compression: `Imaging`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def motion_kernel(displacement: np.ndarray) -> np.ndarray | None:
    """Line kernel for an image motion of `displacement` px (dx, dy) during the exposure.

    Centred on the middle of the exposure, so blur widens edges without shifting them.
    None when the motion is too small to matter.
    """
    d = np.asarray(displacement, float)
    length = float(np.hypot(*d))
    if length < 0.3:
        return None
    half = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    n = max(4, int(np.ceil(length * 4)))
    for s in np.linspace(-0.5, 0.5, n):
        x, y = half + s * d[0], half + s * d[1]
        ix, iy = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - ix, y - iy
        k[iy, ix] += (1 - fx) * (1 - fy)
        k[iy, ix + 1] += fx * (1 - fy)
        k[iy + 1, ix] += (1 - fx) * fy
        k[iy + 1, ix + 1] += fx * fy
    return k / k.sum()


def flicker_gain(t: np.ndarray, amplitude: float, hz: float, phase: float = 0.0) -> np.ndarray:
    """Brightness factor of the picture at wall time(s) t: 1 + amplitude * sin(2 pi hz t + phase).

    Lamps on mains power flicker at twice its frequency (100 Hz in Europe); the amplitude is
    what ends up in the picture, after the exposure has averaged part of it away. With a rolling
    shutter each row has its own time, so the flicker shows as horizontal bands.
    """
    return 1.0 + amplitude * np.sin(
        2 * np.pi * hz * (np.asarray(t, float) % (1e4 / max(hz, 1e-9))) + phase
    )


class NoiseBank:
    """A few precomputed Gaussian noise frames, drawn at random: realistic enough, and cheap."""

    def __init__(
        self, shape: tuple[int, ...], sigma: float, rng: np.random.Generator, count: int = 6
    ):
        self.sigma = sigma
        self.frames = (
            [sigma * rng.standard_normal(shape, dtype=np.float32) for _ in range(count)]
            if sigma > 0
            else []
        )
        self.rng = rng

    def apply(self, img: np.ndarray) -> np.ndarray:
        if not self.frames:
            return img
        noise = self.frames[int(self.rng.integers(len(self.frames)))]
        return cv2.add(img, noise, dtype=cv2.CV_8U)


def cover_fraction(t: float, events: list[tuple[float, float]], ramp: float = 0.15) -> float:
    """How much of the lens a hand covers at wall time t: 0 -> 1 over `ramp` s, held, then 1 -> 0."""
    c = 0.0
    for start, duration in events:
        if t < start or t > start + duration + ramp:
            continue
        if t < start + ramp:
            c = max(c, (t - start) / ramp)
        elif t <= start + duration:
            c = 1.0
        else:
            c = max(c, 1.0 - (t - start - duration) / ramp)
    return float(np.clip(c, 0.0, 1.0))


def apply_cover(img: np.ndarray, fraction: float, skin: np.ndarray) -> np.ndarray:
    """Slide a dark, skin-toned occluder up from the bottom; at 1.0 it fills the frame."""
    if fraction <= 0.0:
        return img
    h, w = img.shape[:2]
    # Edge of the hand: a gentle curve (fingers), rising from below the frame to above it.
    x = np.linspace(-1.0, 1.0, w, dtype=np.float32)
    edge = h * (1.15 - 1.45 * fraction) + 0.12 * h * x**2
    rows = np.arange(h, dtype=np.float32)[:, None]
    alpha = np.clip((rows - edge[None, :]) / 12.0 + 0.5, 0.0, 1.0)[..., None]  # soft 12 px edge
    # Light leaking around the hand fades the rest of the picture as it closes in.
    dim = 1.0 - 0.5 * fraction
    out = img.astype(np.float32) * dim * (1.0 - alpha) + skin.astype(np.float32) * alpha
    return np.clip(out, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Imaging:
    """What a real camera and room add to the picture (`annotator simulate`'s imaging options);
    the default adds nothing. Applied in the order light meets the sensor: defocus, light
    (vignetting, an uneven and changing light level, auto-exposure steps), then, after the
    sensor noise, compression."""

    defocus_px: float = 0.0  # Gaussian blur sigma of a lens slightly out of focus, px
    jpeg_quality: int = 0  # every frame through JPEG at this quality (1-100); 0 = no compression
    vignetting: float = 0.0  # the corners this much darker than the centre (0.4 = 40 %)
    uneven_light: float = 0.0  # a brightness gradient of +-this across the picture, turning slowly
    light_change: float = 0.0  # the light level drifts by +-this over time (10 s period)
    exposure_steps: float = 0.0  # auto-exposure: a new gain within +-this every 3 s

    def __post_init__(self) -> None:
        for name in ("defocus_px", "vignetting", "uneven_light", "light_change", "exposure_steps"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, not {v!r}")
        if self.vignetting >= 1 or self.uneven_light >= 1 or self.light_change >= 1:
            raise ValueError("vignetting, uneven_light and light_change must be below 1")
        if self.exposure_steps >= 1:
            raise ValueError("exposure_steps must be below 1")
        if not 0 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 0..100, not {self.jpeg_quality!r}")

    @property
    def active(self) -> bool:
        return any(
            v > 0
            for v in (
                self.defocus_px,
                self.jpeg_quality,
                self.vignetting,
                self.uneven_light,
                self.light_change,
                self.exposure_steps,
            )
        )


class CameraImaging:
    """:class:`Imaging` for one camera: its vignetting map and its draws of light and exposure."""

    EXPOSURE_STEP_S = 3.0
    LIGHT_PERIOD_S = 10.0

    def __init__(self, imaging: Imaging, width: int, height: int, seed: int) -> None:
        self.imaging = imaging
        rng = np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 7]))
        y, x = np.mgrid[0:height, 0:width].astype(np.float32)
        self._x = (x - (width - 1) / 2) / (np.hypot(width, height) / 2)
        self._y = (y - (height - 1) / 2) / (np.hypot(width, height) / 2)
        # corners (radius 1) this much darker, falling off with the square of the radius
        self._vignette = 1.0 - imaging.vignetting * (self._x**2 + self._y**2)
        self._light_angle = float(rng.uniform(0, 2 * np.pi))
        self._light_phase = float(rng.uniform(0, 2 * np.pi))
        self._seed = seed

    def gain(self, t: float) -> np.ndarray | float:
        """Brightness factor of each pixel (or of all) at wall time t."""
        im = self.imaging
        level = 1.0 + im.light_change * np.sin(
            2 * np.pi * t / self.LIGHT_PERIOD_S + self._light_phase
        )
        if im.exposure_steps > 0:
            slot = int(np.floor(t / self.EXPOSURE_STEP_S))
            step = np.random.default_rng([self._seed & 0xFFFFFFFF, 8, slot & 0xFFFFFFFF])
            level *= 1.0 + im.exposure_steps * float(step.uniform(-1, 1))
        if im.vignetting == 0 and im.uneven_light == 0:
            return float(level)
        gain = self._vignette * np.float32(level)
        if im.uneven_light > 0:
            a = self._light_angle + 0.05 * t  # the light's direction turns as the view changes
            gain = gain * (1.0 + im.uneven_light * (np.cos(a) * self._x + np.sin(a) * self._y))
        return gain

    def optics(self, gray: np.ndarray, t: float) -> np.ndarray:
        """Defocus and light on the gray picture, before the sensor noise."""
        im = self.imaging
        if im.defocus_px > 0:
            gray = cv2.GaussianBlur(gray, (0, 0), im.defocus_px, borderType=cv2.BORDER_REPLICATE)
        gain = self.gain(t)
        if isinstance(gain, float) and gain == 1.0:
            return gray
        return np.clip(gray.astype(np.float32) * gain + 0.5, 0, 255).astype(np.uint8)

    def compress(self, img: np.ndarray) -> np.ndarray:
        """The picture after JPEG at the chosen quality (none at 0)."""
        q = self.imaging.jpeg_quality
        if q <= 0:
            return img
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(q)])
        if not ok:
            raise RuntimeError("OpenCV could not encode a JPEG frame")
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if out is None:
            raise RuntimeError("OpenCV could not decode its own JPEG frame")
        return np.asarray(out)
