"""What the uncertainty stage reads and gives: the parameter blocks, the frames and clocks it
reads (protocols), its settings and the per-row result."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from annotator.vision.detection import Detections


BLOCKS = ("markers", "rig", "intrinsics", "readout")


class VideoFrames(Protocol):
    """What this module reads of one camera's frames (the pipeline's CameraFrames)."""

    @property
    def camera(self) -> str: ...
    @property
    def t(self) -> np.ndarray: ...  # (N,) wall-clock seconds
    @property
    def detections(self) -> Sequence[Detections]: ...
    @property
    def frame_interval(self) -> float: ...


class VideoClock(Protocol):
    """What :func:`sync_time_sigma` reads of a camera's clock map (``annotator.core.sync.ClockMap``)."""

    def to_video(self, t_rssi: np.ndarray | float) -> np.ndarray: ...
    def sigma_at(self, pts: np.ndarray | float) -> np.ndarray: ...


@dataclass(frozen=True, slots=True)
class UncertaintySettings:
    huber_px: float = 1.5  # robust weights of corner residuals at the smoothed pose
    marker_gate_px: float = 3.0  # a marker whose RMS exceeds max(this, 4 x median) gets no weight
    param_window_s: float = 0.05  # Gaussian kernel sigma of the per-row parameter variance average
    scale_priors: bool = True  # check the priors against the residuals and rescale each block
    min_scale: float = 0.02
    max_scale: float = 4.0
    max_smear_px: float = 10.0  # frames smearing more are down-weighted, beyond 3x dropped
    unmodelled_m: float = 0.0015  # floor added in quadrature to every row's sigma
    # Propagate a refined record's joint covariance (cross-block terms, the rig's gauge, the map's
    # datum) instead of each block on its own; off, or without a joint record, blocks are independent.
    joint_covariance: bool = True
    default_exposure_frac: float = (
        0.5  # exposure as a share of the frame interval when not calibrated
    )


@dataclass(frozen=True, eq=False)
class RowUncertainty:
    """Per trajectory row (NaN where there is no pose): the parts of sigma_m and the smear."""

    params_var: np.ndarray  # (N, 4) per-axis position variance from each block (BLOCKS order), m^2
    blur_m: np.ndarray  # (N,)
    smear_px: np.ndarray  # (N,) median predicted corner smear over the cameras' frames
    scales: dict[str, float]  # the block scales applied (1 = the priors as stated)

    @property
    def params_m(self) -> np.ndarray:
        return np.sqrt(self.params_var.sum(1))
