"""Images the renderer pastes: marker textures (with quiet zone) at several resolutions,
a wrap-around background panorama and the skin-toned occluder of the hands-cover event."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

QUIET_CELLS = 1  # white margin around the black square, in marker cells
MARKER_CELLS = 8  # DICT_6X6: 6 data bits plus a one-cell black border on each side
CELL_PX_LEVELS = (96, 48, 24, 12, 6, 3)  # texture resolutions, largest first


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """`DICT_6X6_50` -> the predefined dictionary; ValueError names an unknown one."""
    code = getattr(cv2.aruco, name, None)
    if not name.startswith("DICT_") or not isinstance(code, int):
        raise ValueError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(code)


@dataclass
class MarkerTextures:
    """Lazily built marker images; the texture of a level spans (8 + 2*QUIET_CELLS) cells."""

    dictionary: cv2.aruco.Dictionary
    black: int = 28
    white: int = 215
    _cache: dict[tuple[int, int, int], np.ndarray] = field(default_factory=dict)

    @staticmethod
    def cells_total() -> int:
        return MARKER_CELLS + 2 * QUIET_CELLS

    def get(self, marker_id: int, level: int, gain: float = 1.0) -> np.ndarray:
        g = int(round(gain * 100))
        key = (marker_id, level, g)
        tex = self._cache.get(key)
        if tex is None:
            top = CELL_PX_LEVELS[0]
            img = cv2.aruco.generateImageMarker(self.dictionary, marker_id, MARKER_CELLS * top)
            q = QUIET_CELLS * top
            img = cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)
            side = self.cells_total() * CELL_PX_LEVELS[level]
            if level:
                # Area averaging by an integer factor keeps pixel-centre geometry exact and
                # stands in for the lens' low-pass: no aliasing on small, distant markers.
                img = cv2.resize(img, (side, side), interpolation=cv2.INTER_AREA)
            lo, hi = self.black * g / 100.0, self.white * g / 100.0
            tex = np.clip(lo + img.astype(np.float32) * ((hi - lo) / 255.0), 0, 255).astype(
                np.uint8
            )
            self._cache[key] = tex
        return tex

    @staticmethod
    def level_for(side_px: float) -> int:
        """Coarsest level whose black square still has at least as many pixels as on screen."""
        for level in range(len(CELL_PX_LEVELS) - 1, -1, -1):
            if MARKER_CELLS * CELL_PX_LEVELS[level] >= side_px:
                return level
        return 0


def background_panorama(height: int, focal: float, rng: np.random.Generator) -> np.ndarray:
    """A gray wrap-around panorama 2*pi*focal wide: smooth blotches, soft edges, a floor band."""
    out_w, out_h = int(round(2 * np.pi * focal)), height
    # Built at half resolution and upscaled: the texture is smooth anyway and this is 4x cheaper.
    width, height = (out_w + 1) // 2, (out_h + 1) // 2
    blend = max(16, width // 8)
    raw_w = width + blend
    small = rng.normal(0.0, 1.0, (max(8, height // 16), max(16, raw_w // 16))).astype(np.float32)
    base = cv2.resize(
        cv2.GaussianBlur(small, (0, 0), 1.5), (raw_w, height), interpolation=cv2.INTER_CUBIC
    )
    fine = cv2.GaussianBlur(rng.standard_normal((height, raw_w), dtype=np.float32), (0, 0), 1.0)
    tex = 22.0 * base + 12.0 * fine
    # Cross-fade the overhang into the start so the panorama wraps around without a seam.
    w = np.linspace(0.0, 1.0, blend, dtype=np.float32)[None, :]
    tex[:, :blend] = tex[:, :blend] * w + tex[:, width:] * (1.0 - w)
    tex = tex[:, :width]
    rows = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    floor = np.where(rows > 0.62, -25.0, 0.0).astype(np.float32)  # darker floor below the horizon
    img = np.clip(125.0 + tex + floor, 0, 255).astype(np.uint8)
    return cv2.resize(img, (out_w, out_h), interpolation=cv2.INTER_LINEAR)


def skin_texture(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A dark, skin-toned BGR image with soft shading: a hand pressed over the lens."""
    shade = cv2.GaussianBlur(
        rng.normal(0.0, 1.0, (height // 8 + 1, width // 8 + 1)).astype(np.float32), (0, 0), 2.0
    )
    shade = cv2.resize(shade, (width, height), interpolation=cv2.INTER_CUBIC)[..., None]
    tone = np.array([38.0, 52.0, 82.0], np.float32)  # BGR: dim reddish-brown
    return np.clip(tone * (1.0 + 0.15 * shade), 0, 255).astype(np.uint8)
