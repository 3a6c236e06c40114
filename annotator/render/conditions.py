"""Named conditions for `annotator simulate` and the benches: the errors of the files handed to
the annotator (``--errors``), how the bundle is carried along which path (``--path``, ``--motion``,
the profiles are ``trajectory.MOTION_PROFILES``) and what the camera adds to the picture
(``--imaging``, an :class:`annotator.render.effects.Imaging`). ConfigError names a bad value."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from annotator.errors import ConfigError
from annotator.render.effects import Imaging
from annotator.render.trajectory import LoopTrajectory, PolylineTrajectory

# `--imaging real`: what a phone-grade or action camera in an office gives (issue 29's captures):
# a lens ~1.5 px out of focus, JPEG-grade compression, 40 % vignetting, light uneven by +-20 %
# across the picture and drifting +-10 %, auto-exposure steps of +-8 %. Use with --noise 5.
IMAGING_PRESETS: dict[str, Imaging] = {
    "clean": Imaging(),
    "real": Imaging(
        defocus_px=1.5,
        jpeg_quality=60,
        vignetting=0.4,
        uneven_light=0.2,
        light_change=0.1,
        exposure_steps=0.08,
    ),
}
# The sensor noise that goes with each preset (gray levels), unless given.
IMAGING_NOISE = {"clean": 2.0, "real": 5.0}


def resolve_imaging(preset: str, **given: float | int | None) -> Imaging:
    """The preset's imaging with every value the user gave (not None) on top; ValueError names
    a bad preset or value."""
    if preset not in IMAGING_PRESETS:
        raise ValueError(f"imaging preset {preset!r}: expected one of {', '.join(IMAGING_PRESETS)}")
    known = {f.name for f in fields(Imaging)}
    unknown = set(given) - known
    if unknown:
        raise ValueError(f"imaging: unknown setting {sorted(unknown)[0]!r}")
    overrides: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
    return replace(IMAGING_PRESETS[preset], **overrides)


# `--errors field`: the errors of a careful real capture (issue 10's table): marker survey
# 1.5 cm / 1 deg, rig 3 mm / 1 deg, focal 0.4 %, principal point 1 px, a k1 = -0.28 lens, 15 ms
# rolling-shutter readout (written as 0, as users rarely know it), 8 ms exposure and lamp flicker.
ERROR_PRESETS: dict[str, dict[str, float | str]] = {
    "none": {},
    "field": {
        "survey_m": 0.015,
        "survey_deg": 1.0,
        "rig_m": 0.003,
        "rig_deg": 1.0,
        "focal_rel": 0.004,
        "principal_px": 1.0,
        "distortion": 0.0,
        "lens": "wide",
        "readout": 0.015,
        "exposure": 0.008,
        "flicker": 0.1,
    },
}


def resolve_errors(preset: str, **given: float | str | None) -> dict[str, float | str]:
    """The preset's values with every option the user gave (not None) on top; unset -> 0/defaults."""
    if preset not in ERROR_PRESETS:
        raise ConfigError(f"--errors {preset!r}: expected one of {', '.join(ERROR_PRESETS)}")
    defaults: dict[str, float | str] = {
        "survey_m": 0.0,
        "survey_deg": 0.0,
        "rig_m": 0.0,
        "rig_deg": 0.0,
        "focal_rel": 0.0,
        "principal_px": 0.0,
        "distortion": 0.0,
        "lens": "mild",
        "readout": 0.0,
        "exposure": 1 / 120,
        "flicker": 0.0,
    }
    out = {**defaults, **ERROR_PRESETS[preset]}
    out.update({k: v for k, v in given.items() if v is not None})
    return out


def path_trajectory(
    path: str, t0: float, speed: float, dwell: float, turn: bool, motion: str = "walk"
) -> LoopTrajectory | PolylineTrajectory:
    """--path value -> the trajectory to render: `loop`, a preset polyline or a waypoints YAML,
    carried as --motion says (walk, cart or hand)."""
    from annotator.io.waypoints import load_waypoints
    from annotator.render.trajectory import MOTION_PROFILES, PRESET_PATHS

    if motion not in MOTION_PROFILES:
        raise ConfigError(f"--motion {motion!r}: expected one of {', '.join(MOTION_PROFILES)}")
    carried: dict[str, Any] = dict(MOTION_PROFILES[motion])
    if path == "loop":
        return LoopTrajectory(t0=t0, speed=speed, **carried)
    if path in PRESET_PATHS:
        waypoints = PRESET_PATHS[path]
    elif path.endswith((".yaml", ".yml")):
        waypoints = tuple((float(x), float(y)) for x, y in load_waypoints(Path(path)))
    else:
        raise ConfigError(
            f"--path {path!r}: expected loop, {', '.join(PRESET_PATHS)} or a FILE.yaml with "
            "'waypoints: [[x, y], ...]'"
        )
    return PolylineTrajectory(waypoints, t0=t0, speed=speed, dwell=dwell, turn=turn, **carried)
