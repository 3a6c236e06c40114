"""refinement.json: what the self-calibration found (also report.json's ``refinement``
section), as typed records. ``capture.refinement_report`` builds it; the tracking passes add
``timing`` and ``jig``, `annotator run` the ``files`` it wrote."""

from __future__ import annotations

from typing import Any, TypedDict

REFINEMENT_VERSION = 1


class Observability(TypedDict):
    """Which of a camera's parameters the capture determined."""

    # block -> True (the capture determined it), False (its prior kept), None (not refined)
    determined: dict[str, bool | None]
    notes: list[str]  # "rolling-shutter readout not observable in this walk: ..."


class CameraRefinement(Observability):
    """What the self-calibration found for one camera, against what the files said."""

    rms_px_before: float
    rms_px_after: float
    rig_rotation_change_deg: list[float]
    rig_position_change_m: list[float]
    focal_change_rel: list[float]  # fx, fy
    principal_change_px: list[float]
    distortion_change: list[float]
    readout_s: float
    corner_bias_px: float
    readout_sigma_s: float | None
    clock_offset_ms: float
    clock_sigma_ms: float | None


class MovedMarker(TypedDict):
    id: int
    offset_m: list[float]
    survey_sigma_m: float
    note: str


class PrintedLength(TypedDict, total=False):
    """The markers' printed size: ``stated_m`` and ``estimated`` always, the rest when it was."""

    stated_m: float
    estimated: bool
    scale: float
    scale_sigma: float
    found_m: float
    determined: bool
    used_m: float
    note: str


class RefinementReport(TypedDict, total=False):
    """refinement.json. ``timing`` and ``jig`` are added by the tracking passes, ``files`` by
    `annotator run` (the refined files it wrote, relative to its output folder)."""

    version: int
    mode: str
    keyframes: int
    corners: int
    markers_seen: list[int]
    iterations: int
    seconds: float
    corner_sigma_px: float
    cameras: dict[str, CameraRefinement]
    markers_mapped: list[int]
    markers_moved: list[MovedMarker]
    printed_length: PrintedLength
    timing: dict[str, float]
    jig: dict[str, Any]
    files: dict[str, str]
