"""The one place that knows the order of the tracking stages: ``track_experiment``.

Per video (in parallel processes with jobs > 1): decode by PTS -> detect markers -> per-frame
bundle pose from that camera. Then, for method ``rig``: choose between mirror solutions of
single-marker frames -> smooth (pass 1) -> joint two-camera solves of near-simultaneous frames,
motion-compensated with the pass-1 trajectory -> smooth again -> (refine != none) self-calibration
over keyframes (annotator.core.refine) -> joint solves with the refined map, rig and lenses (rolling
shutter from the previous pass's motion) -> smooth again. Method ``paper``: per-marker poses
-> batches -> selection -> random-walk Kalman filter.
With jobs > 1 one process pool serves the whole run: the videos, then the joint solves and the
rotation half of each smoothing pass.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import Manager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.priors import ParameterCovariance
from annotator.core.refine import (
    Refinement,
    RefineSettings,
    blur_weight,
    motion_at,
    predicted_smear_px,
    refine_capture,
)
from annotator.core.smoothing import SmootherSettings, smooth_positions, smooth_rotations, supported
from annotator.core.uncertainty import (
    UncertaintySettings,
    row_uncertainty,
    sync_time_sigma,
    total_sigma,
)
from annotator.errors import NoDataError
from annotator.io.experiment import Experiment, MarkerSetup, RigCamera
from annotator.io.trajectory import Trajectory
from annotator.io.video import iter_frames, video_info
from annotator.vision.detection import Detections, DetectorSettings, MarkerDetector
from annotator.vision.geometry import MarkerRoom
from annotator.vision.paper import MarkerPoses, PaperSettings, marker_poses, paper_track
from annotator.vision.pose import (
    BundlePose,
    CameraObservation,
    SolverSettings,
    observe,
    solve_bundle_pose,
)

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]  # (camera, frames done, frames expected)


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
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)  # what sigma_m holds
    # rig: self-calibration after the first pass (annotator.core.refine): none | map | all
    refine: str = "all"
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


# --- stage 1: one video -----------------------------------------------------------------------

def process_video(path: Path, camera: RigCamera, markers: MarkerSetup, t_start: float,
                  settings: TrackSettings, progress: Callable[[int, int], None] | None = None) -> CameraFrames:
    """Decode, detect and solve every frame of one camera's video."""
    info = video_info(path)
    room = MarkerRoom.from_map(markers.markers, markers.length)
    det_settings = dataclasses.replace(settings.detector, dictionary=markers.dictionary,
                                       keep_unknown=settings.detector.keep_unknown or settings.refine != "none")
    detector = MarkerDetector(det_settings, room, camera.calibration)
    cal = camera.calibration
    ts, dets, poses, mposes = [], [], [], []
    total = info.frame_count if settings.max_frames is None else min(info.frame_count, settings.max_frames)
    prior = None
    threads = 1 if settings.jobs > 1 else None  # one process per video already keeps cores busy
    for k, (pts, frame) in enumerate(iter_frames(path, gray=True, threads=threads, luma=True)):
        if settings.max_frames is not None and k >= settings.max_frames:
            break
        if k == 0 and (frame.shape[1], frame.shape[0]) != (cal.width, cal.height):
            raise NoDataError(f"{path}: frames are {frame.shape[1]}x{frame.shape[0]} but the calibration "
                              f"{Path(cal.source).name} is for {cal.width}x{cal.height}")
        det = detector.detect(frame)
        ts.append(t_start + pts)
        dets.append(det)
        if settings.method == "rig":
            obs = observe(det, room, cal, camera.R_bundle_camera, camera.t_bundle_camera)
            pose = solve_bundle_pose([obs], room, settings.solver, prior)
            poses.append(pose)
            prior = (pose.R_wb, pose.t_wb) if pose is not None and pose.n_markers > 1 else prior
        else:
            mposes.append(marker_poses(det, room, camera))
        if progress is not None and (k % 10 == 0):
            progress(k + 1, total)
    if progress is not None:
        progress(len(ts), len(ts))
    interval = float(np.median(np.diff(ts))) if len(ts) > 1 else 1.0 / max(info.fps, 1.0)
    return CameraFrames(camera.name, np.array(ts), dets, poses, mposes, interval)


