"""Tracking maths on arrays, in the order pipeline.py calls them: the single-camera poses of
single-marker frames disambiguated (``resolve_ambiguities``), stacked into a trajectory of
measurements (``stack_poses``), smoothed onto the output times (``smooth``), the joint
multi-camera solves motion-compensated with the previous pass (``joint_measurements``), the
quality columns of the output (``measurement_quality``); method ``paper``: ``track_paper``.
No file is read or written here: the frames come from pipeline.process_video.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import Experiment
from annotator.core.parallel import map_in_runs
from annotator.core.refine import Refinement, blur_weight, motion_at, predicted_smear_px
from annotator.core.smoothing import SmootherSettings, smooth_positions, smooth_rotations, supported
from annotator.core.trajectory import Trajectory
from annotator.core.uncertainty import UncertaintySettings
from annotator.errors import NoDataError
from annotator.vision.detection import Detections, DetectorSettings
from annotator.vision.geometry import MarkerRoom
from annotator.vision.paper import MarkerPoses, PaperSettings, paper_track
from annotator.vision.pose import (
    BundlePose,
    CameraObservation,
    SolverSettings,
    observe,
    solve_bundle_pose,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TrackSettings:
    method: str = "rig"  # rig | paper
    jobs: int = 1
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    solver: SolverSettings = field(default_factory=SolverSettings)
    smoother: SmootherSettings = field(default_factory=SmootherSettings)
    paper: PaperSettings = field(default_factory=PaperSettings)
    joint: bool = True  # rig: joint two-camera solve of near-simultaneous frames
    max_frames: int | None = None  # per video; for quick looks and benchmarks
    uncertainty: UncertaintySettings = field(
        default_factory=UncertaintySettings
    )  # what sigma_m holds
    # rig: self-calibration after the first pass (annotator.core.refine): none | map | all
    refine: str = "all"
    # Each camera's clock against the others' as the self-calibration's prior (s; 0: held at the
    # sync's). `annotator run` sets it where the clock slate synchronised every video.
    clock_sigma_s: float = 0.0
    # Joint solves also inside the previous pass's gaps up to this long (s; 0: never)
    joint_bridge_s: float = 2.0
    # Assumed exposure for the motion-blur measure (predicted smear, px, of each frame's markers).
    exposure_s: float = 0.008


@dataclass(frozen=True, eq=False)
class CameraFrames:
    """What one video yields: frame times, detections and (method rig) single-camera poses."""

    camera: str
    t: np.ndarray  # (N,) wall-clock seconds
    detections: list[Detections]
    poses: list[BundlePose | None]  # method rig
    marker_poses: list[MarkerPoses]  # method paper
    frame_interval: float


def stack_poses(items: list[tuple[float, BundlePose]]) -> Trajectory:
    """Solved frames (time, pose) as a trajectory in time order, with per-row quality ``cov``
    (6x6, rotation then position), ``markers`` and ``rms_px``."""
    items = sorted(items, key=lambda it: it[0])
    if not items:
        z = np.zeros(0)
        return Trajectory(
            z,
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            {"cov": np.zeros((0, 6, 6)), "markers": z, "rms_px": z},
        )
    return Trajectory(
        np.array([t for t, _ in items]),
        np.array([p.t_wb for _, p in items]),
        np.array([p.R_wb for _, p in items]),
        {
            "cov": np.array([p.cov for _, p in items]),
            "markers": np.array([p.n_markers for _, p in items]),
            "rms_px": np.array([p.rms_px for _, p in items]),
        },
    )


def resolve_ambiguities(
    items: list[tuple[float, BundlePose]], window_s: float
) -> list[tuple[float, BundlePose]]:
    """For single-marker frames pick the mirror solution closest to unambiguous neighbours.

    Frames with no unambiguous neighbour within ``window_s`` cannot be decided and are dropped.
    """
    sure = [(t, p) for t, p in items if not p.alternatives]
    if len(sure) == len(items):
        return items
    t_sure = np.array([t for t, _ in sure])
    out = list(sure)
    for t, p in items:
        if not p.alternatives:
            continue
        if len(t_sure) == 0:
            continue
        j = int(np.argmin(np.abs(t_sure - t)))
        if abs(t_sure[j] - t) > window_s:
            continue
        ref = Rotation.from_matrix(sure[j][1].R_wb)
        cands = (p, *p.alternatives)
        angles = [(ref.inv() * Rotation.from_matrix(c.R_wb)).magnitude() for c in cands]
        best = cands[int(np.argmin(angles))]
        out.append((t, BundlePose(best.R_wb, best.t_wb, best.cov, best.rms_px, best.n_markers)))
    return sorted(out, key=lambda it: it[0])


def _nearest(sorted_t: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query time the index of the nearest of ``sorted_t`` and its distance (inf when
    ``sorted_t`` is empty)."""
    query = np.asarray(query, float)
    if not len(sorted_t):
        return np.zeros(len(query), int), np.full(len(query), np.inf)
    hi = (
        np.clip(np.searchsorted(sorted_t, query), 1, len(sorted_t) - 1)
        if len(sorted_t) > 1
        else np.zeros(len(query), int)
    )
    lo = np.maximum(hi - 1, 0)
    pick = np.where(np.abs(sorted_t[lo] - query) <= np.abs(sorted_t[hi] - query), lo, hi)
    return pick, np.abs(sorted_t[pick] - query)


