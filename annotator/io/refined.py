"""The self-calibration's files: the refined marker map (marker_positions.dat, and markers.yaml
with a sigma per marker), rig.yaml and one OpenCV calibration per camera (annotator.core.refine
computes them)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import yaml

from annotator.core.experiment import CameraCalibration
from annotator.core.refine import Refinement
from annotator.io.experiment import CORNER_BIAS_KEY, EXPOSURE_KEY, READOUT_KEY
from bgt_core.formats.markers import format_dat


def _write_calibration(path: Path, cal: CameraCalibration) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(cal.width))
        fs.write("image_height", int(cal.height))
        fs.write("camera_matrix", np.asarray(cal.camera_matrix, float))
        fs.write("distortion_coefficients", np.asarray(cal.dist_coeffs, float).reshape(1, -1))
        if cal.model != "radtan":
            fs.write("distortion_model", cal.model)
        fs.write(READOUT_KEY, float(cal.readout_s))
        if cal.corner_bias_px:
            fs.write(CORNER_BIAS_KEY, float(cal.corner_bias_px))
        if cal.exposure_s is not None:  # the camera's setting: the next capture's input keeps it
            fs.write(EXPOSURE_KEY, float(cal.exposure_s))
    finally:
        fs.release()


def write_refined(folder: str | Path, refinement: Refinement) -> dict[str, str]:
    """The refined map (marker_positions.dat and markers.yaml with a sigma per marker), rig.yaml
    and one calibration per camera into ``folder``; returns {what: file name}."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    exp = refinement.experiment
    markers = exp.markers.markers
    (out / "marker_positions.dat").write_text(format_dat(markers), encoding="utf-8")
    cov = refinement.covariance.markers
    moved = {m["id"] for m in refinement.report["markers_moved"]}
    rows = []
    for mid in sorted(markers):
        m = markers[mid]
        c = cov.get(mid)
        rows.append(
            {
                "id": int(mid),
                "position": [round(float(v), 5) for v in m.position],
                "rotation_xyz": [round(float(v), 6) for v in m.euler_xyz],
                "sigma_m": None
                if c is None
                else round(math.sqrt(float(np.trace(c[3:, 3:])) / 3), 5),
                "sigma_deg": None
                if c is None
                else round(math.degrees(math.sqrt(float(np.trace(c[:3, :3])) / 3)), 4),
                "source": "video"
                if mid in refinement.mapped
                else ("video, moved since the survey?" if mid in moved else "survey + video"),
            }
        )
    header = (
        "# Marker map refined from the capture (annotator.core.refine). sigma_*: 1-sigma per axis.\n"
        f"# dictionary {exp.markers.dictionary}, marker length {exp.markers.length} m\n"
    )
    (out / "markers.yaml").write_text(
        header + yaml.safe_dump({"markers": rows}, sort_keys=False), encoding="utf-8"
    )
    lines = ["# Rig refined from the capture (annotator.core.refine).", "cameras:"]
    for name, cam in exp.rig.cameras.items():
        _write_calibration(out / f"{name}.yaml", cam.calibration)
        rows_r = ", ".join(
            "[" + ", ".join(repr(float(v)) for v in row) + "]" for row in cam.R_bundle_camera
        )
        lines += [
            f"  {name}:",
            f"    calibration: {name}.yaml",
            f"    R_bundle_camera: [{rows_r}]",
            "    t_bundle_camera: [" + ", ".join(repr(float(v)) for v in cam.t_bundle_camera) + "]",
        ]
    (out / "rig.yaml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    files = {
        "marker_positions": "marker_positions.dat",
        "markers": "markers.yaml",
        "rig": "rig.yaml",
    }
    files.update({f"calibration_{n}": f"{n}.yaml" for n in exp.rig.cameras})
    return files
