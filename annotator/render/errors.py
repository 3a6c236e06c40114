"""Real-world errors in the files a render hands to the annotator: a marker survey, a rig and
calibrations that are a little off, as a careful real capture's are. The video is always
rendered with the exact values; only the written files carry the errors.

Conventions match `annotator.core.priors`: a marker's written rotation is exp([d]x) @ R_true with d a
world-frame rotation vector, a rig camera's exp([d]x) @ R_bundle_camera with d in the bundle
frame; positions get an additive offset. Each kind of error draws from its own random stream
(seeded from `seed` and the kind), as unit normals scaled by the sigma: a given seed moves the
same marker the same way whatever the other magnitudes, and a sigma of 0 leaves the value exact.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.render.camera import CameraModel
from bgt_core.formats.markers import MarkerPose

# Stream numbers of the kinds of error (part of the seed: do not renumber).
_SURVEY, _RIG, _INTRINSICS, _SKIPPED, _JIG = 1, 2, 3, 5, 6


@dataclass(frozen=True)
class FileErrors:
    """1-sigma errors of the written marker map, rig and calibrations (0 = exact)."""

    survey_m: float = 0.0  # marker centre, per axis
    survey_deg: float = 0.0  # marker orientation, per axis
    rig_m: float = 0.0  # camera position in the bundle, per axis
    rig_deg: float = 0.0  # camera orientation in the bundle, per axis
    focal_rel: float = 0.0  # one relative error applied to both fx and fy
    principal_px: float = 0.0  # cx and cy, each
    distortion: float = 0.0  # added to each radial coefficient (k1, k2) of the lens
    write_readout: bool = (
        False  # write the true rolling-shutter readout (else 0, as users rarely know it)
    )
    surveyed: int | None = (
        None  # only this many markers (a seeded random choice) in the written map
    )
    seed: int = 0

    def _magnitudes(self) -> dict[str, float]:
        return {
            k: v for k, v in asdict(self).items() if k not in ("write_readout", "seed", "surveyed")
        }

    def __post_init__(self) -> None:
        for key, value in self._magnitudes().items():
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{key} must be a finite number >= 0, not {value!r}")
        if self.surveyed is not None and self.surveyed < 1:
            raise ValueError(f"surveyed must be at least 1, not {self.surveyed}")

    @property
    def perturbs(self) -> bool:
        """Whether any written value is off (a marker subset alone is not)."""
        return any(v > 0 for v in self._magnitudes().values())


def _stream(seed: int, kind: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, kind]))


def perturb_markers(
    markers: dict[int, MarkerPose], sigma_m: float, sigma_deg: float, seed: int
) -> dict[int, MarkerPose]:
    """The marker map a surveyor with these per-axis 1-sigma errors would have written."""
    rng = _stream(seed, _SURVEY)
    out = {}
    for mid in sorted(markers):
        m = markers[mid]
        d_pos = sigma_m * rng.standard_normal(3)
        d_rot = np.radians(sigma_deg) * rng.standard_normal(3)
        if sigma_m == 0 and sigma_deg == 0:
            out[mid] = m
            continue
        rot = Rotation.from_rotvec(d_rot) * Rotation.from_euler("xyz", m.euler_xyz)
        out[mid] = MarkerPose.from_values(mid, np.asarray(m.position) + d_pos, rot.as_euler("xyz"))
    return out


def surveyed_subset(
    markers: dict[int, MarkerPose], count: int | None, seed: int
) -> dict[int, MarkerPose]:
    """The markers a surveyor who measured only `count` of them (a seeded random choice) wrote down."""
    if count is None or count >= len(markers):
        return markers
    ids = sorted(markers)
    keep = sorted(int(i) for i in _stream(seed, _SKIPPED).choice(ids, size=count, replace=False))
    return {i: markers[i] for i in keep}


def perturb_rig(
    extrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
    sigma_m: float,
    sigma_deg: float,
    seed: int,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(R_bundle_camera, t_bundle_camera) per camera as a hand measurement would have them."""
    rng = _stream(seed, _RIG)
    out = {}
    for name in sorted(extrinsics):
        r, t = extrinsics[name]
        d_t = sigma_m * rng.standard_normal(3)
        d_rot = np.radians(sigma_deg) * rng.standard_normal(3)
        if sigma_m == 0 and sigma_deg == 0:
            out[name] = (r, t)
            continue
        out[name] = (
            (Rotation.from_rotvec(d_rot) * Rotation.from_matrix(r)).as_matrix(),
            np.asarray(t, float) + d_t,
        )
    return {name: out[name] for name in extrinsics}