def _position_sigma(p: BundlePose) -> float:
    return float(np.sqrt(np.trace(p.cov[3:, 3:]) / 3))


def anchor_unresolved(
    singles: list[tuple[float, BundlePose]],
    frames: list[CameraFrames],
    exp: Experiment,
    room: MarkerRoom,
    solver: SolverSettings,
    smoother: SmootherSettings,
) -> list[tuple[float, BundlePose]]:
    """``singles`` plus still joint solves where no single-camera pose is both unambiguous and
    precise enough for the smoother (``smoother.max_meas_sigma_m``) within ``smoother.max_gap_s``.

    With a sparse map (a few surveyed markers) each camera often sees one known marker, far away:
    its pose is a mirror pair, metres deep. Two cameras looking different ways fix the pose
    together: those frames of the first camera are solved jointly with the other cameras' nearest
    frames (within half a frame), the bundle taken as still between them. The later passes redo
    these solves with the motion; this only gives them a start. A frame's own single pose is
    replaced by the joint one.
    """
    if len(frames) < 2:
        return singles
    t_good = np.sort(
        [
            t
            for t, p in singles
            if not p.alternatives and _position_sigma(p) <= smoother.max_meas_sigma_m
        ]
    )
    base = frames[0]
    _, gap = _nearest(t_good, base.t)
    nearest = [_nearest(np.asarray(cf.t, float), base.t) for cf in frames]
    found: dict[float, BundlePose] = {}
    for k in np.flatnonzero(gap > smoother.max_gap_s):
        t = float(base.t[k])
        obs = []
        for cf, (at, dist) in zip(frames, nearest, strict=True):
            j = int(at[k])
            if dist[k] > 0.5 * base.frame_interval or not len(cf.detections[j].ids):
                continue
            cam = exp.rig.cameras[cf.camera]
            obs.append(
                observe(
                    cf.detections[j],
                    room,
                    cam.calibration,
                    cam.R_bundle_camera,
                    cam.t_bundle_camera,
                )
            )
        if sum(1 for o in obs if len(o.ids)) < 2:
            continue  # one camera alone gave its single pose already
        pose = solve_bundle_pose(obs, room, solver)
        if pose is not None and not pose.alternatives:
            found[t] = pose
    if not found:
        return singles
    log.info("%d frames posed by still joint solves (no precise single pose near)", len(found))
    kept = [(t, p) for t, p in singles if t not in found]
    return sorted(kept + list(found.items()), key=lambda it: it[0])


def _usable(meas: Trajectory, s: SmootherSettings) -> tuple[Trajectory, np.ndarray]:
    """The measurements the smoother uses, without the vague ones (a lone far marker would only
    bridge gaps with guesses), and each one's rotation variance (rad^2)."""
    vague = (
        np.sqrt(np.trace(meas.quality["cov"][:, 3:, 3:], axis1=1, axis2=2) / 3) > s.max_meas_sigma_m
    )
    meas = meas.select(~vague)
    return meas, np.trace(meas.quality["cov"][:, :3, :3], axis1=1, axis2=2) / 3