def _job(args: tuple[Any, ...]) -> CameraFrames:
    path, camera, markers, t_start, settings, q = args
    name = camera.name

    def report(done: int, total: int) -> None:
        q.put((name, done, total))

    return process_video(path, camera, markers, t_start, settings, report)


def _all_videos(exp: Experiment, settings: TrackSettings, progress: Progress | None,
                pool: ProcessPoolExecutor | None = None) -> list[CameraFrames]:
    if exp.video_start is None:
        raise NoDataError(f"{exp.path}: no video start times; run the sync step first (sync.mode auto)")
    names = list(exp.videos)
    if pool is None or len(names) == 1:
        out = []
        for name in names:
            cb = None if progress is None else (lambda d, n, name=name: progress(name, d, n))
            out.append(process_video(exp.videos[name], exp.rig.cameras[name], exp.markers,
                                     exp.video_start[name], settings, cb))
        return out
    with Manager() as mgr:
        q = mgr.Queue()
        futures = [pool.submit(_job, (exp.videos[n], exp.rig.cameras[n], exp.markers, exp.video_start[n],
                                      settings, q)) for n in names]
        while not all(f.done() for f in futures):
            try:
                name, done, total = q.get(timeout=0.2)
            except queue.Empty:
                continue
            if progress is not None:
                progress(name, done, total)
        while True:  # drain the last reports
            try:
                name, done, total = q.get_nowait()
            except queue.Empty:
                break
            if progress is not None:
                progress(name, done, total)
        return [f.result() for f in futures]


@contextmanager
def _worker_pool(settings: TrackSettings) -> Iterator[ProcessPoolExecutor | None]:
    """One process pool for the whole run (videos, then joint solves); None with jobs 1."""
    if settings.jobs <= 1:
        yield None
        return
    # The pool already keeps every core busy; OpenCV's own threads on top would only contend for
    # them. Set it here, before the workers are forked, not in them: a forked child that resizes
    # OpenCV's inherited thread pool can deadlock. This process does no heavy OpenCV work meanwhile.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ProcessPoolExecutor(max_workers=settings.jobs) as pool:
            yield pool
    finally:
        cv2.setNumThreads(threads)


# --- stage 2 (rig): ambiguity, smoothing, joint solves -----------------------------------------------

@dataclass(frozen=True, eq=False)
class Measurements:
    t: np.ndarray  # (N,) sorted
    R: np.ndarray  # (N, 3, 3)
    p: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 6, 6)
    n_markers: np.ndarray  # (N,)
    rms_px: np.ndarray  # (N,)


def _stack(items: list[tuple[float, BundlePose]]) -> Measurements:
    items = sorted(items, key=lambda it: it[0])
    if not items:
        z = np.zeros(0)
        return Measurements(z, np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6, 6)), z, z)
    return Measurements(np.array([t for t, _ in items]), np.array([p.R_wb for _, p in items]),
                        np.array([p.t_wb for _, p in items]), np.array([p.cov for _, p in items]),
                        np.array([p.n_markers for _, p in items]), np.array([p.rms_px for _, p in items]))


def _select(m: Measurements, keep: np.ndarray) -> Measurements:
    return Measurements(m.t[keep], m.R[keep], m.p[keep], m.cov[keep], m.n_markers[keep], m.rms_px[keep])


def resolve_ambiguities(items: list[tuple[float, BundlePose]], window_s: float) -> list[tuple[float, BundlePose]]:
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


