"""Loading an experiment: experiment.yaml, the rig, camera calibrations and the marker map (the
types they load into are in annotator.core.experiment).

Every path inside a YAML file is relative to that file; every problem is one ConfigError line.
"""

from __future__ import annotations

import logging
import re
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from annotator.core.experiment import (
    ANTENNAS,
    CameraCalibration,
    Experiment,
    MarkerSetup,
    Rig,
    RigCamera,
    SyncSettings,
)
from annotator.core.priors import parse_priors
from annotator.errors import ConfigError
from annotator.fields import known_keys as _known_keys
from annotator.fields import mac as _mac
from annotator.fields import mapping
from annotator.fields import number as _number
from bgt_core.formats.markers import read_marker_map

log = logging.getLogger(__name__)


# --- YAML plumbing --------------------------------------------------------------------------


def _yaml_loader() -> type:
    import yaml

    from bgt_core.safe_yaml import SafeLoader

    class _Loader(SafeLoader):
        """The bounded safe loader, also understanding OpenCV's !!opencv-matrix tag."""

    def _matrix(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict[Any, Any]:
        return dict(loader.construct_mapping(node, deep=True))

    _Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", _matrix)
    _Loader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", _matrix)
    return _Loader


# OpenCV writes "%YAML:1.0" (not valid YAML) or "%YAML 1.2" (PyYAML speaks 1.1): drop the directive.
_DIRECTIVE = re.compile(r"^%YAML[: ]\s*\d+\.\d+\s*$", re.MULTILINE)


def load_yaml(path: Path, what: str) -> Any:
    """Parse a YAML file (OpenCV FileStorage flavour included) with the bounded loader of
    bgt_core.safe_yaml (no aliases, limited size and depth); one-line ConfigError on failure."""
    from bgt_core.safe_yaml import YamlError, load_file

    try:
        return load_file(
            path, loader=_yaml_loader(), preprocess=lambda text: _DIRECTIVE.sub("", text, count=1)
        )
    except YamlError as e:
        raise ConfigError(f"{what}: {e}") from None


def _mapping(obj: Any, source: str, what: str) -> dict[str, Any]:
    return mapping(obj, f"{source}: {what}")


def _matrix(value: Any, source: str, key: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """A matrix written as !!opencv-matrix / ROS {rows, cols, data} / nested lists."""
    try:
        if isinstance(value, dict):
            data = np.asarray(value["data"], dtype=float)
            rows, cols = int(value.get("rows", 1)), int(value.get("cols", data.size))
            arr = data.reshape(rows, cols)
        else:
            arr = np.asarray(value, dtype=float)
    except (KeyError, TypeError, ValueError) as e:
        raise ConfigError(f"{source}: {key}: not a numeric matrix ({e})") from None
    if shape is not None and arr.size == int(np.prod(shape)):
        arr = arr.reshape(shape)
    if shape is not None and arr.shape != shape:
        raise ConfigError(f"{source}: {key}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{source}: {key}: contains non-finite numbers")
    return arr


# --- calibration ----------------------------------------------------------------------------

# `distortion_model` as written by OpenCV tools / ROS camera_info -> our lens model name.
LENS_MODELS = {
    "plumb_bob": "radtan",
    "rational_polynomial": "radtan",
    "radtan": "radtan",
    "fisheye": "fisheye",
    "equidistant": "fisheye",
}
# Optional calibration key: rolling-shutter readout, first row to last, seconds.
READOUT_KEY = "rolling_shutter_readout_s"
# Optional calibration key: exposure time, seconds (the motion-blur measure; default half a frame).
EXPOSURE_KEY = "exposure_s"
# Optional calibration key written by the refinement: the detector's corner bias, px.
CORNER_BIAS_KEY = "marker_corner_bias_px"


def _lens(d: dict[str, Any], source: str) -> tuple[str, np.ndarray]:
    """The lens model and its distortion coefficients, checked against what OpenCV takes."""
    dist = _matrix(d["distortion_coefficients"], source, "distortion_coefficients").ravel()
    named = d.get("distortion_model", "plumb_bob")
    if named not in LENS_MODELS:
        raise ConfigError(
            f"{source}: distortion_model {named!r} is not supported ({', '.join(LENS_MODELS)})"
        )
    model = LENS_MODELS[named]
    if model == "fisheye" and dist.size != 4:
        raise ConfigError(
            f"{source}: distortion_coefficients: the fisheye model takes 4 values (k1 k2 k3 k4), "
            f"not {dist.size}"
        )
    if model == "radtan" and dist.size not in (0, 4, 5, 8, 12, 14):
        raise ConfigError(
            f"{source}: distortion_coefficients: {dist.size} values; OpenCV takes 4, 5, 8, 12 or 14"
        )
    return model, (np.zeros(5) if dist.size == 0 else dist)


def _image_size(d: dict[str, Any], source: str) -> tuple[int, int]:
    try:
        width, height = int(d["image_width"]), int(d["image_height"])
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{source}: image_width / image_height must be integers") from None
    if not (0 < width <= 100_000 and 0 < height <= 100_000):
        raise ConfigError(f"{source}: image_width / image_height must be in 1..100000 pixels")
    return width, height


def _seconds_below_one(value: Any, source: str, key: str) -> float:
    """A time in [0, 1) s (readout, exposure)."""
    try:
        seconds = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: {key} must be a number (seconds)") from None
    if not 0.0 <= seconds < 1.0:
        raise ConfigError(f"{source}: {key} must be between 0 and 1 s, not {seconds}")
    return seconds


def parse_calibration(obj: Any, source: str) -> CameraCalibration:
    """OpenCV FileStorage calibration or ROS camera_info, already parsed from YAML."""
    d = _mapping(obj, source, "a camera calibration")
    for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
        if key not in d:
            raise ConfigError(
                f"{source}: missing '{key}' (need an OpenCV FileStorage or ROS camera_info calibration)"
            )
    K = _matrix(d["camera_matrix"], source, "camera_matrix", (3, 3))
    model, dist = _lens(d, source)
    readout = _number(d.get(READOUT_KEY, 0.0), f"{source}: {READOUT_KEY} (seconds)", -1e3, 1e3)
    if not 0.0 <= readout < 1.0:
        raise ConfigError(f"{source}: {READOUT_KEY} must be between 0 and 1 s, not {readout}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
        raise ConfigError(f"{source}: camera_matrix: need fx, fy > 0 and K[2][2] = 1")
    width, height = _image_size(d, source)
    exposure = d.get(EXPOSURE_KEY)
    if exposure is not None:
        exposure = _seconds_below_one(exposure, source, EXPOSURE_KEY)
    try:
        bias = float(d.get(CORNER_BIAS_KEY, 0.0))
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: {CORNER_BIAS_KEY} must be a number (pixels)") from None
    if not abs(bias) < 5:
        raise ConfigError(f"{source}: {CORNER_BIAS_KEY} must be within +-5 px, not {bias}")
    return CameraCalibration(
        K, dist, width, height, source, model, readout, exposure_s=exposure, corner_bias_px=bias
    )


def load_calibration(path: str | Path) -> CameraCalibration:
    path = Path(path)
    return parse_calibration(load_yaml(path, "camera calibration"), str(path))


# --- rig ------------------------------------------------------------------------------------


def _rotation(value: Any, source: str, key: str) -> np.ndarray:
    R = _matrix(value, source, key, (3, 3))
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ConfigError(f"{source}: {key}: not a rotation (need R^T R = I and det +1)")
    # Re-orthonormalise: a YAML file written with 6-digit numbers is a rotation only to ~1e-6.
    u, _, vt = np.linalg.svd(R)
    return u @ vt


# Keys of rig.yaml, and of each of its cameras.
RIG_KEYS = ("cameras", "antennas")
RIG_CAMERA_KEYS = ("calibration", "R_bundle_camera", "t_bundle_camera")


def parse_rig(obj: Any, path: Path) -> Rig:
    source = str(path)
    d = _mapping(obj, source, "the rig")
    _known_keys(d, RIG_KEYS, source)
    cams = d.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise ConfigError(f"{source}: expected a non-empty 'cameras:' mapping")
    out: dict[str, RigCamera] = {}
    for name, spec in cams.items():
        where = f"{source}: cameras.{name}"
        spec = _mapping(spec, where, "a camera")
        _known_keys(spec, RIG_CAMERA_KEYS, source, f"cameras.{name}")
        for key in RIG_CAMERA_KEYS:
            if key not in spec:
                raise ConfigError(f"{where}: missing '{key}'")
        cal_path = path.parent / str(spec["calibration"])
        if not cal_path.is_file():
            raise ConfigError(f"{where}.calibration: no such file {cal_path}")
        out[str(name)] = RigCamera(
            name=str(name),
            calibration=load_calibration(cal_path),
            R_bundle_camera=_rotation(spec["R_bundle_camera"], where, "R_bundle_camera"),
            t_bundle_camera=_matrix(spec["t_bundle_camera"], where, "t_bundle_camera", (3,)),
        )
    return Rig(out, source, _antennas(d.get("antennas"), source))


def _antennas(value: Any, source: str) -> dict[str, np.ndarray]:
    """rig.yaml's ``antennas:``: {beacon: [x, y, z], receiver: [x, y, z]} in the bundle frame,
    metres, each within 2 m of the origin."""
    if value is None:
        return {}
    d = _mapping(value, source, "antennas")
    _known_keys(d, ANTENNAS, source, "antennas")
    out = {}
    for name, v in d.items():
        xyz = _matrix(v, source, f"antennas.{name}", (3,))
        if not np.linalg.norm(xyz) <= 2.0:
            raise ConfigError(
                f"{source}: antennas.{name}: {np.linalg.norm(xyz):.3g} m from the bundle's "
                "origin; expected metres within 2 m"
            )
        out[str(name)] = xyz
    return out


def load_rig(path: str | Path) -> Rig:
    path = Path(path)
    return parse_rig(load_yaml(path, "rig"), path)


# --- experiment -----------------------------------------------------------------------------


# Keys of experiment.yaml's top level and of its `markers:` section.
EXPERIMENT_KEYS = ("markers", "rig", "videos", "rssi", "sync", "refine", "receiver")
MARKERS_KEYS = ("file", "dictionary", "length", "length_sigma")


def _markers(value: Any, base: Path, source: str) -> MarkerSetup:
    d = _mapping(value, source, "markers")
    _known_keys(d, MARKERS_KEYS, source, "markers")
    for key in ("file", "dictionary", "length"):
        if key not in d:
            raise ConfigError(f"{source}: markers: missing '{key}'")
    import cv2

    dictionary = str(d["dictionary"])
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise ConfigError(f"{source}: markers.dictionary: unknown ArUco dictionary {dictionary!r}")
    length = _number(d["length"], f"{source}: markers.length (metres)", -1e3, 1e3)
    if not length > 0:
        raise ConfigError(f"{source}: markers.length must be positive (metres)")
    length_sigma = _number(
        d.get("length_sigma", 0.01),
        f"{source}: markers.length_sigma",
        0.0,
        0.2,
        "a relative 1-sigma of the printed size in 0..0.2 (0.01 = 1 %)",
    )
    # MarkerMapError is a known error too; the CLI prints it as one line.
    return MarkerSetup(read_marker_map(base / str(d["file"])), dictionary, length, length_sigma)


# The `sync:` section: every key it may hold.
SYNC_KEYS = tuple(f.name for f in fields(SyncSettings))
# A video's start is Unix seconds between 1970 and 2100.
UNIX_S_MAX = 4_102_444_800.0


def parse_sync(obj: Any, source: str, cameras: list[str]) -> SyncSettings:
    """The `sync:` section, checked and normalised: numbers as floats, the beacon as a 12-hex MAC.
    Unknown keys, values that are not numbers, NaN, infinities and times outside 1970..2100 are one
    ConfigError line naming the field."""
    sync = dict(_mapping(obj, source, "sync"))
    _known_keys(sync, SYNC_KEYS, source, "sync")
    mode = sync.get("mode", "manual")
    if mode not in ("manual", "auto", "slate"):
        raise ConfigError(
            f"{source}: sync.mode must be 'manual', 'auto' or 'slate', not {mode!r:.40}"
        )
    sync["mode"] = mode
    video_start: dict[str, float] | None = None
    if sync.get("video_start") is not None:
        starts = _mapping(sync["video_start"], source, "sync.video_start")
        video_start = {
            str(k): _number(
                v,
                f"{source}: sync.video_start.{str(k)[:40]}",
                0.0,
                UNIX_S_MAX,
                "Unix seconds in 1970..2100",
            )
            for k, v in starts.items()
        }
        missing = sorted(set(cameras) - set(video_start))
        if missing:
            raise ConfigError(f"{source}: sync.video_start: no start time for {', '.join(missing)}")
        sync["video_start"] = video_start
    elif mode == "manual":
        raise ConfigError(f"{source}: sync.mode is manual but sync.video_start is missing")
    for key in ("min_cover_s", "max_cover_s", "max_start_error"):
        if key in sync:
            sync[key] = _number(sync[key], f"{source}: sync.{key}", 1e-3, 86_400.0)
    for key, low, high in (
        ("slate_hz", 10.0, 500.0),
        ("slate_latency", 0.0, 1.0),
        ("slate_latency_sigma", 0.0, 1.0),
        ("slate_window", 0.5, 3600.0),
    ):
        if key in sync:
            sync[key] = _number(sync[key], f"{source}: sync.{key}", low, high)
    lo = sync.get("min_cover_s", SyncSettings.min_cover_s)
    hi = sync.get("max_cover_s", SyncSettings.max_cover_s)
    if not lo < hi:
        raise ConfigError(
            f"{source}: sync.min_cover_s ({lo:g}) must be less than sync.max_cover_s ({hi:g})"
        )
    if sync.get("beacon") is not None:
        sync["beacon"] = _mac(sync["beacon"], f"{source}: sync.beacon")
    return SyncSettings(**sync)


def parse_experiment(obj: Any, path: Path) -> Experiment:
    source = str(path)
    d = _mapping(obj, source, "the experiment")
    _known_keys(d, EXPERIMENT_KEYS, source)
    base = path.parent
    for key in ("markers", "rig", "videos"):
        if key not in d:
            raise ConfigError(f"{source}: missing '{key}'")
    markers = _markers(d["markers"], base, source)
    rig_path = base / str(d["rig"])
    if not rig_path.is_file():
        raise ConfigError(f"{source}: rig: no such file {rig_path}")
    rig = load_rig(rig_path)
    videos_raw = _mapping(d["videos"], source, "videos")
    unknown = sorted(set(map(str, videos_raw)) - set(rig.cameras))
    if unknown:
        raise ConfigError(
            f"{source}: videos: camera(s) {', '.join(unknown)} not in the rig ({rig_path.name})"
        )
    if not videos_raw:
        raise ConfigError(f"{source}: videos: no video given")
    videos = {str(k): base / str(v) for k, v in videos_raw.items()}
    for name, vp in videos.items():
        if not vp.is_file():
            raise ConfigError(f"{source}: videos.{name}: no such file {vp}")
    rssi = base / str(d["rssi"]) if d.get("rssi") is not None else None

    sync = parse_sync(d.get("sync", {"mode": "manual"}), source, list(videos))
    priors = parse_priors(d.get("refine"), source)
    receiver = None
    if d.get("receiver") is not None:
        receiver = _mac(d["receiver"], f"{source}: receiver")
        if sync.beacon is not None:
            raise ConfigError(
                f"{source}: receiver and sync.beacon exclude each other (receiver mode labels "
                "the receiver's readings of every beacon; remove one)"
            )
    return Experiment(
        path, markers, rig, videos, rssi, sync.video_start, sync, priors, receiver=receiver
    )


def load_experiment(path: str | Path) -> Experiment:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"no such experiment file: {path}")
    exp = parse_experiment(load_yaml(path, "experiment"), path)
    log.debug(
        "experiment %s: cameras %s, %d markers", path, list(exp.videos), len(exp.markers.markers)
    )
    return exp
