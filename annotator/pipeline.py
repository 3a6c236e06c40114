"""The one place that knows the order of the stages: ``track`` and ``run_experiment``.

Per video (in parallel processes with jobs > 1): decode by PTS -> detect markers -> per-frame
bundle pose from that camera. Then, for method ``rig``: choose between mirror solutions of
single-marker frames -> smooth (pass 1) -> joint two-camera solves of near-simultaneous frames,
motion-compensated with the pass-1 trajectory -> smooth again -> (refine != none) self-calibration
over keyframes (annotator.core.refine) -> joint solves with the refined map, rig and lenses (rolling
shutter from the previous pass's motion) -> smooth again. Method ``paper``: per-marker poses
-> batches -> selection -> random-walk Kalman filter.
With jobs > 1 one process pool serves the whole run: the videos, then the joint solves, the
rotation half of each smoothing pass and the rows' uncertainty.

Only the order lives here: the maths of each stage are in annotator.core (tracking, smoothing,
refine, uncertainty, sync, labeling), the files are read by annotator.io. ``track`` returns a
``TrackResult`` and ``run_experiment`` a ``RunResult``; neither writes a file, the commands
(annotator.commands.track, annotator.commands.run) write the outputs.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import Manager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from annotator.core.experiment import Experiment, MarkerSetup, RigCamera
from annotator.core.jig import (
    correct_experiment,
    datum_variance,
    jig_correction,
    rest_rows,
    rest_variance,
)
from annotator.core.priors import ParameterCovariance
from annotator.core.refine import Refinement, RefineSettings, refine_capture
from annotator.core.refine.model import CLOCK_SIGMA_S
from annotator.core.tracking import (
    CameraFrames,
    TrackSettings,
    anchor_unresolved,
    joint_measurements,
    mapped_poses,
    measurement_quality,
    motion_rotations,
    resolve_ambiguities,
    smooth,
    stack_poses,
    track_paper,
)
from annotator.core.trajectory import Trajectory
from annotator.core.uncertainty import (
    condition_on_rest,
    row_uncertainty,
    sync_time_sigma,
    total_sigma,
)
from annotator.errors import NoDataError
from annotator.io.video import iter_frames, video_info
from annotator.vision.detection import MarkerDetector
from annotator.vision.geometry import MarkerRoom
from annotator.vision.paper import marker_poses
from annotator.vision.pose import observe, solve_bundle_pose

if TYPE_CHECKING:
    from annotator.core.labeling import Labels
    from annotator.core.sync import SyncResult
    from annotator.io.report_records import Report
    from annotator.io.rssi import RssiTable

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]  # (camera, frames done, frames expected)


# --- stage 1: one video -----------------------------------------------------------------------


def process_video(
    path: Path,
    camera: RigCamera,
    markers: MarkerSetup,
    t_start: float,
    settings: TrackSettings,
    progress: Callable[[int, int], None] | None = None,
    frames: tuple[int, int | None] | None = None,
    warmup: int = 0,
) -> CameraFrames:
    """Decode, detect and solve every frame of one camera's video, or only frames
    ``[first, stop)`` (``stop`` None: to the end) after ``warmup`` frames solved but not kept
    (the previous frame's pose starts each solve: a chunk begins as the whole video would)."""
    first, stop = frames if frames is not None else (0, None)
    lo = max(0, first - warmup)
    info = video_info(path)
    room = MarkerRoom.from_map(markers.markers, markers.length)
    det_settings = dataclasses.replace(
        settings.detector,
        dictionary=markers.dictionary,
        keep_unknown=settings.detector.keep_unknown or settings.refine != "none",
        edge_corners_for_refine=settings.detector.edge_corners_for_refine
        or settings.refine != "none",
    )
    detector = MarkerDetector(det_settings, room, camera.calibration)
    cal = camera.calibration
    ts, dets, poses, mposes = [], [], [], []
    total = (
        info.frame_count
        if settings.max_frames is None
        else min(info.frame_count, settings.max_frames)
    )
    prior = None
    threads = 1 if settings.jobs > 1 else None  # one process per video already keeps cores busy
    for k, (pts, frame) in enumerate(iter_frames(path, gray=True, threads=threads, luma=True)):
        if (settings.max_frames is not None and k >= settings.max_frames) or (
            stop is not None and k >= stop
        ):
            break
        if k < lo:
            continue
        if k == 0 and (frame.shape[1], frame.shape[0]) != (cal.width, cal.height):
            raise NoDataError(
                f"{path}: frames are {frame.shape[1]}x{frame.shape[0]} but the calibration "
                f"{Path(cal.source).name} is for {cal.width}x{cal.height}"
            )
        det = detector.detect(frame)
        keep = k >= first
        if keep:
            ts.append(t_start + pts)
            dets.append(det)
        if settings.method == "rig":
            obs = observe(det, room, cal, camera.R_bundle_camera, camera.t_bundle_camera)
            pose = solve_bundle_pose([obs], room, settings.solver, prior)
            if keep:
                poses.append(pose)
            prior = (pose.R_wb, pose.t_wb) if pose is not None and pose.n_markers > 1 else prior
        elif keep:
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


def _all_videos(
    exp: Experiment,
    settings: TrackSettings,
    progress: Progress | None,
    pool: ProcessPoolExecutor | None = None,
) -> list[CameraFrames]:
    if exp.video_start is None:
        raise NoDataError(
            f"{exp.path}: no video start times; run the sync step first (sync.mode auto)"
        )
    names = list(exp.videos)
    if pool is None or len(names) == 1:
        out = []
        for name in names:
            cb = None if progress is None else (lambda d, n, name=name: progress(name, d, n))
            out.append(
                process_video(
                    exp.videos[name],
                    exp.rig.cameras[name],
                    exp.markers,
                    exp.video_start[name],
                    settings,
                    cb,
                )
            )
        return out
    with Manager() as mgr:
        q = mgr.Queue()
        futures = [
            pool.submit(
                _job,
                (exp.videos[n], exp.rig.cameras[n], exp.markers, exp.video_start[n], settings, q),
            )
            for n in names
        ]
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


@dataclass(frozen=True, eq=False)
class TrackResult:
    """A tracking run: the trajectory, and what the self-calibration did (None without it)."""

    trajectory: Trajectory
    refinement: Refinement | None = None
    # Uncertainty of the map, rig and lenses the final pass used (refined, or the priors'):
    # what the uncertainty propagation consumes.
    params: ParameterCovariance | None = None
    # How much later than its synchronised stamps each camera's frames were seen, as the
    # self-calibration found (the cameras' mean held at 0); empty without it.
    clock_s: dict[str, float] = field(default_factory=dict)


def _track_rig(
    frames: list[CameraFrames],
    exp: Experiment,
    settings: TrackSettings,
    t_out: np.ndarray,
    pool: ProcessPoolExecutor | None = None,
    params: ParameterCovariance | None = None,
) -> TrackResult:
    """``params``: covariance of map, rig and intrinsics for sigma_m; None -> the refinement's, else the
    experiment's priors."""
    room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
    s = settings.smoother
    singles = [
        (float(t), p) for cf in frames for t, p in zip(cf.t, cf.poses, strict=True) if p is not None
    ]
    if not singles:
        raise NoDataError(f"{exp.path}: no marker from the map was detected in any video")
    seen = len(singles)
    singles = anchor_unresolved(singles, frames, exp, room, settings.solver, s)
    meas = stack_poses(resolve_ambiguities(singles, s.max_gap_s))
    pos, R, sig = smooth(meas, t_out, s, pool)
    if settings.joint and len(frames) > 1:
        joint = resolve_ambiguities(
            joint_measurements(frames, exp, room, settings, t_out, pos, R, pool), s.max_gap_s
        )
        meas = stack_poses(joint)
        pos, R, sig = smooth(meas, t_out, s, pool)
    if not np.isfinite(pos).all(1).any():
        raise NoDataError(
            f"{exp.path}: no frame could be posed: {seen} frames saw markers of the map, never "
            "enough of them for a sure pose (a lone far marker is ambiguous); add markers near "
            "the walk to the map"
        )
    refinement = None
    given = exp
    rounds = 2 if settings.refine != "none" else 0
    clock = {"solve": 0.0, "retrack": 0.0, "rounds": 0}  # what the self-calibration cost, s
    offsets = {cf.camera: 0.0 for cf in frames}  # each camera's clock as the rounds found it
    while rounds:
        rounds -= 1
        initial = None if refinement is None else mapped_poses(refinement)
        t0 = time.perf_counter()
        again = refine_capture(
            frames,
            given,
            t_out,
            pos,
            motion_rotations(meas, t_out, R, s),
            RefineSettings(
                mode=settings.refine,
                exposure_s=settings.exposure_s,
                clock_sigma_s=settings.clock_sigma_s,
            ),
            initial,
        )
        clock["solve"] += time.perf_counter() - t0
        if again is None:
            break
        refinement, t0 = again, time.perf_counter()
        clock["rounds"] += 1
        refinement.report["timing"] = clock
        # Track again with the refined map, rig and lenses; the last pass gives the motion.
        exp = refinement.experiment
        room = MarkerRoom.from_map(exp.markers.markers, exp.markers.length)
        # Each camera's frames at the time they were seen (the clock offsets found); the last
        # pass's motion stays on its own grid.
        t_prev = t_out
        if any(refinement.clock_s.values()):
            frames = [
                dataclasses.replace(cf, t=cf.t + refinement.clock_s.get(cf.camera, 0.0))
                for cf in frames
            ]
            for name, dt in refinement.clock_s.items():
                offsets[name] += dt
            t_out = np.unique(np.concatenate([cf.t for cf in frames]))
        joint = resolve_ambiguities(
            joint_measurements(
                frames, exp, room, settings, t_prev, pos, R, pool, resolve_singles=True
            ),
            s.max_gap_s,
        )
        meas = stack_poses(joint)
        pos, R, sig = smooth(meas, t_out, s, pool)
        clock["retrack"] += time.perf_counter() - t0
        # A second round helps when markers were mapped from a trajectory with gaps, and always
        # when the lenses' readouts are refined: the first round fitted them to the motion of a
        # trajectory tracked with the written readout (0 when unknown) and rig, whose row-to-row
        # motion is off; the fit then leans on the readout's prior and on the rig's turn about
        # each optical axis, which a steady turn of the walk makes look alike. On field renders
        # (15 ms true, 0 written) one round gave 0-13.6 ms (stated sigma ~1.5 ms), two 10.9-14.9.
        if not refinement.mapped and settings.refine != "all":
            break
    if exp.priors.jig is not None:
        exp, pos, R, refinement = _apply_jig(exp, given, t_out, pos, R, refinement)
    posterior = (
        params
        if params is not None
        else (refinement.covariance if refinement is not None else None)
    )
    if posterior is not None and refinement is not None and "jig" in refinement.report:
        # The rest pinned the rig's gauge and where the map sits near it: condition on it.
        jig = exp.priors.jig
        assert jig is not None
        posterior = condition_on_rest(
            frames,
            exp,
            t_out,
            pos,
            R,
            posterior,
            rest_rows(t_out, pos, R, jig),
            rest_variance(jig),
            settings.uncertainty,
        )
    if posterior is not None:
        params = posterior
    else:
        cams = {n: c.calibration.camera_matrix for n, c in exp.rig.cameras.items()}
        params = ParameterCovariance.from_priors(exp.priors, [int(i) for i in room.ids], cams)
    # The priors (posterior None) are checked against the residuals; a posterior is not shrunk.
    u = row_uncertainty(
        frames, exp, t_out, pos, R, posterior, settings.uncertainty, pool, settings.jobs
    )
    traj = Trajectory(
        t_out,
        pos,
        R,
        {**measurement_quality(meas, t_out), **total_sigma(sig, u, settings.uncertainty)},
    )
    return TrackResult(traj, refinement, params, offsets if any(offsets.values()) else {})


def _apply_jig(
    exp: Experiment,
    given: Experiment,
    t_out: np.ndarray,
    pos: np.ndarray,
    R: np.ndarray,
    refinement: Refinement | None,
) -> tuple[Experiment, np.ndarray, np.ndarray, Refinement | None]:
    """The rig's gauge from the rest on the jig (annotator.core.jig): every pose, the rig and the
    map corrected; the refinement's experiment and report say so. ``given``: the experiment as
    written (which markers were surveyed)."""
    jig = exp.priors.jig
    assert jig is not None
    c = jig_correction(t_out, pos, R, jig)
    if c is None:
        log.warning(
            "jig: no pose between %.2f and %.2f s (the trajectory's times): rig kept as measured",
            jig.start,
            jig.end,
        )
        return exp, pos, R, refinement
    for problem in c.problems():
        log.warning("jig: %s", problem)
    seen = (
        refinement.report["markers_seen"] if refinement is not None else list(given.markers.markers)
    )
    pr = exp.priors
    surveyed = [m for m in seen if m in given.markers.markers and pr.marker(m).known]
    exp, pos, R, record = correct_experiment(
        exp, pos, R, c, datum_variance([pr.marker(m).sigma_m for m in surveyed])
    )
    if refinement is not None:
        refinement.report["jig"] = record
        refinement = dataclasses.replace(refinement, experiment=exp)
    return exp, pos, R, refinement


def track(
    exp: Experiment, settings: TrackSettings | None = None, progress: Progress | None = None
) -> TrackResult:
    """Track the bundle over the experiment's videos (with the self-calibration's record)."""
    settings = settings or TrackSettings()
    if settings.method not in ("rig", "paper"):
        raise ValueError(f"unknown method {settings.method!r}")
    if settings.refine not in ("none", "map", "all"):
        raise ValueError(f"unknown refine mode {settings.refine!r}")
    with _worker_pool(settings) as pool:
        return frames_to_result(_all_videos(exp, settings, progress, pool), exp, settings, pool)


def track_experiment(
    exp: Experiment, settings: TrackSettings | None = None, progress: Progress | None = None
) -> Trajectory:
    """Trajectory of the bundle (R_world_bundle, beacon position) over the experiment's videos."""
    return track(exp, settings, progress).trajectory


# --- `annotator run`: track -> sync -> label --------------------------------------------------
# Stage order of a full run. Sync needs the per-frame marker counts (and the slate's frames), so
# in `sync.mode: auto` and `slate` each video is first processed on its own PTS clock, then its frame times are mapped onto the RSSI
# clock before the cameras are combined (the joint solve pairs frames by wall time).


@dataclass(frozen=True, slots=True)
class RunSettings:
    track: TrackSettings = field(default_factory=TrackSettings)
    max_gap: float = 0.5  # s: a reading between poses further apart than this stays unlabelled
    beacon: str | None = None  # the bundle's beacon; default: sync.beacon, else the most heard one
    # Receiver mode: label every reading taken by this sensor on the bundle (default: the
    # experiment's `receiver:`); excludes `beacon`.
    receiver: str | None = None


@dataclass(frozen=True, eq=False)
class RunResult:
    """A full run; the command layer writes it (annotator.commands.run.write_run_outputs)."""

    trajectory: Trajectory
    sync: SyncResult
    labels: Labels  # one per reading of `rssi`
    rssi: RssiTable  # the readings labelled: of the bundle's beacon, or taken by its receiver
    report: Report  # report.json's content, without the names of the files written
    refinement: Refinement | None = (
        None  # what the self-calibration did (None: --refine none, paper)
    )
    params: ParameterCovariance | None = None  # uncertainty of the map, rig and lenses tracked with


def frames_to_trajectory(
    frames: list[CameraFrames],
    exp: Experiment,
    settings: TrackSettings,
    pool: ProcessPoolExecutor | None = None,
    params: ParameterCovariance | None = None,
) -> Trajectory:
    """Stage 2 of tracking on frames whose times are already wall-clock (joint solves in ``pool``);
    ``params`` as in ``_track_rig``."""
    return frames_to_result(frames, exp, settings, pool, params).trajectory


def frames_to_result(
    frames: list[CameraFrames],
    exp: Experiment,
    settings: TrackSettings,
    pool: ProcessPoolExecutor | None = None,
    params: ParameterCovariance | None = None,
) -> TrackResult:
    """`frames_to_trajectory` with the self-calibration's record."""
    if not any(len(cf.t) for cf in frames):
        raise NoDataError(f"{exp.path}: the videos hold no frames")
    if settings.method == "paper":
        return TrackResult(track_paper(frames, settings))
    t_out = np.unique(np.concatenate([cf.t for cf in frames]))
    return _track_rig(frames, exp, settings, t_out, pool, params)


def run_experiment(
    exp: Experiment,
    settings: RunSettings | None = None,
    progress: Progress | None = None,
    frames: list[CameraFrames] | None = None,
) -> RunResult:
    """Everything `annotator run` computes: track, synchronise with the RSSI log, label every
    reading of the bundle's beacon (beacon mode) or every reading its receiver took (receiver
    mode). Writes nothing (see annotator.commands.run.write_run_outputs). ``frames``: every
    video already decoded and detected on its own clock (``video_start`` 0; e.g. in chunks on a
    cluster, annotator.dataset.runs); None decodes them here."""
    from dataclasses import replace

    from annotator.core.labeling import label_readings
    from annotator.core.sync import cover_intervals, manual_sync
    from annotator.errors import ConfigError
    from annotator.io.outputs import build_report
    from annotator.io.rssi import bundle_beacon, load_rssi, receiver_readings

    settings = settings or RunSettings()
    track = settings.track
    if exp.rssi is None:
        raise ConfigError(f"{exp.path}: no 'rssi:' entry; annotator run needs the RSSI recording")
    receiver = settings.receiver or exp.receiver
    asked_beacon = settings.beacon or exp.sync.beacon
    if receiver is not None and asked_beacon is not None:
        raise ConfigError(
            f"receiver {receiver} and beacon {asked_beacon} both given: receiver mode labels the "
            "receiver's readings of every beacon, beacon mode one beacon's readings; choose one"
        )
    everything = load_rssi(exp.rssi)
    if receiver is not None:
        # Receiver mode: the readings the bundle's receiver took, of any beacon. Hands over the
        # bundle dim every beacon at once, so the cover event pools over beacons.
        table = receiver_readings(everything, receiver)
        subject, pooled_by, antenna = f"receiver {receiver}", table.beacon, "receiver"
        beacon = None
    else:
        beacon = bundle_beacon(everything, asked_beacon)
        table = everything.select(everything.beacon == beacon)
        subject, pooled_by, antenna = f"beacon {beacon}", table.sensor, "beacon"

    if exp.sync_mode in ("auto", "slate"):
        from annotator.sync_stage import sync_frames

        if frames is None:
            with _worker_pool(track) as pool:
                frames = _all_videos(
                    replace(exp, video_start={n: 0.0 for n in exp.videos}), track, progress, pool
                )
        frames, sync = sync_frames(exp, frames, table, pooled_by, subject, progress)
    else:
        sync = manual_sync(exp.video_start or {})
        if frames is None:
            with _worker_pool(track) as pool:
                frames = _all_videos(exp, track, progress, pool)
        else:
            starts = exp.video_start or {}
            frames = [replace(cf, t=cf.t + starts.get(cf.camera, 0.0)) for cf in frames]
    if sync.slates and set(sync.slates) == set(sync.clocks):
        # Each video read the slate on its own: its clock is free against the others'.
        track = replace(track, clock_sigma_s=track.clock_sigma_s or CLOCK_SIGMA_S)
    with _worker_pool(track) as pool:
        result = frames_to_result(frames, exp, track, pool)
    traj = result.trajectory
    if result.clock_s:
        from annotator.sync_stage import clock_shift

        sync = clock_shift(sync, result.clock_s)
    if sync.slates and result.refinement is not None:
        from annotator.sync_stage import readout_shift

        refined = result.refinement.experiment.rig.cameras
        sync, traj = readout_shift(
            sync,
            {n: c.calibration.readout_s for n, c in exp.rig.cameras.items()},
            {n: c.calibration.readout_s for n, c in refined.items()},
            traj,
        )

    # Readings while hands covered the bundle carry the hands' attenuation: never labelled. Each
    # reading gets the pose of the antenna that took part in it (the beacon's or the receiver's).
    labels = label_readings(
        traj.at_point(exp.rig.antenna(antenna)),
        table.t_ns,
        max_gap=settings.max_gap,
        exclude=cover_intervals(sync.rssi_events),
        time_sigma=sync_time_sigma(sync.clocks, table.t_seconds()),
    )
    report = build_report(
        experiment=exp.path,
        sync=sync,
        beacon=beacon,
        receiver=receiver,
        antenna=exp.rig.antenna(antenna),
        readings_total=len(everything),
        table=table,
        labels=labels,
        traj_t=traj.t,
        traj_valid=traj.valid,
        max_gap=settings.max_gap,
        method=track.method,
    )
    return RunResult(traj, sync, labels, table, report, result.refinement, result.params)