def motion_rotations(
    meas: Trajectory, t_out: np.ndarray, R: np.ndarray, s: SmootherSettings
) -> np.ndarray:
    """The rotations the self-calibration reads each frame's motion from: the same measurements
    fitted with the narrower ``motion_rot_bandwidth_s`` kernel, at the rows ``R`` (the smoothed
    rotations) has; ``R`` itself where the narrow fit has no support."""
    meas, var = _usable(meas, s)
    out = np.array(R, dtype=float, copy=True)
    rows = np.isfinite(out).all((1, 2))
    if len(meas.t) == 0 or not rows.any() or s.motion_rot_bandwidth_s >= s.rot_bandwidth_s:
        return out
    narrow = dataclasses.replace(s, rot_bandwidth_s=s.motion_rot_bandwidth_s)
    fit, _ = smooth_rotations(
        meas.t, Rotation.from_matrix(meas.rotation), var, np.asarray(t_out)[rows], narrow
    )
    found = np.isfinite(fit).all((1, 2))
    idx = np.flatnonzero(rows)[found]
    out[idx] = fit[found]
    return out


def smooth(
    meas: Trajectory,
    t_out: np.ndarray,
    s: SmootherSettings,
    pool: ProcessPoolExecutor | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (M, 3), rotations (M, 3, 3) and position sigma (M,) at t_out; NaN where unsupported.

    The sigma is the smoother's, scaled to the noise the frames show about the smoothed track
    (``smooth_positions``' noise_scale): a frame's stated covariance comes from its own corner
    residuals, which also hold the map's and lenses' misfit, covered by sigma_m's parameter part.

    With a pool, the rotation fit runs in a worker while this process filters the positions.
    """
    if len(meas.t) == 0:
        return (
            np.full((len(t_out), 3), np.nan),
            np.full((len(t_out), 3, 3), np.nan),
            np.full(len(t_out), np.nan),
        )
    meas, var = _usable(meas, s)
    if len(meas.t) == 0:
        return (
            np.full((len(t_out), 3), np.nan),
            np.full((len(t_out), 3, 3), np.nan),
            np.full(len(t_out), np.nan),
        )
    cov = meas.quality["cov"]
    rot_args = (meas.t, Rotation.from_matrix(meas.rotation), var, t_out, s)
    rot_future = None if pool is None else pool.submit(smooth_rotations, *rot_args)
    pos, sig, ok_p, noise_scale = smooth_positions(meas.t, meas.position, cov[:, 3:, 3:], t_out, s)
    R, ok_r = smooth_rotations(*rot_args) if rot_future is None else rot_future.result()
    log.info(
        "smoother kept %d/%d positions, %d/%d rotations; the frames scatter about the track "
        "at %.2f of their stated sigma",
        ok_p.sum(),
        len(ok_p),
        ok_r.sum(),
        len(ok_r),
        noise_scale,
    )
    ok = supported(meas.t[ok_p & ok_r], t_out, s.max_gap_s, s.max_extrapolate_s)
    # The rotation fit reaches 3 kernel widths (0.24 s) from a measurement; the position filter
    # bridges gaps up to max_gap_s with a sigma that grows with the gap. In between (a fast
    # turn where both cameras lose the markers for half a second) the rotation is blended
    # between the fits on either side, so a row the filter places is not lost for its rotation.
    missing = ok & np.isfinite(pos).all(1) & ~np.isfinite(R).all((1, 2))
    if missing.any():
        filled = Trajectory(t_out, np.zeros((len(t_out), 3)), R).bridged(s.max_gap_s).rotation
        R[missing] = filled[missing]
    bad = ~ok | ~np.isfinite(pos).all(1) | ~np.isfinite(R).all((1, 2)) | ~(sig <= s.max_out_sigma_m)
    pos[bad], R[bad], sig[bad] = np.nan, np.nan, np.nan
    # Which rows are posed follows the stated noise (above); the sigma reported follows the noise
    # the frames showed.
    return pos, R, sig * noise_scale


def _solve_run(
    shared: tuple[MarkerRoom, SolverSettings],
    problems: Sequence[tuple[list[CameraObservation], tuple[np.ndarray, np.ndarray]]],
) -> list[BundlePose | None]:
    room, solver = shared
    return [
        solve_bundle_pose(obs, room, solver, prior=prior, prior_first=True)
        for obs, prior in problems
    ]


def solve_all(
    problems: list[tuple[list[CameraObservation], tuple[np.ndarray, np.ndarray]]],
    room: MarkerRoom,
    solver: SolverSettings,
    pool: ProcessPoolExecutor | None,
    jobs: int,
) -> list[BundlePose | None]:
    """Joint solves (each independent of the others), in the pool's processes when there is one."""
    parts = map_in_runs(_solve_run, (room, solver), problems, pool, jobs)
    return [pose for part in parts for pose in part]


def joint_measurements(
    frames: list[CameraFrames],
    exp: Experiment,
    room: MarkerRoom,
    settings: TrackSettings,
    t_grid: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    pool: ProcessPoolExecutor | None = None,
    resolve_singles: bool = False,
) -> list[tuple[float, BundlePose]]:
    """Joint solves pairing each frame of the first camera with the other cameras' nearest frames.

    The other camera saw the room at a slightly different time; its extrinsics are moved by the
    bundle motion between the two times, taken from the pass-1 trajectory (relative motion over
    a few ms is known far better than the absolute pose).
    """
    out: list[tuple[float, BundlePose]] = []
    base = frames[0]
    used_other: list[set[int]] = [set() for _ in frames]
    # Pair each base frame with the nearest frame of every other camera (within half a frame).
    pairs: list[list[tuple[CameraFrames, int]]] = []
    for k, t in enumerate(base.t):
        cams = [(base, k)]
        for other in frames[1:]:
            j = int(np.argmin(np.abs(other.t - t))) if len(other.t) else -1
            if j >= 0 and abs(other.t[j] - t) <= 0.5 * base.frame_interval:
                cams.append((other, j))
        pairs.append(cams)
    # Pass-1 poses at every time involved, interpolated in one go.
    need = np.array([float(cf.t[j]) for cams in pairs for cf, j in cams])
    # Where the previous pass has a short gap (a fast turn that blurred the markers of both
    # cameras past a sure single-camera pose), its motion is bridged: the pairing and the rows'
    # times need only a rough motion, and the two cameras together often pose what neither could.
    guess = Trajectory(t_grid, pos, R).bridged(settings.joint_bridge_s)
    R_at, p_at, om_at, v_at, ok_at = motion_at(need, t_grid, guess.position, guess.rotation)
    lookup = {float(tt): n for n, tt in enumerate(need)}
    tasks: list[
        tuple[float, list[CameraObservation], tuple[np.ndarray, np.ndarray], list[tuple[int, int]]]
    ] = []
    for k, t in enumerate(base.t):
        cams = pairs[k]
        n0 = lookup[float(t)]
        if len(cams) == 1 or not ok_at[n0]:
            continue
        at_t = (R_at[n0], p_at[n0])
        obs: list[CameraObservation] = []
        joined: list[tuple[int, int]] = []  # (camera index, frame) of the other cameras used
        for cf, j in cams:
            cam = exp.rig.cameras[cf.camera]
            R_bc, t_bc = cam.R_bundle_camera, cam.t_bundle_camera
            if cf is not base:
                n1 = lookup[float(cf.t[j])]
                if not ok_at[n1]:
                    continue
                there = (R_at[n1], p_at[n1])
                # Delta = T_wb(t)^-1 T_wb(t_other): the bundle at t_other, seen from the bundle at t.
                R_d = at_t[0].T @ there[0]
                t_d = at_t[0].T @ (there[1] - at_t[1])
                R_bc, t_bc = R_d @ R_bc, R_d @ t_bc + t_d
                joined.append((frames.index(cf), j))
            n1 = lookup[float(cf.t[j])]
            # Rolling shutter: each corner at its row's time, the bundle moving as in the first pass.
            motion = (R_at[n1], p_at[n1], om_at[n1], v_at[n1])
            obs.append(observe(cf.detections[j], room, cam.calibration, R_bc, t_bc, motion))
        if sum(len(o.ids) for o in obs) == 0:
            continue
        tasks.append((float(t), obs, at_t, joined))
    solved = solve_all(
        [(obs, at_t) for _, obs, at_t, _ in tasks], room, settings.solver, pool, settings.jobs
    )
    for (t, obs, at_t, joined), pose in zip(tasks, solved, strict=True):
        if pose is not None:
            out.append((t, blurred(pose, obs, at_t, lookup[t], om_at, v_at, settings.exposure_s)))
            for ci, j in joined:
                used_other[ci].add(j)
    single = single_solver(exp, room, settings, resolve_singles)
    # Frames of the other cameras not paired with any base frame keep their own solves.
    for ci, cf in enumerate(frames[1:], 1):
        out += [
            (float(cf.t[j]), p)
            for j in range(len(cf.t))
            if j not in used_other[ci] and (p := single(cf, j)) is not None
        ]
    # Base frames whose joint solve failed keep their single-camera solve.
    done = {t for t, _ in out}
    out += [
        (float(t), p)
        for j, t in enumerate(base.t)
        if float(t) not in done and (p := single(base, j)) is not None
    ]
    return out


def single_solver(
    exp: Experiment, room: MarkerRoom, settings: TrackSettings, resolve: bool
) -> Callable[[CameraFrames, int], BundlePose | None]:
    """A frame's single-camera pose: the first pass's, or (resolve) solved again with ``exp``'s
    parameters (after refinement the first pass's poses carry the old map, rig and lenses)."""

    def single(cf: CameraFrames, j: int) -> BundlePose | None:
        first = cf.poses[j]
        if not resolve or (first is None and not len(cf.detections[j].ids)):
            return first
        cam = exp.rig.cameras[cf.camera]
        obs = observe(
            cf.detections[j], room, cam.calibration, cam.R_bundle_camera, cam.t_bundle_camera
        )
        # A frame the first pass could not solve may see markers the refinement mapped.
        if first is None:
            return solve_bundle_pose([obs], room, settings.solver)
        prior = (first.R_wb, first.t_wb)
        return solve_bundle_pose([obs], room, settings.solver, prior, prior_first=True)

    return single


def blurred(
    pose: BundlePose,
    obs: list[CameraObservation],
    at_t: tuple[np.ndarray, np.ndarray],
    n: int,
    om_at: np.ndarray,
    v_at: np.ndarray,
    exposure_s: float,
) -> BundlePose:
    """The pose with its covariance widened by the frame's predicted motion blur (the smear of its
    markers during the exposure, from the first pass's velocity)."""
    o = obs[0]
    if not len(o.ids) or exposure_s <= 0:
        return pose
    smear = predicted_smear_px(
        o.world, at_t[0], at_t[1], om_at[n], v_at[n], o.R_bc, o.t_bc, o.focal, exposure_s
    )
    w = blur_weight(smear)
    return pose if w >= 0.999 else dataclasses.replace(pose, cov=pose.cov / w)


def measurement_quality(meas: Trajectory, t_out: np.ndarray) -> dict[str, np.ndarray]:
    """Quality columns ``markers`` and ``rms_px`` at each output time from the measurement made at
    that very time (0 markers and NaN where there was none)."""
    idx = np.searchsorted(meas.t, t_out)
    idx = np.clip(idx, 0, max(len(meas.t) - 1, 0))
    hit = (
        (len(meas.t) > 0) & (np.abs(meas.t[idx] - t_out) < 1e-6)
        if len(meas.t)
        else np.zeros(len(t_out), bool)
    )
    n_markers = np.where(hit, meas.quality["markers"][idx] if len(meas.t) else 0, 0)
    rms = np.where(hit, meas.quality["rms_px"][idx] if len(meas.t) else np.nan, np.nan)
    return {"markers": n_markers.astype(float), "rms_px": rms}


def mapped_poses(refinement: Refinement) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """(R_world_marker, centre) of the markers a refinement mapped from the video."""
    markers = refinement.experiment.markers.markers
    return {
        mid: (
            Rotation.from_euler("xyz", markers[mid].euler_xyz).as_matrix(),
            np.asarray(markers[mid].position),
        )
        for mid in refinement.mapped
    }


def track_paper(frames: list[CameraFrames], settings: TrackSettings) -> Trajectory:
    # All cameras' frames go in together: paper_track orders them in time and counts them as one stream.
    t = np.concatenate([cf.t for cf in frames])
    poses = [mp for cf in frames for mp in cf.marker_poses]
    if not any(len(mp.distance) for mp in poses):
        raise NoDataError("no marker from the map was detected in any video")
    tb, pos, rot, used = paper_track(t, poses, settings.paper)
    if not len(tb):
        raise NoDataError(
            f"{len(t)} frames in all are fewer than one batch of {settings.paper.frames}"
        )
    bad = used == 0
    pos[bad], rot[bad] = np.nan, np.nan
    return Trajectory(tb, pos, rot, {"markers": used.astype(float)})
