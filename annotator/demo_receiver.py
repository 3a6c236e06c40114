"""`annotator demo --receiver`: the other direction with no hardware, rendered and scored.

Beacons stand at the tetam site's twelve sensor positions; the bundle carries a receiver (10 cm
above its beacon) that hears them while it walks the demo's loop, with the same hands-cover
events. There is no live capture here: the readings are simulated straight into a collector-style
run (annotator.render.rssi), the walk is rendered as two videos, and `annotator run` in receiver
mode (automatic sync) labels every reading the receiver took, scored against the receiver
antenna's true path.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from annotator.demo import (
    Capture,
    DemoResult,
    DemoSettings,
    Progress,
    bundle_pose_at,
    demo_path,
    prepare_out,
    render,
    score,
    summarize_run,
    write_summary,
)

# Any fixed time works: nothing here runs live.
T0 = 1_700_000_000.0
# Adverts per second of each fixed beacon (the simulated agents of the beacon demo use 10).
RATE_HZ = 10.0


def run_receiver_demo(settings: DemoSettings, progress: Progress | None = None) -> DemoResult:
    """Render, simulate, annotate and score receiver mode; writes OUT/capture (the simulated run),
    OUT/experiment, OUT/results and OUT/demo_summary.json."""
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment
    from annotator.render.rssi import (
        RECEIVER_ANTENNA,
        RECEIVER_MAC,
        add_receiver,
        write_simulated_run,
    )

    out = prepare_out(settings)
    started = time.monotonic()
    path = demo_path(settings.speed_mps)
    run_dir = out / "capture" / "receiver-run"
    simulated = write_simulated_run(
        run_dir,
        bundle_pose_at(path, T0),
        (T0, T0 + settings.duration_s),
        covers=settings.covers(),
        seed=settings.seed,
        rate_hz=RATE_HZ,
        receiver=RECEIVER_MAC,
    )
    exp_path = render(settings, path, T0, run_dir, progress)
    add_receiver(exp_path)
    experiment = load_experiment(exp_path)
    run = run_experiment(experiment, RunSettings(track=TrackSettings(jobs=settings.jobs)), progress)
    results = out / "results"
    report = write_run_outputs(results, experiment, run)
    true_starts = {"front": T0, "back": T0 + settings.start_offset_s}
    antenna = np.asarray(RECEIVER_ANTENNA, dtype=float)
    summary: dict[str, Any] = score(run, path, T0, true_starts, settings.duration_s, antenna)
    summary.update(
        {
            "duration_s": settings.duration_s,
            "t0": T0,
            "receiver": RECEIVER_MAC,
            "receiver_antenna_m": list(RECEIVER_ANTENNA),
            "beacons": list(simulated.beacons),
            "covers": [{"start_s": s, "duration_s": d} for s, d in settings.covers()],
            "capture": {"run_dir": str(run_dir), "readings": simulated.readings},
            "experiment": str(exp_path),
            "results": str(results),
            "plots": [str(results / p) for p in report.get("plots", {}).values()],
            "wall_time_s": time.monotonic() - started,
        }
    )
    capture = Capture(run_dir, T0, summarize_run(run_dir))
    return DemoResult(capture, exp_path, results, summary, write_summary(out, summary))
