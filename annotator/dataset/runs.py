"""Annotating a campaign's runs on a Dask cluster, each at most once per set of inputs.

A run's digest covers every byte `annotator run` reads for it (experiment.yaml, rig,
calibrations, marker map, videos, RSSI files) and the suite's version; its results live in the
cache under that digest, so a second build with nothing changed annotates nothing.

A run is a small graph: each video is cut into chunks of ``chunk_s`` seconds (fixed by the
campaign, so the result never depends on the cluster), each chunk's frames are decoded,
detected and solved by one task (after a few warm-up frames, so it starts as the whole video
would), and one task merges the chunks and does the rest of `annotator run` (sync, the joint
solve and self-calibration, the smoother, the labels). That last task writes into a folder of
its own and renames it into place when complete: a worker lost mid-run (Dask retries the task)
leaves no half-written results.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from annotator.dataset.campaign import RunSpec

if TYPE_CHECKING:
    from annotator.core.tracking import CameraFrames

log = logging.getLogger(__name__)

PROGRESS_TOPIC = "bgt-dataset-progress"
CHUNK = 1 << 20
CHUNK_S = 60.0  # seconds of video per detection task
WARMUP_FRAMES = 10  # solved before a chunk's first frame and dropped


def suite_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ble-groundtruth")
    except PackageNotFoundError:
        return "unknown"


def run_inputs(spec: RunSpec) -> list[Path]:
    """Every file `annotator run` reads for this run, in a fixed order."""
    from annotator.io.experiment import load_experiment
    from bgt_core import safe_yaml

    exp = load_experiment(spec.experiment)
    doc = safe_yaml.load_file(spec.experiment)
    files = [spec.experiment]
    markers = doc.get("markers", {}) if isinstance(doc, dict) else {}
    if isinstance(markers, dict) and isinstance(markers.get("file"), str):
        files.append(spec.experiment.parent / markers["file"])
    if exp.rig.source:
        files.append(Path(exp.rig.source))
    files += [Path(c.calibration.source) for c in exp.rig.cameras.values() if c.calibration.source]
    files += [exp.videos[name] for name in sorted(exp.videos)]
    if exp.rssi is not None:
        rssi = Path(exp.rssi)
        files += sorted(p for p in rssi.rglob("*") if p.is_file()) if rssi.is_dir() else [rssi]
    seen: set[Path] = set()
    out = []
    for f in files:
        r = f.resolve()
        if r not in seen and r.is_file():
            seen.add(r)
            out.append(r)
    return out


def run_digest(spec: RunSpec, chunk_s: float = CHUNK_S) -> str:
    """SHA-256 over the suite's version, the chunk length (the chunks' first frames start from
    their warm-up, not the whole video's past) and each input's name (relative to the
    experiment's folder where it lies below it) and bytes."""
    h = hashlib.sha256(f"ble-groundtruth {suite_version()} chunk {chunk_s!r}\n".encode())
    base = spec.experiment.parent.resolve()
    for f in run_inputs(spec):
        name = str(f.relative_to(base)) if f.is_relative_to(base) else f.name
        h.update(f"{name}\n".encode())
        with f.open("rb") as fh:
            while chunk := fh.read(CHUNK):
                h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class RunDone:
    name: str
    digest: str
    results: Path  # the cached `annotator run` output folder
    cached: bool  # found in the cache: no annotation this build


def _report(name: str, stage: str, done: int, total: int) -> None:
    """Progress from inside a Dask task to the client (a no-op outside a worker)."""
    try:
        from distributed import get_worker

        get_worker().log_event(
            PROGRESS_TOPIC, {"run": name, "stage": stage, "done": done, "total": total}
        )
    except (ImportError, ValueError):
        pass


def chunk_ranges(frame_count: int, fps: float, chunk_s: float) -> list[tuple[int, int | None]]:
    """[first, stop) frame ranges of ``chunk_s`` seconds; the last one runs to the end (a
    container's frame count may be approximate)."""
    step = max(1, int(round(chunk_s * max(fps, 1.0))))
    starts = list(range(0, max(frame_count, 1), step))
    return [(a, b) for a, b in zip(starts, [*starts[1:], None], strict=True)]


def detect_chunk(
    experiment: str, camera: str, first: int, stop: int | None, warmup: int
) -> CameraFrames:
    """One task: frames [first, stop) of one camera's video, decoded, detected and solved on the
    video's own clock."""
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import TrackSettings, process_video

    exp = load_experiment(experiment)
    return process_video(
        exp.videos[camera],
        exp.rig.cameras[camera],
        exp.markers,
        0.0,
        TrackSettings(jobs=1),
        frames=(first, stop),
        warmup=warmup,
    )


def merge_chunks(chunks: list[CameraFrames]) -> CameraFrames:
    """One camera's chunks, in order, as if the video had been processed whole."""
    import numpy as np

    t = np.concatenate([c.t for c in chunks])
    interval = float(np.median(np.diff(t))) if len(t) > 1 else chunks[0].frame_interval
    return replace(
        chunks[0],
        t=t,
        detections=[d for c in chunks for d in c.detections],
        poses=[p for c in chunks for p in c.poses],
        marker_poses=[m for c in chunks for m in c.marker_poses],
        frame_interval=interval,
    )


def finish_run(name: str, experiment: str, dest: str, *chunks: CameraFrames) -> str:
    """One task: the chunks of every camera merged, the rest of `annotator run`, its outputs
    written beside ``dest`` and renamed into place."""
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment

    final = Path(dest)
    if (final / "report.json").is_file():
        return dest  # a retried task whose first attempt finished
    exp = load_experiment(experiment)
    frames = [merge_chunks([c for c in chunks if c.camera == cam]) for cam in exp.videos]
    result = run_experiment(
        exp,
        RunSettings(track=TrackSettings(jobs=1)),
        lambda stage, done, total: _report(name, stage, done, total),
        frames=frames,
    )
    tmp = final.with_name(f"{final.name}.part-{uuid.uuid4().hex[:8]}")
    write_run_outputs(tmp, exp, result, plots=True)
    try:
        tmp.rename(final)
    except OSError:
        if not (final / "report.json").is_file():
            raise
        shutil.rmtree(tmp, ignore_errors=True)  # another attempt got there first
    return dest


def submit_run(
    client: Any,
    spec: RunSpec,
    digest: str,
    folder: Path,
    chunk_s: float,
    on_chunk: Callable[[int], None] | None = None,
    finish: Callable[..., str] = finish_run,
) -> Any:
    """The run's graph on ``client``: one detection task per video chunk, then its finish task
    (``finish``: `finish_run`, or a test's wrapper of it). Returns the finish task's future."""
    from annotator.io.experiment import load_experiment
    from annotator.io.video import video_info

    exp = load_experiment(spec.experiment)
    chunks = []
    for cam in exp.videos:
        info = video_info(exp.videos[cam])
        for i, (first, stop) in enumerate(chunk_ranges(info.frame_count, info.fps, chunk_s)):
            fut = client.submit(
                detect_chunk,
                str(spec.experiment),
                cam,
                first,
                stop,
                WARMUP_FRAMES if first else 0,
                key=f"detect-{spec.name}-{cam}-{i}-{digest[:12]}",
                pure=False,
                retries=2,
            )
            chunks.append(fut)
    if on_chunk is not None:
        total = len(chunks)
        for fut in chunks:
            fut.add_done_callback(lambda _f: on_chunk(total))
    return client.submit(
        finish,
        spec.name,
        str(spec.experiment),
        str(folder),
        *chunks,
        key=f"finish-{spec.name}-{digest[:12]}",
        pure=False,
        retries=2,
    )


def annotate_runs(
    runs: tuple[RunSpec, ...],
    cache: Path,
    client: Any,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    on_done: Callable[[RunDone], None] | None = None,
    *,
    chunk_s: float = CHUNK_S,
    finish: Callable[..., str] = finish_run,
) -> list[RunDone]:
    """Every run's results, from the cache or annotated as tasks on ``client`` (a
    ``distributed.Client``; unused when every run is cached); in the campaign's order."""
    from distributed import as_completed

    done: dict[str, RunDone] = {}
    futures = {}
    for spec in runs:
        digest = run_digest(spec, chunk_s)
        folder = cache / "runs" / spec.name / digest[:16]
        for stale in folder.parent.glob(f"{folder.name}.part-*"):
            shutil.rmtree(stale, ignore_errors=True)  # a build or worker that died mid-run
        if (folder / "report.json").is_file():
            done[spec.name] = RunDone(spec.name, digest, folder, True)
            if on_done is not None:
                on_done(done[spec.name])
            continue
        folder.parent.mkdir(parents=True, exist_ok=True)
        on_chunk = None
        if on_progress is not None:
            on_chunk = _chunk_counter(spec.name, on_progress)
        fut = submit_run(client, spec, digest, folder, chunk_s, on_chunk, finish)
        futures[fut] = (spec, digest, folder)
    if futures and on_progress is not None:
        client.subscribe_topic(PROGRESS_TOPIC, lambda event: on_progress(event[1]))
    try:
        for fut in as_completed(list(futures)) if futures else ():
            spec, digest, folder = futures[fut]
            fut.result()  # a run that failed every retry: its error, one line upstream
            done[spec.name] = RunDone(spec.name, digest, folder, False)
            if on_done is not None:
                on_done(done[spec.name])
    finally:
        if futures and on_progress is not None:
            client.unsubscribe_topic(PROGRESS_TOPIC)
    return [done[spec.name] for spec in runs]


def _chunk_counter(
    name: str, on_progress: Callable[[dict[str, Any]], None]
) -> Callable[[int], None]:
    state = {"done": 0}

    def one_more(total: int) -> None:
        state["done"] += 1
        on_progress({"run": name, "stage": "video chunks", "done": state["done"], "total": total})

    return one_more
