"""Render a whole simulated experiment: two rig videos along a known trajectory plus the files
`annotator track` reads (experiment.yaml, rig.yaml, calibrations, marker map) and truth.csv."""

from __future__ import annotations

import logging
import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.rolling_shutter import row_delay
from annotator.render.camera import (
    RIG_EXTRINSICS,
    CameraModel,
    camera_pose,
    default_cameras,
    rig_yaml,
    write_calibration,
)
from annotator.render.effects import Imaging, flicker_gain
from annotator.render.errors import (
    FileErrors,
    perturb_cameras,
    perturb_markers,
    perturb_rig,
    perturbation_record,
    surveyed_subset,
)
from annotator.render.frames import (
    CameraJob,
    Progress,
    render_camera,
    rolling_bands,
    row_time_offsets,
)
from annotator.render.textures import aruco_dictionary
from annotator.render.trajectory import PolylineTrajectory
from bgt_core.formats.markers import MarkerPose, format_dat, read_marker_map
from bgt_core.sites import site_dir

log = logging.getLogger(__name__)

PoseAt = Callable[[np.ndarray], tuple[np.ndarray, Rotation]]
TRUTH_HEADER = "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33"


@dataclass(frozen=True)
class RenderResult:
    out_dir: Path
    experiment: Path
    truth: Path
    videos: dict[str, Path]
    frames: dict[str, int]