def perturb_cameras(
    cameras: dict[str, CameraModel],
    focal_rel: float,
    principal_px: float,
    distortion: float,
    seed: int,
) -> dict[str, CameraModel]:
    """Calibrations as a calibration with these 1-sigma errors would have written them."""
    rng = _stream(seed, _INTRINSICS)
    out = {}
    for name in sorted(cameras):
        cam = cameras[name]
        e_f = focal_rel * rng.standard_normal()
        e_c = principal_px * rng.standard_normal(2)
        e_k = distortion * rng.standard_normal(2)
        dist = np.array(cam.dist, float)
        dist[:2] += e_k
        out[name] = replace(
            cam,
            fx=cam.fx * (1 + e_f),
            fy=cam.fy * (1 + e_f),
            cx=cam.cx + e_c[0],
            cy=cam.cy + e_c[1],
            dist=tuple(float(v) for v in dist),
        )
    return {name: out[name] for name in cameras}


def _marker_record(m: MarkerPose) -> dict[str, list[float]]:
    return {
        "position": [float(v) for v in m.position],
        "rotation_xyz": [float(v) for v in m.euler_xyz],
    }


def _camera_record(
    cam: CameraModel, r: np.ndarray, t: np.ndarray, readout: float
) -> dict[str, object]:
    return {
        "model": cam.model,
        "fx": float(cam.fx),
        "fy": float(cam.fy),
        "cx": float(cam.cx),
        "cy": float(cam.cy),
        "dist": [float(v) for v in cam.dist],
        "readout_s": float(readout),
        "R_bundle_camera": [[float(v) for v in row] for row in np.asarray(r)],
        "t_bundle_camera": [float(v) for v in np.asarray(t)],
    }


def perturbation_record(
    settings: dict[str, object],
    true_markers: dict[int, MarkerPose],
    written_markers: dict[int, MarkerPose],
    true_cams: dict[str, CameraModel],
    written_cams: dict[str, CameraModel],
    true_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    written_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    readout: float,
    written_readout: float,
) -> dict[str, object]:
    """What perturbation.yaml holds: the settings, and true vs written values with their
    differences (written - true; rotations as the rotation vector taking true to written, deg)."""
    markers = []
    for mid in sorted(true_markers):
        a, b = true_markers[mid], written_markers.get(mid)
        if b is None:  # not surveyed: absent from the written map
            markers.append({"id": int(mid), "true": _marker_record(a), "written": None})
            continue
        d_rot = (
            Rotation.from_euler("xyz", b.euler_xyz) * Rotation.from_euler("xyz", a.euler_xyz).inv()
        )
        markers.append(
            {
                "id": int(mid),
                "true": _marker_record(a),
                "written": _marker_record(b),
                "offset_m": [float(v) for v in np.subtract(b.position, a.position)],
                "rotation_offset_deg": [float(v) for v in np.degrees(d_rot.as_rotvec())],
            }
        )
    cameras = {}
    for name in true_cams:
        tc, wc = true_cams[name], written_cams[name]
        (r0, t0), (r1, t1) = true_rig[name], written_rig[name]
        d_rot = Rotation.from_matrix(r1) * Rotation.from_matrix(r0).inv()
        cameras[name] = {
            "true": _camera_record(tc, r0, t0, readout),
            "written": _camera_record(wc, r1, t1, written_readout),
            "rig_offset_m": [float(v) for v in np.subtract(t1, t0)],
            "rig_rotation_offset_deg": [float(v) for v in np.degrees(d_rot.as_rotvec())],
            "focal_error_rel": float(wc.fx / tc.fx - 1.0),
            "principal_offset_px": [float(wc.cx - tc.cx), float(wc.cy - tc.cy)],
            "dist_offset": [float(b - a) for a, b in zip(tc.dist, wc.dist, strict=True)],
        }
    return {"settings": settings, "markers": markers, "cameras": cameras}


def jig_entry(
    position: np.ndarray,
    rotation: Rotation,
    start: float,
    end: float,
    sigma_m: float,
    sigma_deg: float,
    seed: int,
    perturb: bool,
) -> tuple[dict[str, object], dict[str, list[float]]]:
    """experiment.yaml's ``refine: jig:`` for a rest at the true pose (``position``, ``rotation``:
    R_world_bundle), written off by the jig's stated sigmas when ``perturb``; and the error
    written (offset_m, rotation_offset_deg: world-frame rotation vector) for perturbation.yaml."""
    rng = _stream(seed, _JIG)
    d_pos = sigma_m * rng.standard_normal(3) if perturb else np.zeros(3)
    d_rot = np.radians(sigma_deg) * rng.standard_normal(3) if perturb else np.zeros(3)
    R = (Rotation.from_rotvec(d_rot) * rotation).as_matrix()
    entry = {
        "from": float(start),
        "to": float(end),
        "position": [round(float(v), 6) for v in np.asarray(position) + d_pos],
        "R_world_bundle": [[round(float(v), 9) for v in row] for row in R],
        "sigma_m": float(sigma_m),
        "sigma_deg": float(sigma_deg),
    }
    error = {
        "offset_m": [float(v) for v in d_pos],
        "rotation_offset_deg": [float(v) for v in np.degrees(d_rot)],
    }
    return entry, error
