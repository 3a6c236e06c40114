"""Annotating a campaign's runs on a Dask cluster, each at most once per set of inputs.

A run's digest covers every byte `annotator run` reads for it (experiment.yaml, rig,
calibrations, marker map, videos, RSSI files) and the suite's version; its results live in the
cache under that digest, so a second build with nothing changed annotates nothing. A run is one
task: it writes into a folder of its own and renames it into place when complete, so a worker
lost mid-run (Dask retries the task) leaves no half-written results.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.dataset.campaign import RunSpec

log = logging.getLogger(__name__)

PROGRESS_TOPIC = "bgt-dataset-progress"
CHUNK = 1 << 20


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


def run_digest(spec: RunSpec) -> str:
    """SHA-256 over the suite's version and each input's name (relative to the experiment's
    folder where it lies below it) and bytes."""
    h = hashlib.sha256(f"ble-groundtruth {suite_version()}\n".encode())
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


def annotate_run(name: str, experiment: str, dest: str) -> str:
    """One Dask task: `annotator run` of ``experiment`` into ``dest`` (written beside it, then
    renamed into place). Single-process: the cluster's workers are the parallelism."""
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment

    final = Path(dest)
    if (final / "report.json").is_file():
        return dest  # a retried task whose first attempt finished
    tmp = final.with_name(f"{final.name}.part-{uuid.uuid4().hex[:8]}")
    exp = load_experiment(experiment)
    result = run_experiment(
        exp,
        RunSettings(track=TrackSettings(jobs=1)),
        lambda stage, done, total: _report(name, stage, done, total),
    )
    write_run_outputs(tmp, exp, result, plots=True)
    try:
        tmp.rename(final)
    except OSError:
        if not (final / "report.json").is_file():
            raise
        shutil.rmtree(tmp, ignore_errors=True)  # another attempt got there first
    return dest


def annotate_runs(
    runs: tuple[RunSpec, ...],
    cache: Path,
    client: Any,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    on_done: Callable[[RunDone], None] | None = None,
) -> list[RunDone]:
    """Every run's results, from the cache or annotated as tasks on ``client`` (a
    ``distributed.Client``); returned in the campaign's order."""
    from distributed import as_completed

    done: dict[str, RunDone] = {}
    futures = {}
    for spec in runs:
        digest = run_digest(spec)
        folder = cache / "runs" / spec.name / digest[:16]
        for stale in folder.parent.glob(f"{folder.name}.part-*"):
            shutil.rmtree(stale, ignore_errors=True)  # a build or worker that died mid-run
        if (folder / "report.json").is_file():
            done[spec.name] = RunDone(spec.name, digest, folder, True)
            if on_done is not None:
                on_done(done[spec.name])
            continue
        folder.parent.mkdir(parents=True, exist_ok=True)
        fut = client.submit(
            annotate_run,
            spec.name,
            str(spec.experiment),
            str(folder),
            key=f"annotate-{spec.name}-{digest[:12]}",
            pure=False,
            retries=2,
        )
        futures[fut] = (spec, digest, folder)
    if futures and on_progress is not None:
        client.subscribe_topic(PROGRESS_TOPIC, lambda event: on_progress(event[1]))
    try:
        for fut in as_completed(list(futures)):
            spec, digest, folder = futures[fut]
            fut.result()  # a run that failed every retry: its error, one line upstream
            done[spec.name] = RunDone(spec.name, digest, folder, False)
            if on_done is not None:
                on_done(done[spec.name])
    finally:
        if futures and on_progress is not None:
            client.unsubscribe_topic(PROGRESS_TOPIC)
    return [done[spec.name] for spec in runs]