def _camera_poses(pose_at: PoseAt, times: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    pos, rot = pose_at(times)
    r_wc, c_w = camera_pose(rot, np.asarray(pos, float), name)
    return r_wc.as_matrix().reshape(-1, 3, 3), np.asarray(c_w).reshape(-1, 3)


def frame_times(start: float, t_end: float, fps: float) -> np.ndarray:
    """Wall times of the frames of a constant-rate video starting at `start`, all before t_end."""
    n = int(np.floor((t_end - start) * fps + 1e-9))
    return start + np.arange(max(n, 0)) / fps


def format_truth(times: np.ndarray, pos: np.ndarray, rot: Rotation) -> str:
    mats = rot.as_matrix().reshape(-1, 9)
    lines = [TRUTH_HEADER]
    for t, p, m in zip(times, pos, mats, strict=True):
        lines.append(
            f"{t:.6f}," + ",".join(f"{v:.9f}" for v in p) + "," + ",".join(f"{v:.12f}" for v in m)
        )
    return "\n".join(lines) + "\n"


def experiment_yaml(
    video_start: dict[str, float],
    dictionary: str,
    length: float,
    media: str = "",
    rssi_dir: str = "rssi",
) -> str:
    """experiment.yaml of a render; `media` is the folder of the videos and of `rssi_dir` (the
    RSSI readings' folder) relative to it."""
    starts = ", ".join(f"{k}: {v!r}" for k, v in video_start.items())
    return (
        "# Rendered by `annotator simulate`: a synthetic experiment with known truth (truth.csv).\n"
        f"markers: {{file: marker_positions.dat, dictionary: {dictionary}, length: {length!r}}}\n"
        "rig: rig.yaml\n"
        f"videos: {{front: {media}front.mp4, back: {media}back.mp4}}\n"
        f"rssi: {media}{rssi_dir}\n"
        "sync:\n"
        "  mode: manual\n"
        f"  video_start: {{{starts}}}\n"
    )


def path_yaml(waypoints: Sequence[Sequence[float]]) -> str:
    """The planned path in the YAML `annotator evaluate --path` reads."""
    pts = ", ".join(f"[{float(x)!r}, {float(y)!r}]" for x, y in waypoints)
    return (
        "# Planned path of this render (room xy, m): `annotator evaluate TRAJ.csv --path path.yaml`.\n"
        f"waypoints: [{pts}]\n"
    )


def write_experiment_files(
    out_dir: str | Path,
    cameras: dict[str, CameraModel],
    markers: dict[int, MarkerPose],
    video_start: dict[str, float],
    *,
    dictionary: str = "DICT_6X6_50",
    marker_length: float = 0.298,
    readout: float = 0.0,
    exposure: float | None = None,
    errors: FileErrors | None = None,
    settings: dict[str, object] | None = None,
    rssi_dir: str = "rssi",
    true_length: float | None = None,
) -> dict[str, object]:
    """Write what the annotator reads (experiment.yaml, rig.yaml, calibrations, marker map, an
    empty `rssi_dir` folder for the readings) with `errors` applied, the exact files under
    true/ (with a true/experiment.yaml that uses the same videos), and perturbation.yaml (true vs written values). `exposure` (s),
    when given, goes into every calibration as the camera's known setting (`exposure_s`). The
    videos are not touched: a render's folder can be given other errors without rendering again.
    `true_length` is the printed side written into true/experiment.yaml (default
    `marker_length`). Returns the perturbation record."""
    out = Path(out_dir)
    errors = errors or FileErrors()
    written_markers = surveyed_subset(
        perturb_markers(markers, errors.survey_m, errors.survey_deg, errors.seed),
        errors.surveyed,
        errors.seed,
    )
    true_rig = {name: RIG_EXTRINSICS[name] for name in cameras}
    written_rig = perturb_rig(true_rig, errors.rig_m, errors.rig_deg, errors.seed)
    written_cams = perturb_cameras(
        cameras, errors.focal_rel, errors.principal_px, errors.distortion, errors.seed
    )
    written_readout = readout if errors.write_readout else 0.0

    (out / "true").mkdir(parents=True, exist_ok=True)
    (out / rssi_dir).mkdir(exist_ok=True)
    exact_length = marker_length if true_length is None else true_length
    for folder, cams, rig, mk, ro, media, length in (
        (out, written_cams, written_rig, written_markers, written_readout, "", marker_length),
        (out / "true", cameras, true_rig, markers, readout, "../", exact_length),
    ):
        for name, cam in cams.items():
            write_calibration(str(folder / f"{name}.yaml"), cam, ro, exposure)
        (folder / "rig.yaml").write_text(rig_yaml(rig), encoding="utf-8")
        (folder / "marker_positions.dat").write_text(format_dat(mk), encoding="utf-8")
        (folder / "experiment.yaml").write_text(
            experiment_yaml(video_start, dictionary, length, media, rssi_dir),
            encoding="utf-8",
        )
    record = perturbation_record(
        {**(settings or {}), **asdict(errors), "readout_s": float(readout)},
        markers,
        written_markers,
        cameras,
        written_cams,
        true_rig,
        written_rig,
        readout,
        written_readout,
    )
    from bgt_core.safe_yaml import dump

    text = (
        "# What `annotator simulate` changed in the files handed to the annotator: true vs written\n"
        "# values (offsets are written - true; rotation offsets are rotation vectors, degrees, taking\n"
        "# the true orientation to the written one, world frame for markers, bundle frame for the rig).\n"
    )
    (out / "perturbation.yaml").write_text(text + dump(record, sort_keys=False), encoding="utf-8")
    return record


def printed_scales(
    markers: dict[int, MarkerPose], scale: float, scatter: float, seed: int
) -> dict[int, float] | None:
    """Printed side / nominal length per marker: ``scale`` x (1 + N(0, ``scatter``)), drawn by
    ``seed``; None when every marker is printed exactly."""
    if not (np.isfinite(scale) and 0.5 < scale < 2.0) or not (
        np.isfinite(scatter) and 0 <= scatter < 0.1
    ):
        raise ValueError(
            f"print scale {scale!r} must be in (0.5, 2) and scatter {scatter!r} in [0, 0.1)"
        )
    if scale == 1.0 and scatter == 0.0:
        return None
    rng = np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 9]))
    ids = sorted(markers)
    draws = rng.standard_normal(len(ids))
    return {i: float(scale * (1.0 + scatter * d)) for i, d in zip(ids, draws, strict=True)}


