"""What an experiment is, once loaded: the camera calibrations, the rig, the marker map, the sync
settings and the priors (annotator.io.experiment reads them from experiment.yaml and its files).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.core.priors import Priors
from bgt_core.formats.markers import MarkerPose


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Pinhole intrinsics, a lens model with its coefficients, and the rolling-shutter readout.

    ``model`` is "radtan" (OpenCV's radial-tangential: k1 k2 p1 p2 [k3 ...]) or "fisheye"
    (OpenCV's equidistant fisheye: k1 k2 k3 k4). ``readout_s`` is the time from the first image
    row to the last (0 = global shutter): row v of a frame stamped t is seen at
    t + readout_s * v / height.
    """

    camera_matrix: np.ndarray  # 3x3
    dist_coeffs: np.ndarray  # (n,) in the order of `model`
    width: int
    height: int
    source: str = ""
    model: str = "radtan"
    readout_s: float = 0.0
    exposure_s: float | None = None  # optional: exposure time, for the motion-blur measure
    # Detected marker corners sit this far (px) outward (+) or inward (-) of the true corner along
    # the square's diagonal; estimated by the self-calibration (annotator.core.refine), 0 otherwise.
    corner_bias_px: float = 0.0


@dataclass(frozen=True, eq=False)
class RigCamera:
    """One camera of the bundle: its calibration and where it sits on the bundle."""

    name: str
    calibration: CameraCalibration
    R_bundle_camera: np.ndarray  # camera-frame vectors -> bundle frame
    t_bundle_camera: np.ndarray  # camera centre in the bundle frame, metres


# What the bundle carries besides its cameras, and may give an antenna position for in rig.yaml.
ANTENNAS = ("beacon", "receiver")


@dataclass(frozen=True, eq=False)
class Rig:
    """The bundle's cameras and the antenna positions of what it carries (bundle frame, metres).

    The bundle's origin is its beacon unless ``antennas`` says otherwise; an antenna not given
    sits at the origin.
    """

    cameras: dict[str, RigCamera]
    source: str = ""
    antennas: dict[str, np.ndarray] = field(default_factory=dict)

    def antenna(self, name: str) -> np.ndarray:
        """Position of ``name`` ("beacon" or "receiver") in the bundle frame, metres."""
        return np.asarray(self.antennas.get(name, np.zeros(3)), dtype=float)


@dataclass(frozen=True, eq=False)
class MarkerSetup:
    markers: dict[int, MarkerPose]
    dictionary: str  # e.g. "DICT_6X6_50"
    length: float  # printed outer black square, metres
    # 1-sigma of the printed size relative to ``length``: the self-calibration estimates one
    # scale for all markers with this prior (a printer's scaling is rarely exact); 0 = exact.
    length_sigma: float = 0.01


@dataclass(frozen=True)
class SyncSettings:
    """experiment.yaml's ``sync:`` section, checked once at load (see ``parse_sync``)."""

    mode: str = "manual"  # manual | auto (hands cover) | slate (clock slate, cover as fallback)
    video_start: dict[str, float] | None = None  # as written: wall time of each video's first frame
    beacon: str | None = None  # the bundle's beacon, 12 lower-case hex digits
    min_cover_s: float = 0.3  # auto: shortest and longest "hands over the bundle" event, s
    max_cover_s: float = 10.0
    max_start_error: float = 60.0  # auto: how far (s) a stated video start may be off
    # slate: the screen's refresh rate (Hz), its display delay and that delay's 1-sigma (s), and
    # how far into each end of a video (s) to look for the slate.
    slate_hz: float = 60.0
    slate_latency: float = 0.0
    slate_latency_sigma: float = 0.005
    slate_window: float = 15.0


@dataclass(frozen=True, eq=False)
class Experiment:
    path: Path
    markers: MarkerSetup
    rig: Rig
    videos: dict[str, Path]
    rssi: Path | None
    video_start: dict[str, float] | None  # wall time of each video's first frame (manual sync)
    sync: SyncSettings = field(default_factory=SyncSettings)
    priors: Priors = field(default_factory=Priors)  # the `refine:` section: survey/rig/lens sigmas
    # Receiver mode: the sensor on the bundle (12 lower-case hex digits) whose readings of every
    # beacon are labelled; None = beacon mode (readings of the bundle's beacon by fixed sensors).
    receiver: str | None = None

    @property
    def sync_mode(self) -> str:
        return self.sync.mode
