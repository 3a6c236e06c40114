"""What is known about the room, the rig and the lenses, and how well: priors and covariances.

`Priors` is what the user states (experiment.yaml's ``refine:`` section, or the defaults, which
suit a room surveyed with a tape measure and a rig measured by hand). `ParameterCovariance` is
what is known after refinement (or, without refinement, what the priors say), in the form the
uncertainty propagation consumes. Pure data: no I/O beyond validating an already parsed mapping.

Perturbation conventions (shared by refinement and propagation):
- marker: R_world_marker = exp([d_rot]x) @ R0 (world-frame rotation vector, rad), centre + d_pos (m);
  its 6x6 covariance orders (d_rot, d_pos);
- rig camera: R_bundle_camera = exp([d_rot]x) @ R0 (bundle frame), t_bundle_camera + d_t; 6x6 over
  (d_rot, d_t);
- intrinsics: 4x4 over (fx, fy, cx, cy) in pixels; distortion (over the coefficients) and readout
  (1x1, s^2) are optional: filled by the refinement, empty when only the priors are known.

After refinement the blocks are correlated: the same corners fit the map, the rig and the lenses,
and the surveyed markers together fix where the map sits in the room (an error common to every
marker). The record then also carries the refinement's joint covariance and the rows of each
block in it. Priors alone are independent: no joint covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.errors import ConfigError
from annotator.fields import number
from bgt_core.keys import unknown_key

REFINE_MODES = ("none", "map", "all")


@dataclass(frozen=True, slots=True)
class MarkerPrior:
    """Survey uncertainty of one marker; ``known=False`` means "not surveyed: map it from video"."""

    sigma_m: float
    sigma_deg: float
    known: bool = True


JIG_SIGMA_M, JIG_SIGMA_DEG = 0.001, 0.1  # Jig's defaults: a levelled plate, squared to a wall


@dataclass(frozen=True, eq=False, slots=True)
class Jig:
    """A rest of the bundle at a known pose: the rig's gauge (docs/annotator.md, "The rig jig").

    From ``start`` to ``end`` (the trajectory's times, s) the bundle sat still on a jig whose pose
    in the room is known: ``position`` (the bundle's origin, m) and ``rotation`` (R_world_bundle),
    each to ``sigma_m`` / ``sigma_deg`` per axis (1-sigma)."""

    start: float
    end: float
    position: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3)
    sigma_m: float = JIG_SIGMA_M
    sigma_deg: float = JIG_SIGMA_DEG


@dataclass(frozen=True, slots=True)
class Priors:
    """1-sigma uncertainties of the inputs the user measured (defaults: a tape-measured room)."""

    mode: str = "all"  # none | map | all: what refinement may change (CLI --refine overrides)
    survey_sigma_m: float = 0.015  # marker centre, per axis
    survey_sigma_deg: float = 1.0  # marker orientation, per axis
    markers: dict[int, MarkerPrior] = field(default_factory=dict)  # per-marker overrides
    rig_sigma_m: float = 0.003  # camera position in the bundle, per axis
    rig_sigma_deg: float = 1.0  # camera orientation in the bundle, per axis
    focal_sigma_rel: float = 0.005  # fx, fy relative
    principal_sigma_px: float = 2.0  # cx, cy
    distortion_sigma: float = 0.05  # each distortion coefficient
    readout_sigma_s: float = 0.02  # rolling-shutter readout time (prior mean: the calibration's)
    # fx / fy: the pixel aspect is the sensor's, and a ChArUco calibration gives it to a few 1e-4.
    # Looser (0.001), the refinement read the foreshortening of slanted wall markers, which both
    # corner detectors narrow in x, as fy 0.25 % short (docs/annotator.md, "The pixel aspect").
    aspect_sigma_rel: float = 0.0002
    jig: Jig | None = None  # a rest at a known pose, which fixes the rig's gauge

    def marker(self, marker_id: int) -> MarkerPrior:
        return self.markers.get(marker_id, MarkerPrior(self.survey_sigma_m, self.survey_sigma_deg))


def _positive(d: dict[str, Any], key: str, default: float, where: str) -> float:
    return number(
        d.get(key, default), f"{where}.{key}", math.ulp(0.0), math.inf, "a positive finite number"
    )


def parse_priors(obj: Any, source: str) -> Priors:
    """The ``refine:`` section of experiment.yaml (already parsed); absent -> defaults."""
    if obj is None:
        return Priors()
    where = f"{source}: refine"
    if not isinstance(obj, dict):
        raise ConfigError(f"{where}: must be a mapping")
    d = Priors()
    known_keys = {
        "mode",
        "survey_sigma_m",
        "survey_sigma_deg",
        "markers",
        "rig_sigma_m",
        "rig_sigma_deg",
        "focal_sigma_rel",
        "principal_sigma_px",
        "distortion_sigma",
        "readout_sigma_s",
        "aspect_sigma_rel",
        "jig",
    }
    message = unknown_key(obj, sorted(known_keys), source, "refine")
    if message is not None:
        raise ConfigError(message)
    mode = str(obj.get("mode", d.mode))
    if mode not in REFINE_MODES:
        raise ConfigError(f"{where}.mode: must be one of {', '.join(REFINE_MODES)}, not {mode!r}")
    survey_m = _positive(obj, "survey_sigma_m", d.survey_sigma_m, where)
    survey_deg = _positive(obj, "survey_sigma_deg", d.survey_sigma_deg, where)
    markers: dict[int, MarkerPrior] = {}
    raw = obj.get("markers") or {}
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{where}.markers: must map marker ids to {{sigma_m, sigma_deg}} or 'unknown'"
        )
    for key, spec in raw.items():
        try:
            mid = int(key)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}.markers: {key!r} is not a marker id") from None
        if spec == "unknown":
            markers[mid] = MarkerPrior(math.inf, math.inf, known=False)
            continue
        if not isinstance(spec, dict) or set(map(str, spec)) - {"sigma_m", "sigma_deg"}:
            raise ConfigError(
                f"{where}.markers.{mid}: expected {{sigma_m: M, sigma_deg: D}} or 'unknown'"
            )
        markers[mid] = MarkerPrior(
            _positive(spec, "sigma_m", survey_m, f"{where}.markers.{mid}"),
            _positive(spec, "sigma_deg", survey_deg, f"{where}.markers.{mid}"),
        )
    return Priors(
        mode=mode,
        survey_sigma_m=survey_m,
        survey_sigma_deg=survey_deg,
        markers=markers,
        rig_sigma_m=_positive(obj, "rig_sigma_m", d.rig_sigma_m, where),
        rig_sigma_deg=_positive(obj, "rig_sigma_deg", d.rig_sigma_deg, where),
        focal_sigma_rel=_positive(obj, "focal_sigma_rel", d.focal_sigma_rel, where),
        principal_sigma_px=_positive(obj, "principal_sigma_px", d.principal_sigma_px, where),
        distortion_sigma=_positive(obj, "distortion_sigma", d.distortion_sigma, where),
        readout_sigma_s=_positive(obj, "readout_sigma_s", d.readout_sigma_s, where),
        aspect_sigma_rel=_positive(obj, "aspect_sigma_rel", d.aspect_sigma_rel, where),
        jig=_jig(obj.get("jig"), source),
    )


def _vector(value: Any, where: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, float)
    except (TypeError, ValueError, OverflowError):
        a = np.zeros(0)
    if a.shape != shape or not np.isfinite(a).all():
        want = {(): "a number", (3,): "3 numbers"}.get(shape, "3 rows of 3 numbers")
        raise ConfigError(f"{where}: must be {want}, not {value!r}")
    return a


def _jig(obj: Any, source: str) -> Jig | None:
    """``refine: jig:`` -> Jig: from, to (s), position [x, y, z] (m), R_world_bundle (3x3),
    optional sigma_m and sigma_deg."""
    where = f"{source}: refine.jig"
    if obj is None:
        return None
    if not isinstance(obj, dict):
        raise ConfigError(f"{where}: must be a mapping with from, to, position, R_world_bundle")
    keys = ("from", "to", "position", "R_world_bundle", "sigma_m", "sigma_deg")
    message = unknown_key(obj, keys, source, "refine.jig")
    if message is not None:
        raise ConfigError(message)
    missing = sorted({"from", "to", "position", "R_world_bundle"} - set(map(str, obj)))
    if missing:
        raise ConfigError(f"{where}: missing {', '.join(missing)} (keys: {', '.join(keys)})")
    start, end = (float(_vector(obj[k], f"{where}.{k}", ())) for k in ("from", "to"))
    if not end > start:
        raise ConfigError(f"{where}: 'to' ({end}) must come after 'from' ({start})")
    R = _vector(obj["R_world_bundle"], f"{where}.R_world_bundle", (3, 3))
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
        raise ConfigError(f"{where}.R_world_bundle: not a rotation (need R^T R = I and det +1)")
    u, _, vt = np.linalg.svd(R)
    return Jig(
        start,
        end,
        _vector(obj["position"], f"{where}.position", (3,)),
        u @ vt,
        _positive(obj, "sigma_m", JIG_SIGMA_M, where),
        _positive(obj, "sigma_deg", JIG_SIGMA_DEG, where),
    )


# ParameterCovariance.joint_index's key of the markers' printed size (relative, one for all).
PRINTED_SCALE: tuple[str, str] = ("scale", "printed")


@dataclass(frozen=True, eq=False)
class ParameterCovariance:
    """Uncertainty of the static parameters the tracker uses (conventions in the module doc)."""

    markers: dict[int, np.ndarray]  # id -> (6, 6)
    rig: dict[str, np.ndarray]  # camera -> (6, 6)
    intrinsics: dict[str, np.ndarray]  # camera -> (4, 4) over fx, fy, cx, cy
    # After refinement (empty without): camera -> (n, n) over the lens' distortion coefficients in
    # the calibration's order, and camera -> (1, 1) over the rolling-shutter readout (s^2).
    distortion: dict[str, np.ndarray] = field(default_factory=dict)
    readout: dict[str, np.ndarray] = field(default_factory=dict)
    # After refinement: the joint covariance of the refined parameters as the trajectory sees them
    # (refine.solver._solve: the rig's gauge and the markers' floors included), and the rows of each block
    # in it keyed (kind, marker id or camera) with kind one of markers, rig, intrinsics,
    # distortion, readout, bias (the detector's corner bias, px), and PRINTED_SCALE: the markers'
    # printed size relative to the length used, one for all. A block without an entry is
    # independent of the rest.
    joint: np.ndarray | None = None
    joint_index: dict[tuple[str, int | str], np.ndarray] = field(default_factory=dict)

    @classmethod
    def from_priors(
        cls, priors: Priors, marker_ids: list[int], cameras: dict[str, np.ndarray]
    ) -> ParameterCovariance:
        """Block-diagonal covariances straight from the priors (what is known without refinement).

        ``cameras`` maps each camera name to its 3x3 camera matrix (the focal prior is relative).
        Markers whose prior is unknown get no entry: they cannot be used without refinement.
        """

        def block(sig_deg: float, sig_m: float) -> np.ndarray:
            r = math.radians(sig_deg)
            return np.diag([r * r] * 3 + [sig_m * sig_m] * 3)

        markers = {}
        for mid in marker_ids:
            p = priors.marker(mid)
            if p.known:
                markers[mid] = block(p.sigma_deg, p.sigma_m)
        rig = {name: block(priors.rig_sigma_deg, priors.rig_sigma_m) for name in cameras}
        intr = {}
        for name, K in cameras.items():
            f = priors.focal_sigma_rel
            intr[name] = np.diag(
                [
                    (f * K[0, 0]) ** 2,
                    (f * K[1, 1]) ** 2,
                    priors.principal_sigma_px**2,
                    priors.principal_sigma_px**2,
                ]
            )
        return cls(markers, rig, intr)
