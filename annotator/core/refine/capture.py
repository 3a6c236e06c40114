"""A capture's self-calibration: keyframes from the first tracking pass, the solve, the refined
experiment and its report."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.priors import ParameterCovariance
from annotator.core.refine.model import CameraParams, Problem, RefineSettings, Solution
from annotator.core.refine.problem import FrameView, Keyframe, build_problem
from annotator.core.refine.report import (
    REFINEMENT_VERSION,
    CameraRefinement,
    MovedMarker,
    Observability,
    PrintedLength,
    RefinementReport,
)
from annotator.core.refine.solver import solve

if TYPE_CHECKING:
    from annotator.core.experiment import Experiment, RigCamera
    from annotator.core.uncertainty import VideoFrames

log = logging.getLogger(__name__)

# --- a capture: keyframes from the first tracking pass, the refined experiment ---------------------


def motion_at(
    times: np.ndarray, t_grid: np.ndarray, pos: np.ndarray, R: np.ndarray, dt: float = 1 / 60
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bundle pose and velocity at ``times`` from a trajectory: (R, p, omega_world, v_world, ok)."""
    from annotator.core.trajectory import Trajectory

    times = np.asarray(times, float)
    traj = Trajectory(np.asarray(t_grid, float), pos, R)
    p0, R0, ok0 = traj.interpolate(times)
    pa, Ra, oka = traj.interpolate(times - dt)
    pb, Rb, okb = traj.interpolate(times + dt)
    ok = ok0 & oka & okb
    omega = np.zeros((len(times), 3))
    vel = np.zeros((len(times), 3))
    if ok.any():
        # R(t + dt) = exp(w dt) R(t): world-frame angular velocity.
        omega[ok] = Rotation.from_matrix(Rb[ok] @ np.transpose(Ra[ok], (0, 2, 1))).as_rotvec() / (
            2 * dt
        )
        vel[ok] = (pb[ok] - pa[ok]) / (2 * dt)
    return R0, p0, omega, vel, ok


def predicted_smear_px(
    world: np.ndarray,
    R_wb: np.ndarray,
    p_wb: np.ndarray,
    omega: np.ndarray,
    vel: np.ndarray,
    R_bc: np.ndarray,
    t_bc: np.ndarray,
    focal: float,
    exposure_s: float,
) -> float:
    """How far (px) the fastest of these world points smears across the image during one exposure.

    The motion-blur measure: the bundle moving at (omega, vel) for ``exposure_s`` moves each point's
    pinhole image by this much (a lens' distortion changes it by a few per cent only).
    """
    pts = np.asarray(world, float).reshape(-1, 3)
    if not len(pts) or exposure_s <= 0:
        return 0.0

    def image(Rw: np.ndarray, pw: np.ndarray) -> np.ndarray:
        Xc = ((pts - pw) @ Rw @ R_bc) - t_bc @ R_bc  # R_bc^T (R_wb^T (X - p) - t_bc)
        z = np.maximum(Xc[:, 2], 1e-3)
        return Xc[:, :2] / z[:, None]

    R1 = Rotation.from_rotvec(omega * exposure_s).as_matrix() @ R_wb
    d = image(R1, p_wb + vel * exposure_s) - image(R_wb, p_wb)
    return float(focal * np.max(np.linalg.norm(d, axis=1)))


def blur_weight(smear_px: float, scale_px: float = 2.0) -> float:
    """Weight of a frame's corners given its predicted smear: 1 when sharp, ~(scale/smear)^2 when not."""
    return 1.0 / (1.0 + (smear_px / scale_px) ** 2)


def camera_params(rig_cam: RigCamera) -> CameraParams:
    cal = rig_cam.calibration
    return CameraParams(
        rig_cam.name,
        rig_cam.R_bundle_camera,
        rig_cam.t_bundle_camera,
        cal.camera_matrix,
        np.asarray(cal.dist_coeffs, float),
        cal.model,
        cal.readout_s,
        cal.height,
        cal.corner_bias_px,
    )