def render_experiment(
    out_dir: str | Path,
    pose_at: PoseAt,
    t_span: tuple[float, float],
    *,
    width: int = 960,
    height: int = 540,
    fps: float = 30.0,
    start_offset: float = 0.41,
    covers: Sequence[tuple[float, float]] = (),
    seed: int = 0,
    noise_sigma: float = 2.0,
    exposure: float = 1 / 120,
    jobs: int = 1,
    marker_file: str | Path | None = None,
    dictionary: str = "DICT_6X6_50",
    marker_length: float = 0.298,
    cameras: dict[str, CameraModel] | None = None,
    lens: str = "mild",
    k1: float | None = None,
    readout: float = 0.0,
    flicker: float = 0.0,
    flicker_hz: float = 100.0,
    errors: FileErrors | None = None,
    progress: Progress | None = None,
    rssi_dir: str = "rssi",
    imaging: Imaging | None = None,
    print_scale: float = 1.0,
    print_scatter: float = 0.0,
    slate: float = 0.0,
    slate_hz: float = 60.0,
) -> RenderResult:
    """Render the rig's two videos along `pose_at` over wall times `t_span` and write the experiment.

    The front video starts at t_span[0], the back one `start_offset` s later; every frame lies
    inside t_span. `covers` are (start, duration) in seconds after t_span[0]: both lenses are
    covered by a hand at the same wall time. A `PolylineTrajectory` also gets its planned path
    written to path.yaml. Returns the paths written.

    The video is always exact: `cameras` (or the `lens` of `default_cameras`, `k1` overriding its
    first coefficient), a rolling shutter whose row v of a frame stamped t is seen at
    t + readout*v/height, and a brightness `flicker` (relative amplitude at `flicker_hz`, seen per
    row). `errors` only change the files written for the annotator (see `write_experiment_files`).
    experiment.yaml's `rssi:` names `rssi_dir`, created empty here.

    What a real capture adds that no file tells: `imaging` (defocus, light, compression) and the
    markers as printed, each `print_scale` x (1 + N(0, `print_scatter`)) times `marker_length`
    (drawn by `seed`), while experiment.yaml says `marker_length`; true/experiment.yaml says
    `marker_length` x `print_scale` and perturbation.yaml lists every printed side.

    `slate` > 0: each camera films the clock slate (`collector slate`, a `slate_hz` screen with a
    seeded refresh phase) for `slate` seconds before t_span[0] and after t_span[1]; the videos
    start and end that much earlier and later, and truth.csv covers t_span only.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker_src = (
        Path(marker_file) if marker_file is not None else site_dir("tetam") / "marker_positions.dat"
    )
    markers = read_marker_map(marker_src)
    aruco_dictionary(dictionary)  # fail early on a bad name
    cams = cameras or default_cameras(width, height, lens, k1)
    if not 0 <= readout < 1 / fps:
        raise ValueError(
            f"readout {readout} s must be between 0 and the frame interval {1 / fps:.4f} s"
        )
    t0, t1 = float(t_span[0]), float(t_span[1])
    if not (0 <= slate <= 10 and 10 <= slate_hz <= 500):
        raise ValueError(
            f"slate {slate} s must be in [0, 10] and its refresh {slate_hz} Hz in [10, 500]"
        )
    starts = {"front": t0 - slate, "back": t0 + start_offset - slate}
    shot = None
    if slate > 0:
        from annotator.render.slate import SlateShot

        rng = np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 18]))
        shot = SlateShot(slate_hz, float(rng.uniform(0, 1 / slate_hz)), seed=seed)
    wall_covers = tuple((t0 + s, d) for s, d in covers)
    errors = errors or FileErrors(seed=seed)
    flicker_phase = float(
        np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 4])).uniform(0, 2 * np.pi)
    )
    scales = printed_scales(markers, print_scale, print_scatter, seed)

    job_list = []
    for idx, name in enumerate(("front", "back")):
        cam = cams[name]
        times = frame_times(starts[name], t1 + slate, fps)
        if not len(times):
            raise ValueError(f"time span {t1 - t0:.3f} s leaves no frames for the {name} camera")
        band_rows = rolling_bands(cam.height, readout)
        # Global shutter: the frame is seen at its stamp; rolling: at its middle row's time.
        mid = float(row_delay((cam.height - 1) / 2, cam.height, readout))
        walk_t = np.clip(times, t0, t1)  # the slate's frames show no room: any pose will do
        r, c = _camera_poses(pose_at, walk_t, name)
        ro, co = _camera_poses(pose_at, walk_t + mid - exposure / 2, name)
        rc, cc = _camera_poses(pose_at, walk_t + mid + exposure / 2, name)
        rb = cb = None
        if band_rows:
            offs = row_time_offsets(band_rows, cam.height, readout)
            rb, cb = _camera_poses(pose_at, (walk_t[:, None] + offs[None, :]).ravel(), name)
            rb, cb = rb.reshape(len(times), len(offs), 3, 3), cb.reshape(len(times), len(offs), 3)
        gains = None
        if flicker > 0:
            row_t = times[:, None] + row_delay(np.arange(cam.height), cam.height, readout)[None, :]
            gains = flicker_gain(row_t, flicker, flicker_hz, flicker_phase).astype(np.float32)
        job_list.append(
            CameraJob(
                name,
                cam,
                str(out / f"{name}.mp4"),
                fps,
                times,
                r,
                c,
                ro,
                co,
                rc,
                cc,
                markers,
                marker_length,
                dictionary,
                wall_covers,
                noise_sigma,
                seed * 1000 + idx,
                band_rows,
                rb,
                cb,
                gains,
                imaging or Imaging(),
                scales,
                shot,
                (t0, t1) if shot is not None else (-np.inf, np.inf),
                readout,
                exposure,
            )
        )

    settings: dict[str, object] = {
        "lens": lens if cameras is None else "custom",
        "k1": k1,
        "exposure_s": float(exposure),
        "flicker": float(flicker),
        "flicker_hz": float(flicker_hz),
        "flicker_phase_rad": flicker_phase,
        "render_seed": int(seed),
        **({"imaging": asdict(imaging)} if imaging is not None and imaging.active else {}),
        **(
            {"slate_s": float(slate), "slate_hz": float(slate_hz), "slate_phase_s": shot.phase}
            if shot is not None
            else {}
        ),
    }
    if scales is not None:
        settings["print_scale"] = float(print_scale)
        settings["print_scatter"] = float(print_scatter)
        settings["printed_length_m"] = {
            int(k): round(marker_length * v, 6) for k, v in sorted(scales.items())
        }
    write_experiment_files(
        out,
        cams,
        markers,
        starts,
        dictionary=dictionary,
        marker_length=marker_length,
        readout=readout,
        exposure=exposure,
        errors=errors,
        settings=settings,
        rssi_dir=rssi_dir,
        true_length=round(marker_length * print_scale, 9),
    )

    all_t = np.unique(np.concatenate([j.times for j in job_list]))
    all_t = all_t[(all_t >= t0) & (all_t <= t1)]
    pos, rot = pose_at(all_t)
    (out / "truth.csv").write_text(
        format_truth(all_t, np.asarray(pos, float), rot), encoding="utf-8"
    )
    if isinstance(pose_at, PolylineTrajectory):
        (out / "path.yaml").write_text(path_yaml(pose_at.waypoints), encoding="utf-8")
    else:  # a path.yaml left by an earlier render into the same folder would not belong to this one
        (out / "path.yaml").unlink(missing_ok=True)

    frames = _run_jobs(job_list, jobs, progress)
    log.info("rendered %s into %s", frames, out)
    return RenderResult(
        out,
        out / "experiment.yaml",
        out / "truth.csv",
        {j.name: Path(j.path) for j in job_list},
        frames,
    )


def _run_jobs(job_list: list[CameraJob], jobs: int, progress: Progress | None) -> dict[str, int]:
    if jobs <= 1 or len(job_list) == 1:
        return {j.name: render_camera(j, progress) for j in job_list}
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe with OpenCV's and rich's threads
    with ctx.Manager() as manager:
        queue = manager.Queue()
        with ProcessPoolExecutor(max_workers=min(jobs, len(job_list)), mp_context=ctx) as pool:
            futures = {j.name: pool.submit(render_camera, j, None, queue) for j in job_list}
            pending = set(futures)
            while pending:
                try:
                    name, done, total = queue.get(timeout=0.2)
                    if progress is not None:
                        progress(name, done, total)
                except Exception:  # noqa: BLE001 - queue.Empty from a manager proxy
                    pass
                pending = {n for n in pending if not futures[n].done()}
            return {n: f.result() for n, f in futures.items()}
