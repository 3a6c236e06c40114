"""Image degradations applied after projection: motion blur, sensor noise, the hands-cover."""

from __future__ import annotations

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