def select_keyframes(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_grid: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    settings: RefineSettings,
) -> list[Keyframe]:
    """Keyframes over the capture: frames of the first camera with the other cameras' nearest
    frames, where the first pass has a pose and enough markers are seen.

    Chosen for what they make observable: up to ``turn_share`` of them are the frames where the
    picture moves fastest (a turn; predicted smear above 1 px and up to ``max_turn_smear_px``),
    since only a moving picture shows the rolling shutter's readout (its skew grows with the
    picture's speed while the blur's weight levels off); the rest are sharp frames (smear up to
    ``max_smear_px``) spread evenly over the capture. A keyframe's corners weigh by its smear (``blur_weight``): a
    blurred frame counts less, it is not excluded. A cart pushed in straight lines with turns in
    place has all its motion in the turns, which a sharp-only choice left out (readout and focal
    length then stayed at their priors)."""
    base = frames[0]
    if not len(base.t):
        return []
    cams = [exp.rig.cameras[cf.camera] for cf in frames]
    focal = [
        float(np.sqrt(c.calibration.camera_matrix[0, 0] * c.calibration.camera_matrix[1, 1]))
        for c in cams
    ]
    Rk, pk, om, vel, ok = motion_at(base.t, t_grid, pos, R)
    counts = np.array([len(d.ids) for d in base.detections])
    partner: list[list[tuple[int, int]]] = [[(0, k)] for k in range(len(base.t))]
    for ci, cf in enumerate(frames[1:], 1):
        if not len(cf.t):
            continue
        order = np.argsort(cf.t, kind="stable")  # each base frame's nearest frame of this camera
        ts = cf.t[order]
        right = np.searchsorted(ts, base.t).clip(0, len(ts) - 1)
        left = (right - 1).clip(0)
        near = np.where(np.abs(ts[left] - base.t) <= np.abs(ts[right] - base.t), left, right)
        for k in np.flatnonzero(np.abs(ts[near] - base.t) <= 0.5 * base.frame_interval).tolist():
            j = int(order[near[k]])
            partner[k].append((ci, j))
            counts[k] += len(cf.detections[j].ids)
    cand = np.flatnonzero(ok & (counts >= settings.min_markers))
    if not len(cand):
        return []
    # The keyframes are spread over the whole capture: scoring the blur of an evenly spread subset
    # of 8 candidates per keyframe keeps a long capture's cost flat and still leaves sharp ones.
    if len(cand) > 8 * settings.max_keyframes:
        cand = cand[
            np.unique(np.linspace(0, len(cand) - 1, 8 * settings.max_keyframes).round().astype(int))
        ]
    # Sharp frames for most keyframes, moving ones (turns) for a share of them.
    room_centres = {int(m): np.asarray(p.position, float) for m, p in exp.markers.markers.items()}
    scored = []
    for k in cand.tolist():
        det = base.detections[k]
        pts = np.array([room_centres[int(i)] for i in det.ids if int(i) in room_centres]).reshape(
            -1, 3
        )
        smear = predicted_smear_px(
            pts,
            Rk[k],
            pk[k],
            om[k],
            vel[k],
            cams[0].R_bundle_camera,
            cams[0].t_bundle_camera,
            focal[0],
            settings.exposure_s,
        )
        scored.append((k, smear))
    fastest = sorted(
        (ks for ks in scored if settings.min_turn_smear_px < ks[1] <= settings.max_turn_smear_px),
        key=lambda ks: -ks[1],
    )
    moving = sorted(fastest[: int(settings.turn_share * settings.max_keyframes)])
    taken = {k for k, _ in moving}
    sharp = [ks for ks in scored if ks[1] <= settings.max_smear_px and ks[0] not in taken]
    if len(sharp) < max(10, len(cand) // 5):  # a fast walk throughout: take the sharpest fifth
        sharp, moving = [(k, 0.0) for k in cand.tolist()], []
    n_moving = len(moving)
    n_sharp = min(settings.max_keyframes - n_moving, len(sharp))
    chosen = sorted(
        [sharp[i] for i in np.unique(np.linspace(0, len(sharp) - 1, n_sharp).round().astype(int))]
        + (
            [
                moving[i]
                for i in np.unique(np.linspace(0, len(moving) - 1, n_moving).round().astype(int))
            ]
            if n_moving
            else []
        )
    )
    log.info(
        "refine: %d keyframes, %d of them of a moving picture (%d candidates: %d sharp, %d moving)",
        len(chosen),
        n_moving,
        len(cand),
        len(sharp),
        len(moving),
    )
    times = np.array([frames[ci].t[j] for k, _ in chosen for ci, j in partner[k]])
    Rj, pj, omj, velj, okj = motion_at(times, t_grid, pos, R)
    out, n = [], 0
    for k, smear in chosen:
        kf_views = []
        R0, p0 = Rk[k], pk[k]
        for ci, j in partner[k]:
            i, n = n, n + 1
            if not okj[i]:
                continue
            det = frames[ci].detections[j]
            kf_views.append(
                FrameView(
                    ci,
                    det.ids,
                    det.corners if det.edge is None else det.edge,
                    R0.T @ Rj[i],
                    R0.T @ (pj[i] - p0),
                    R0.T @ omj[i],
                    R0.T @ velj[i],
                    blur_weight(smear),
                )
            )
        out.append(Keyframe(R0, p0, kf_views))
    return out


@dataclass(frozen=True, eq=False)
class Refinement:
    """What refining a capture produced: the experiment to track with, the record, covariances."""

    experiment: Experiment  # with the refined map, rig and calibrations
    solution: Solution
    covariance: ParameterCovariance
    report: RefinementReport
    mapped: list[int]  # markers the survey did not give, now mapped from the video
    # Per camera: its frames were seen this much later than their stamps (s; the cameras' mean 0).
    clock_s: dict[str, float] = field(default_factory=dict)


def refine_capture(
    frames: Sequence[VideoFrames],
    exp: Experiment,
    t_grid: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    settings: RefineSettings | None = None,
    initial: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Refinement | None:
    """Refine the experiment's map (mode map) and rig, lenses, readouts (mode all) from a first pass.

    ``initial``: start poses (R_world_marker, centre) of markers the survey lacks, from an
    earlier round."""

    from annotator.core.experiment import Rig
    from annotator.vision.geometry import MarkerRoom
    from bgt_core.formats.markers import MarkerPose

    s = (settings or RefineSettings()).validate()
    t0 = time.perf_counter()
    keyframes = select_keyframes(frames, exp, t_grid, pos, R, s)
    if len(keyframes) < 5:
        log.warning(
            "refine: only %d usable keyframes; the given map, rig and lenses are kept",
            len(keyframes),
        )
        return None
    cams = [camera_params(exp.rig.cameras[cf.camera]) for cf in frames]
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    survey = {
        int(m): (room.R_world_marker[i], room.t_world_marker[i]) for i, m in enumerate(room.ids)
    }
    prob, starts = build_problem(
        survey,
        exp.markers.length,
        cams,
        keyframes,
        exp.priors,
        initial=initial,
        length_sigma_rel=exp.markers.length_sigma,
    )
    sol = solve(prob, s, starts)
    euler = Rotation.from_matrix(sol.R_m).as_euler("xyz")
    markers = dict(exp.markers.markers)
    mapped = []
    for m, mid in enumerate(prob.markers):
        if mid not in markers:
            mapped.append(mid)
        markers[mid] = MarkerPose.from_values(mid, sol.t_m[m], euler[m])
    rig = dict(exp.rig.cameras)
    for c, cf in enumerate(frames):
        rc, new = rig[cf.camera], sol.cameras[c]
        # The corner bias is estimated (it keeps small markers from looking too far away in the
        # adjustment) and reported, but not applied to the final pass: its frames see several
        # markers each, where a constant correction of a bias that varies with a marker's size
        # in the image removes no more error than it adds (measured on the renders).
        cal = replace(
            rc.calibration, camera_matrix=new.K, dist_coeffs=new.dist, readout_s=new.readout_s
        )
        rig[cf.camera] = replace(
            rc, calibration=cal, R_bundle_camera=new.R_bc, t_bundle_camera=new.t_bc
        )
    # The markers as printed: the next pass measures with the length the capture found (held at
    # the stated one when the data cannot tell them apart).
    refined = replace(
        exp,
        markers=replace(exp.markers, markers=markers, length=length_used(exp, sol)),
        rig=Rig(rig, exp.rig.source),
    )
    report = refinement_report(
        prob, sol, cams, exp, s, len(keyframes), mapped, time.perf_counter() - t0
    )
    clock_s = {cf.camera: sol.cameras[c].clock_s for c, cf in enumerate(frames)}
    return Refinement(refined, sol, sol.covariance, report, mapped, clock_s)


def length_used(exp: Experiment, sol: Solution) -> float:
    """The markers' length the next pass measures with: the printed size the capture found, or
    the stated length when the data could not tell them apart."""
    return exp.markers.length * (sol.length_scale if sol.length_scale_determined else 1.0)


# The blocks a camera's refinement may change, as report.json names them, with what the prior is.
_BLOCK_NAMES = {
    "rig": ("rig pose", "rig.yaml's"),
    "intr": ("focal length and principal point", "the calibration's"),
    "dist": ("lens distortion", "the calibration's"),
    "readout": ("rolling-shutter readout", "the calibration's"),
    "clock": ("clock offset from the other cameras", "the sync's"),
    "bias": ("corner bias", "0 px"),
}


def observability(determined: dict[str, bool], cam: CameraParams) -> Observability:
    """report.json's per-camera verdicts: which parameters the capture determined and which kept
    their prior because the walk did not show them (``determined``: block -> applied)."""
    out: Observability = {"determined": {}, "notes": []}
    for block, (what, prior) in _BLOCK_NAMES.items():
        if block not in determined:
            out["determined"][block] = None  # not refined (mode map)
            continue
        out["determined"][block] = bool(determined[block])
        if not determined[block]:
            value = f" ({cam.readout_s * 1000:.1f} ms)" if block == "readout" else ""
            out["notes"].append(f"{what} not observable in this walk: {prior} value{value} kept")
    return out


def refinement_report(
    prob: Problem,
    sol: Solution,
    cams: list[CameraParams],
    exp: Experiment,
    s: RefineSettings,
    n_keyframes: int,
    mapped: list[int],
    seconds: float,
) -> RefinementReport:
    """report.json's ``refinement`` section (refinement.json)."""
    cameras: dict[str, CameraRefinement] = {}
    for a, b in zip(cams, sol.cameras, strict=True):
        cov = sol.covariance
        ro = cov.readout.get(a.name)
        cameras[a.name] = {
            "rms_px_before": round(sol.rms_before[a.name], 3),
            "rms_px_after": round(sol.rms_after[a.name], 3),
            "rig_rotation_change_deg": [
                round(float(v), 4)
                for v in np.degrees(Rotation.from_matrix(b.R_bc @ a.R_bc.T).as_rotvec())
            ],
            "rig_position_change_m": [round(float(v), 5) for v in b.t_bc - a.t_bc],
            "focal_change_rel": [
                round(float(b.K[0, 0] / a.K[0, 0] - 1), 6),
                round(float(b.K[1, 1] / a.K[1, 1] - 1), 6),
            ],
            "principal_change_px": [
                round(float(b.K[0, 2] - a.K[0, 2]), 3),
                round(float(b.K[1, 2] - a.K[1, 2]), 3),
            ],
            "distortion_change": [
                round(float(v), 6) for v in np.asarray(b.dist) - np.asarray(a.dist)
            ],
            "readout_s": round(b.readout_s, 5),
            "corner_bias_px": round(b.corner_bias_px, 3),
            "readout_sigma_s": None if ro is None else round(float(np.sqrt(ro[0, 0])), 5),
            "clock_offset_ms": round(1000 * b.clock_s, 2),
            "clock_sigma_ms": (
                round(1000 * sol.clock_sigma_s[a.name], 2) if a.name in sol.clock_sigma_s else None
            ),
            **observability(sol.determined.get(a.name, {}), a),
        }
    moved: list[MovedMarker] = []
    for mid in sol.moved:
        m = prob.markers.index(mid)
        moved.append(
            {
                "id": int(mid),
                "offset_m": [round(float(v), 4) for v in sol.t_m[m] - prob.t_m[m]],
                "survey_sigma_m": float(prob.marker_sigma[m, 1]),
                "note": "moved since the survey?",
            }
        )
    seen = sorted(int(prob.markers[m]) for m in np.unique(prob.obs.marker))
    printed: PrintedLength = {"stated_m": exp.markers.length, "estimated": False}
    if math.isfinite(sol.length_scale_sigma):
        printed.update(
            {
                "estimated": True,
                "scale": round(sol.length_scale, 5),
                "scale_sigma": round(sol.length_scale_sigma, 5),
                "found_m": round(exp.markers.length * sol.length_scale, 5),
                "determined": sol.length_scale_determined,
                "used_m": round(length_used(exp, sol), 5),
                "note": (
                    "the capture measured the printed size"
                    if sol.length_scale_determined
                    else "within noise of the stated length, which was kept"
                ),
            }
        )
    return {
        "version": REFINEMENT_VERSION,
        "mode": s.mode,
        "keyframes": n_keyframes,
        "corners": int(len(prob.obs.uv)),
        "markers_seen": seen,
        "iterations": sol.iterations,
        "seconds": round(seconds, 2),
        "corner_sigma_px": round(sol.sigma_px, 3),
        "cameras": cameras,
        "markers_mapped": [int(m) for m in mapped],
        "markers_moved": moved,
        "printed_length": printed,
    }