def smooth(meas: Measurements, t_out: np.ndarray, s: SmootherSettings,
           pool: ProcessPoolExecutor | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (M, 3), rotations (M, 3, 3) and position sigma (M,) at t_out; NaN where unsupported.

    With a pool, the rotation fit runs in a worker while this process filters the positions.
    """
    if len(meas.t) == 0:
        return np.full((len(t_out), 3), np.nan), np.full((len(t_out), 3, 3), np.nan), np.full(len(t_out), np.nan)
    # Vague measurements (a lone far marker) would only bridge gaps with guesses.
    vague = np.sqrt(np.trace(meas.cov[:, 3:, 3:], axis1=1, axis2=2) / 3) > s.max_meas_sigma_m
    meas = _select(meas, ~vague)
    if len(meas.t) == 0:
        return np.full((len(t_out), 3), np.nan), np.full((len(t_out), 3, 3), np.nan), np.full(len(t_out), np.nan)
    var = np.trace(meas.cov[:, :3, :3], axis1=1, axis2=2) / 3
    rot_args = (meas.t, Rotation.from_matrix(meas.R), var, t_out, s)
    rot_future = None if pool is None else pool.submit(smooth_rotations, *rot_args)
    pos, sig, ok_p = smooth_positions(meas.t, meas.p, meas.cov[:, 3:, 3:], t_out, s)
    R, ok_r = smooth_rotations(*rot_args) if rot_future is None else rot_future.result()
    log.info("smoother kept %d/%d positions, %d/%d rotations", ok_p.sum(), len(ok_p), ok_r.sum(), len(ok_r))
    ok = supported(meas.t[ok_p & ok_r], t_out, s.max_gap_s, s.max_extrapolate_s)
    bad = ~ok | ~np.isfinite(pos).all(1) | ~np.isfinite(R).all((1, 2)) | ~(sig <= s.max_out_sigma_m)
    pos[bad], R[bad], sig[bad] = np.nan, np.nan, np.nan
    return pos, R, sig


def interp_poses(times: np.ndarray, t_grid: np.ndarray, pos: np.ndarray,
                 R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses at ``times`` between grid rows (slerp / linear); (R (n,3,3), p (n,3), valid (n,))."""
    times = np.asarray(times, float)
    i = np.clip(np.searchsorted(t_grid, times), 1, max(len(t_grid) - 1, 1))
    a, b = i - 1, i
    ok = (len(t_grid) > 1) & (times >= t_grid[0]) & (times <= t_grid[-1])
    ok &= np.isfinite(pos[a]).all(1) & np.isfinite(pos[b]).all(1)
    R_out = np.full((len(times), 3, 3), np.nan)
    p_out = np.full((len(times), 3), np.nan)
    if not ok.any():
        return R_out, p_out, ok
    a, b = a[ok], b[ok]
    f = ((times[ok] - t_grid[a]) / np.maximum(t_grid[b] - t_grid[a], 1e-12))[:, None]
    ra, rb = Rotation.from_matrix(R[a]), Rotation.from_matrix(R[b])
    R_out[ok] = (ra * Rotation.from_rotvec(f * (ra.inv() * rb).as_rotvec())).as_matrix()
    p_out[ok] = pos[a] + f * (pos[b] - pos[a])
    return R_out, p_out, ok


def _solve_chunk(args: tuple[Any, ...]) -> list[BundlePose | None]:
    room, solver, problems = args
    return [solve_bundle_pose(obs, room, solver, prior=prior, prior_first=True) for obs, prior in problems]


def _solve_all(problems: list[tuple[list[CameraObservation], tuple[np.ndarray, np.ndarray]]], room: MarkerRoom,
               solver: SolverSettings, pool: ProcessPoolExecutor | None, jobs: int) -> list[BundlePose | None]:
    """Joint solves (each independent of the others), in the pool's processes when there is one."""
    if pool is None or len(problems) < 64:  # a handful of solves costs less than shipping them
        return _solve_chunk((room, solver, problems))
    # A few chunks per worker even out uneven chunks on a loaded machine.
    bounds = np.linspace(0, len(problems), 2 * jobs + 1).astype(int)
    chunks = [(room, solver, problems[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]
    return [pose for part in pool.map(_solve_chunk, chunks) for pose in part]


def joint_measurements(frames: list[CameraFrames], exp: Experiment, room: MarkerRoom, settings: TrackSettings,
                       t_grid: np.ndarray, pos: np.ndarray, R: np.ndarray,
                       pool: ProcessPoolExecutor | None = None,
                       resolve_singles: bool = False) -> list[tuple[float, BundlePose]]:
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
    R_at, p_at, om_at, v_at, ok_at = motion_at(need, t_grid, pos, R)
    lookup = {float(tt): n for n, tt in enumerate(need)}
    tasks: list[tuple[float, list[CameraObservation], tuple[np.ndarray, np.ndarray], list[tuple[int, int]]]] = []
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
    solved = _solve_all([(obs, at_t) for _, obs, at_t, _ in tasks], room, settings.solver, pool, settings.jobs)
    for (t, obs, at_t, joined), pose in zip(tasks, solved, strict=True):
        if pose is not None:
            out.append((t, _blurred(pose, obs, at_t, lookup[t], om_at, v_at, settings.exposure_s)))
            for ci, j in joined:
                used_other[ci].add(j)
    single = _single_solver(exp, room, settings, resolve_singles)
    # Frames of the other cameras not paired with any base frame keep their own solves.
    for ci, cf in enumerate(frames[1:], 1):
        out += [(float(cf.t[j]), p) for j in range(len(cf.t)) if j not in used_other[ci]
                and (p := single(cf, j)) is not None]
    # Base frames whose joint solve failed keep their single-camera solve.
    done = {t for t, _ in out}
    out += [(float(t), p) for j, t in enumerate(base.t) if float(t) not in done and (p := single(base, j)) is not None]
    return out


def _single_solver(exp: Experiment, room: MarkerRoom, settings: TrackSettings,
                   resolve: bool) -> Callable[[CameraFrames, int], BundlePose | None]:
    """A frame's single-camera pose: the first pass's, or (resolve) solved again with ``exp``'s
    parameters (after refinement the first pass's poses carry the old map, rig and lenses)."""
    def single(cf: CameraFrames, j: int) -> BundlePose | None:
        if not resolve or (cf.poses[j] is None and not len(cf.detections[j].ids)):
            return cf.poses[j]
        cam = exp.rig.cameras[cf.camera]
        obs = observe(cf.detections[j], room, cam.calibration, cam.R_bundle_camera, cam.t_bundle_camera)
        # A frame the first pass could not solve may see markers the refinement mapped.
        if cf.poses[j] is None:
            return solve_bundle_pose([obs], room, settings.solver)
        prior = (cf.poses[j].R_wb, cf.poses[j].t_wb)
        return solve_bundle_pose([obs], room, settings.solver, prior, prior_first=True)
    return single


def _blurred(pose: BundlePose, obs: list[CameraObservation], at_t: tuple[np.ndarray, np.ndarray], n: int,
             om_at: np.ndarray, v_at: np.ndarray, exposure_s: float) -> BundlePose:
    """The pose with its covariance widened by the frame's predicted motion blur (the smear of its
    markers during the exposure, from the first pass's velocity)."""
    o = obs[0]
    if not len(o.ids) or exposure_s <= 0:
        return pose
    smear = predicted_smear_px(o.world, at_t[0], at_t[1], om_at[n], v_at[n], o.R_bc, o.t_bc, o.focal, exposure_s)
    w = blur_weight(smear)
    return pose if w >= 0.999 else dataclasses.replace(pose, cov=pose.cov / w)


@dataclass(frozen=True, eq=False)
class TrackResult:
    """A tracking run: the trajectory, and what the self-calibration did (None without it)."""

    trajectory: Trajectory
    refinement: Refinement | None = None
    # Uncertainty of the map, rig and lenses the final pass used (refined, or the priors'):
    # what the uncertainty propagation consumes.
    params: ParameterCovariance | None = None


def _track_rig(frames: list[CameraFrames], exp: Experiment, settings: TrackSettings, t_out: np.ndarray,
               pool: ProcessPoolExecutor | None = None, params: ParameterCovariance | None = None) -> TrackResult:
    """``params``: covariance of map, rig and intrinsics for sigma_m; None -> the refinement's, else the
    experiment's priors."""
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    s = settings.smoother
    singles = [(float(t), p) for cf in frames for t, p in zip(cf.t, cf.poses, strict=True) if p is not None]
    if not singles:
        raise NoDataError(f"{exp.path}: no marker from the map was detected in any video")
    meas = _stack(resolve_ambiguities(singles, s.max_gap_s))
    pos, R, sig = smooth(meas, t_out, s, pool)
    if settings.joint and len(frames) > 1:
        joint = resolve_ambiguities(joint_measurements(frames, exp, room, settings, t_out, pos, R, pool), s.max_gap_s)
        meas = _stack(joint)
        pos, R, sig = smooth(meas, t_out, s, pool)
    refinement = None
    given = exp
    rounds = 2 if settings.refine != "none" else 0
    while rounds:
        rounds -= 1
        initial = None if refinement is None else _mapped_poses(refinement)
        again = refine_capture(frames, given, t_out, pos, R,
                               RefineSettings(mode=settings.refine, exposure_s=settings.exposure_s), initial)
        if again is None:
            break
        refinement = again
        # Track again with the refined map, rig and lenses; the last pass gives the motion.
        exp = refinement.experiment
        room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
        joint = resolve_ambiguities(joint_measurements(frames, exp, room, settings, t_out, pos, R, pool,
                                                       resolve_singles=True), s.max_gap_s)
        meas = _stack(joint)
        pos, R, sig = smooth(meas, t_out, s, pool)
        if not refinement.mapped:
            break  # a second round only helps when markers were mapped from a trajectory with gaps
    posterior = params if params is not None else (refinement.covariance if refinement is not None else None)
    if posterior is not None:
        params = posterior
    else:
        cams = {n: c.calibration.camera_matrix for n, c in exp.rig.cameras.items()}
        params = ParameterCovariance.from_priors(exp.priors, [int(i) for i in room.ids], cams)
    # Quality columns from the measurement at each output time (0 markers where there was none).
    idx = np.searchsorted(meas.t, t_out)
    idx = np.clip(idx, 0, max(len(meas.t) - 1, 0))
    hit = (len(meas.t) > 0) & (np.abs(meas.t[idx] - t_out) < 1e-6) if len(meas.t) else np.zeros(len(t_out), bool)
    n_markers = np.where(hit, meas.n_markers[idx] if len(meas.t) else 0, 0)
    rms = np.where(hit, meas.rms_px[idx] if len(meas.t) else np.nan, np.nan)
    # The priors (posterior None) are checked against the residuals; a posterior is not shrunk.
    u = row_uncertainty(frames, exp, t_out, pos, R, posterior, settings.uncertainty)
    traj = Trajectory(t_out, pos, R, {"markers": n_markers.astype(float), "rms_px": rms,
                                      **total_sigma(sig, u, settings.uncertainty)})
    return TrackResult(traj, refinement, params)


def _mapped_poses(refinement: Refinement) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """(R_world_marker, centre) of the markers a refinement mapped from the video."""
    markers = refinement.experiment.markers.markers
    return {mid: (Rotation.from_euler("xyz", markers[mid].euler_xyz).as_matrix(), np.asarray(markers[mid].position))
            for mid in refinement.mapped}


def _track_paper(frames: list[CameraFrames], settings: TrackSettings) -> Trajectory:
    # All cameras' frames go in together: paper_track orders them in time and counts them as one stream.
    t = np.concatenate([cf.t for cf in frames])
    poses = [mp for cf in frames for mp in cf.marker_poses]
    if not any(len(mp.distance) for mp in poses):
        raise NoDataError("no marker from the map was detected in any video")
    tb, pos, rot, used = paper_track(t, poses, settings.paper)
    if not len(tb):
        raise NoDataError(f"{len(t)} frames in all are fewer than one batch of {settings.paper.frames}")
    bad = used == 0
    pos[bad], rot[bad] = np.nan, np.nan
    return Trajectory(tb, pos, rot, {"markers": used.astype(float)})


def track(exp: Experiment, settings: TrackSettings | None = None, progress: Progress | None = None) -> TrackResult:
    """Track the bundle over the experiment's videos (with the self-calibration's record)."""
    settings = settings or TrackSettings()
    if settings.method not in ("rig", "paper"):
        raise ValueError(f"unknown method {settings.method!r}")
    if settings.refine not in ("none", "map", "all"):
        raise ValueError(f"unknown refine mode {settings.refine!r}")
    with _worker_pool(settings) as pool:
        return frames_to_result(_all_videos(exp, settings, progress, pool), exp, settings, pool)


def track_experiment(exp: Experiment, settings: TrackSettings | None = None,
                     progress: Progress | None = None) -> Trajectory:
    """Trajectory of the bundle (R_world_bundle, beacon position) over the experiment's videos."""
    return track(exp, settings, progress).trajectory


# --- `annotator run`: track -> sync -> label -> outputs ---------------------------------------
# Stage order of a full run. Sync needs the per-frame marker counts, so in `sync.mode: auto` each
# video is first processed on its own PTS clock, then its frame times are mapped onto the RSSI
# clock before the cameras are combined (the joint solve pairs frames by wall time).


@dataclass(frozen=True, slots=True)
class RunSettings:
    track: TrackSettings = field(default_factory=TrackSettings)
    max_gap: float = 0.5  # s: a reading between poses further apart than this stays unlabelled
    beacon: str | None = None  # the bundle's beacon; default: sync.beacon, else the most heard one
    plots: bool = True


@dataclass(frozen=True, eq=False)
class RunResult:
    trajectory: Trajectory
    sync: Any  # annotator.core.sync.SyncResult
    labels: Any  # annotator.core.labeling.Labels, one per reading of `rssi`
    rssi: Any  # annotator.io.rssi.RssiTable: the bundle beacon's readings
    report: dict[str, Any]
    refinement: Refinement | None = None  # what the self-calibration did (None: --refine none, paper)
    params: ParameterCovariance | None = None  # uncertainty of the map, rig and lenses tracked with


def frames_to_trajectory(frames: list[CameraFrames], exp: Experiment, settings: TrackSettings,
                         pool: ProcessPoolExecutor | None = None,
                         params: ParameterCovariance | None = None) -> Trajectory:
    """Stage 2 of tracking on frames whose times are already wall-clock (joint solves in ``pool``);
    ``params`` as in ``_track_rig``."""
    return frames_to_result(frames, exp, settings, pool, params).trajectory


def frames_to_result(frames: list[CameraFrames], exp: Experiment, settings: TrackSettings,
                     pool: ProcessPoolExecutor | None = None,
                     params: ParameterCovariance | None = None) -> TrackResult:
    """`frames_to_trajectory` with the self-calibration's record."""
    if not any(len(cf.t) for cf in frames):
        raise NoDataError(f"{exp.path}: the videos hold no frames")
    if settings.method == "paper":
        return TrackResult(_track_paper(frames, settings))
    t_out = np.unique(np.concatenate([cf.t for cf in frames]))
    return _track_rig(frames, exp, settings, t_out, pool, params)


def run_experiment(exp: Experiment, out_dir: str | Path, settings: RunSettings | None = None,
                   progress: Progress | None = None) -> RunResult:
    """Everything `annotator run` does; writes trajectory.csv, annotated/, annotated.parquet,
    report.json and the plots into ``out_dir``."""
    from dataclasses import replace

    from annotator.core.labeling import label_readings
    from annotator.core.sync import (
        VideoSeries,
        cover_intervals,
        detect_rssi_events,
        manual_sync,
        synchronise,
    )
    from annotator.errors import ConfigError
    from annotator.io.outputs import build_report, write_annotated_mbd, write_parquet, write_report
    from annotator.io.rssi import bundle_beacon, load_rssi
    from annotator.io.sync import brightness_series
    from annotator.io.trajectory import write_trajectory
    from annotator.plots.run import write_run_plots

    settings = settings or RunSettings()
    track = settings.track
    if exp.rssi is None:
        raise ConfigError(f"{exp.path}: no 'rssi:' entry; annotator run needs the RSSI recording")
    everything = load_rssi(exp.rssi)
    beacon = bundle_beacon(everything, settings.beacon or exp.sync.beacon)
    table = everything.select(everything.beacon == beacon)

    if exp.sync_mode == "auto":
        sc = exp.sync
        cover_s = (sc.min_cover_s, sc.max_cover_s)
        # The RSSI event first: cheap, and a missing one should fail before the long video pass.
        rssi_events = detect_rssi_events(table.t_seconds(), table.rssi, table.sensor,
                                         name=f"RSSI of beacon {beacon}", min_duration=cover_s[0],
                                         max_duration=cover_s[1])
        with _worker_pool(track) as pool:
            frames = _all_videos(replace(exp, video_start={n: 0.0 for n in exp.videos}), track, progress, pool)
        series = {}
        for cf in frames:
            n = len(cf.t)
            cb = None if progress is None else (
                lambda k, name=cf.camera, n=n: progress(f"{name} sync", min(k, n), n))
            pts, level = brightness_series(exp.videos[cf.camera], cb)
            if len(pts) < n:
                raise NoDataError(f"{exp.videos[cf.camera]}: decoded {len(pts)} frames, expected {n}")
            if progress is not None:
                progress(f"{cf.camera} sync", n, n)
            counts = np.array([len(d.ids) for d in cf.detections], dtype=float)
            series[cf.camera] = VideoSeries(cf.t, level[:n], counts)
        sync = synchronise(series, rssi_events, approx_start=exp.video_start,
                           max_start_error=sc.max_start_error,
                           min_duration=cover_s[0], max_duration=cover_s[1])
        frames = [replace(cf, t=sync.clocks[cf.camera].to_rssi(cf.t)) for cf in frames]
    else:
        sync = manual_sync(exp.video_start or {})
        with _worker_pool(track) as pool:
            frames = _all_videos(exp, track, progress, pool)
    with _worker_pool(track) as pool:
        result = frames_to_result(frames, exp, track, pool)
    traj = result.trajectory

    # Readings while hands covered the beacon carry the hands' attenuation: never labelled.
    labels = label_readings(traj, table.t_ns, max_gap=settings.max_gap,
                            exclude=cover_intervals(sync.rssi_events),
                            time_sigma=sync_time_sigma(sync.clocks, table.t_seconds()))
    report = build_report(experiment=exp.path, sync=sync, beacon=beacon, readings_total=len(everything),
                          table=table, labels=labels, traj_t=traj.t, traj_valid=traj.valid,
                          max_gap=settings.max_gap, method=track.method)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_trajectory(out / "trajectory.csv", traj)
    write_annotated_mbd(out / "annotated", table, labels)
    write_parquet(out / "annotated.parquet", table, labels)
    if settings.plots:
        valid_t = traj.t[traj.valid]
        plots = write_run_plots(
            out, trajectory=traj.position, t_s=table.t_seconds(), rssi=table.rssi, sensor=table.sensor,
            labelled=labels.labelled, label_positions=labels.positions,
            events=[(e.cover, e.release) for e in sync.rssi_events],
            span=(float(valid_t[0]), float(valid_t[-1])) if valid_t.size else None,
            markers=exp.markers.markers)
        report["plots"] = {k: p.name for k, p in plots.items()}
    if result.refinement is not None:
        from annotator.core.refine import write_refined

        report["refinement"] = {**result.refinement.report,
                                "files": {k: f"refined/{v}" for k, v in write_refined(out / "refined",
                                                                                     result.refinement).items()}}
    write_report(out / "report.json", report)
    log.info("run: %d of %d readings labelled into %s", int(labels.labelled.sum()), len(table), out)
    return RunResult(traj, sync, labels, table, report, result.refinement, result.params)
