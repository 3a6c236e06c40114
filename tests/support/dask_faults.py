"""Faults for Dask tasks: a finish task whose worker process dies the first time it runs (as a
Pi or a workstation lost mid-build would), then runs normally when Dask reschedules it."""

from __future__ import annotations

import os
from pathlib import Path

from annotator.core.tracking import CameraFrames
from annotator.dataset.runs import finish_run


def finish_dying_once(name: str, experiment: str, dest: str, *chunks: CameraFrames) -> str:
    marker = Path(dest).parent / f".died-{name}"
    if not marker.exists():
        marker.write_text("the worker died here once\n")
        # half a run's output on disk, as a worker killed while writing would leave it
        Path(f"{dest}.part-dead").mkdir(parents=True, exist_ok=True)
        (Path(f"{dest}.part-dead") / "trajectory.csv").write_text("t,x\n1,")
        os._exit(1)
    return finish_run(name, experiment, dest, *chunks)
