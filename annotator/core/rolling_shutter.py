"""The rolling shutter, in one place: when each image row is seen, and what that does to a point.

A camera with a rolling shutter exposes its rows one after the other: row ``v`` of a frame stamped
``t`` is seen at ``t + readout_s * v / height`` (``CameraCalibration.readout_s``; 0 = global
shutter). The pose solve moves each corner's world point by the bundle's motion over that delay,
the self-calibration estimates ``readout_s`` from it, the uncertainty propagates its error, and
the renderer draws each band of rows from the pose at its own time: all through this module.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def row_delay(
    v: np.ndarray | float, height: int | np.ndarray, readout_s: float | np.ndarray
) -> np.ndarray:
    """Seconds after the frame stamp at which image row(s) ``v`` (pixels, fractional allowed)
    are seen; ``height`` and ``readout_s`` broadcast (per camera arrays work too)."""
    return np.asarray(readout_s) * np.asarray(v, dtype=float) / np.asarray(height, dtype=float)


def moved_points(
    world: np.ndarray,
    pixels: np.ndarray,
    height: int,
    readout_s: float,
    R_wb: np.ndarray,
    p_wb: np.ndarray,
    omega: np.ndarray,
    vel: np.ndarray,
) -> np.ndarray:
    """World points (..., 3) moved so that the bundle pose at the frame stamp sees each where the
    pose at its pixel row's time (``pixels[..., 1]``) saw it.

    Bundle at t + tau: R(tau) = exp(omega tau) R_wb, p(tau) = p_wb + vel tau (``omega`` the
    world-frame angular rate, ``vel`` the velocity). A point X seen at t + tau lands where
    X' = p + exp(-omega tau) (X - p - vel tau) lands at t.
    """
    tau = row_delay(pixels[..., 1].reshape(-1), height, readout_s)
    X = world.reshape(-1, 3)
    back = Rotation.from_rotvec(-tau[:, None] * np.asarray(omega)[None, :])
    moved = p_wb + back.apply(X - p_wb - tau[:, None] * np.asarray(vel)[None, :])
    return moved.reshape(world.shape)
