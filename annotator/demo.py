"""The end-to-end demo behind `annotator demo`: capture, render, annotate, score, with no hardware.

Owns the demo's scenario (one path, its start time and hands-cover events, shared by the simulated
agents and the renderer), the child processes (collector + three agents) and the scoring against
the known truth. The CLI in annotator/commands/demo.py only prints.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.demo_processes import (
    STARTUP_TIMEOUT_S,
    Children,
    console_script,
    free_port,
    log_tail,
    run_cli,
)
from annotator.errors import DemoError
from bgt_core import safe_yaml
from bgt_core.formats.devices import read_dev
from bgt_core.formats.mbd import iter_rows
from bgt_core.motion import CoverEvent, PathModel
from bgt_core.sites import site_dir

log = logging.getLogger(__name__)

AGENTS = ("pi-1", "pi-2", "pi-3")
SITE = "demo"
# The renderer's hands take this long to close over the lenses (and to open again); the beacon is
# taken as covered from the middle of the closing to the middle of the opening.
COVER_RAMP_S = 0.15
# Radius of the demo path's rounded corners: a relaxed walking turn.
CORNER_RADIUS_M = 1.2

# step(name, done, total) for progress bars; note(text) for one-line messages.
Progress = Callable[[str, int, int], None]
Note = Callable[[str], None]


@dataclass(frozen=True, slots=True)
class DemoSettings:
    out: Path
    duration_s: float = 30.0  # video length; the capture runs a little longer
    start_offset_s: float = 0.35  # the back camera starts this much after the front one
    cover_s: tuple[float, float] = (2.0, 1.5)  # (start after t0, duration) of the first cover
    end_cover: bool = True  # a second cover near the end, for the drift fit
    lead_s: float = 5.0  # t0 is this long after the agents are launched (they need to start up)
    jobs: int = 2
    seed: int = 0
    speed_mps: float = 0.4

    def covers(self) -> list[tuple[float, float]]:
        """(start after t0, duration) of every hands-cover event, as the renderer takes them."""
        out = [self.cover_s]
        second = self.duration_s - 3.0
        if self.end_cover and second - sum(self.cover_s) >= 2.0:
            out.append((second, self.cover_s[1]))
        return out


# --- the scenario ---------------------------------------------------------------------------------

# The demo loop goes round the desk block south of the central corridor, on the site's occupancy
# grid (annotator.core.floor_paths): start in the middle of the bottom side, then these corners.
DEMO_START = (8.8, 4.5)
DEMO_CORNERS = ((11.7, 4.5), (11.7, 9.0), (6.0, 9.0), (6.0, 4.5))
DEMO_MARGIN_M = 0.4  # the planned route keeps this far from desks and walls


def demo_path(speed_mps: float = 0.4) -> PathModel:
    """A rounded loop planned on the tetam occupancy grid, round a desk block and never through
    furniture: true circular corners of radius CORNER_RADIUS_M walked at constant speed, so
    neither the position nor the heading ever changes direction in an instant. Time 0 is in the
    middle of the bottom side."""
    from annotator.core.floor_paths import FloorGrid, plan_route
    from annotator.io.radio_data import site_occupancy

    route = plan_route(
        FloorGrid.from_occupancy(site_occupancy()),
        [DEMO_START, *DEMO_CORNERS],
        margin=DEMO_MARGIN_M,
    )
    # Mid-side points carry the height swing; the corners are rounded by the path model itself.
    plan = [tuple(route[0])]
    for i in range(1, len(route)):
        plan.append(tuple(route[i]))
        if i < len(route) - 1:
            plan.append(tuple((route[i] + route[i + 1]) / 2))
    n = len(plan)
    # Height: one slow swing between about 1.35 and 1.75 m per lap.
    wps = tuple(
        (
            round(float(x), 4),
            round(float(y), 4),
            round(1.55 + 0.2 * math.sin(2 * math.pi * i / n), 4),
        )
        for i, (x, y) in enumerate(plan)
    )
    return PathModel(wps, speed_mps, 0.0, corner_radius=CORNER_RADIUS_M)


def bundle_pose_at(
    path: PathModel, t0: float
) -> Callable[[np.ndarray], tuple[np.ndarray, Rotation]]:
    """pose_at for the renderer: position = the path's, bundle x along the direction of travel
    (horizontal), z up. The heading is the direction of travel averaged over +-0.3 s, so the turn
    rate too builds up gradually where a corner's arc begins (a walker eases into a turn)."""
    window = np.linspace(-0.3, 0.3, 13)

    def pose_at(t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        tau = np.atleast_1d(np.asarray(t, float)) - t0
        pos = np.array([path.position_at(float(s)) for s in tau])
        yaw = np.empty(len(tau))
        for i, s in enumerate(tau):
            d = np.sum([path.direction_at(float(s + w))[:2] for w in window], axis=0)
            yaw[i] = math.atan2(d[1], d[0])
        return pos, Rotation.from_euler("z", yaw[:, None])

    return pose_at


def rssi_events(settings: DemoSettings) -> list[CoverEvent]:
    """The cover events as the simulated agents apply them (hands over the beacon)."""
    return [
        CoverEvent(s + COVER_RAMP_S / 2, d, attenuation_db=20.0, drop_prob=0.6)
        for s, d in settings.covers()
    ]


def split_sensors(n_agents: int = len(AGENTS)) -> list[list[str]]:
    """The tetam sensors (MACs) dealt out to the agents in .dev order, in equal shares."""
    macs = list(read_dev(site_dir("tetam") / "tetam.dev").dongles)
    share = math.ceil(len(macs) / n_agents)
    return [macs[i * share : (i + 1) * share] for i in range(n_agents)]


def agent_config(
    agent_id: str,
    endpoint: str,
    sensors: list[str],
    path: PathModel,
    t0: float,
    events: list[CoverEvent],
    seed: int,
) -> dict[str, Any]:
    """agent.yaml contents for one simulated agent."""
    return {
        "agent_id": agent_id,
        "site": SITE,
        "connect": [endpoint],
        "backend": "simulated",
        "status_interval_s": 60,
        "simulated": {
            "seed": seed,
            "site": "tetam",
            "sensors": sensors,
            "path": path.to_dict(),
            "t0": t0,
            "events": [e.to_dict() for e in events],
            "rate_hz": 10,
        },
    }


# --- the capture ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorFile:
    sensor: str
    path: Path
    rows: int
    first_ns: int | None
    last_ns: int | None


@dataclass(frozen=True)
class Capture:
    run_dir: Path
    t0: float
    files: list[SensorFile]


def summarize_run(run_dir: Path) -> list[SensorFile]:
    """Per .mbd file of a run (rssi/<agent>/<sensor>.mbd): rows and first/last timestamp."""
    out = []
    for p in sorted((run_dir / "rssi").glob("*/*.mbd")):
        n, first, last = 0, None, None
        for row in iter_rows(p):
            n += 1
            first = row.t_ns if first is None else min(first, row.t_ns)
            last = row.t_ns if last is None else max(last, row.t_ns)
        out.append(SensorFile(p.stem, p, n, first, last))
    return out


def capture(
    settings: DemoSettings,
    path: PathModel,
    progress: Progress | None = None,
    note: Note | None = None,
    clock: Callable[[], float] = time.time,
) -> Capture:
    """Collector + three simulated agents over loopback Zenoh: one run from before t0 until after
    t0 + duration. Every child is stopped before this returns or raises."""
    note = note or (lambda _: None)
    cap_dir = settings.out / "capture"
    cfg_dir = settings.out / "config"
    cfg_dir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    collector = console_script("collector", "collector.cli")
    agent = console_script("sensor-agent", "sensor_agent.cli")
    control = ["--connect", endpoint, "--site", SITE]

    with Children(settings.out / "logs") as kids:
        server = kids.spawn(
            "collector",
            [*collector, "serve", "--data-dir", str(cap_dir), "--listen", endpoint, "--site", SITE],
        )
        note(f"collector serving on {endpoint}, data in {cap_dir}")
        note(
            f"watch it live in a browser (the web extra): collector web --connect {endpoint} "
            "--plan tetam, then open http://127.0.0.1:8080/"
        )
        # `start` fails with "no collector answered" until the router is up: retry to a deadline.
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while True:
            kids.check_alive()
            try:
                run_id = run_cli(
                    [*collector, "start", "--name", "demo", *control], "collector start"
                )
                break
            except DemoError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        note(f"run {run_id} started")

        t0 = math.floor(clock()) + settings.lead_s
        events = rssi_events(settings)
        for i, (agent_id, sensors) in enumerate(zip(AGENTS, split_sensors(), strict=True)):
            cfg = agent_config(
                agent_id, endpoint, sensors, path, t0, events, settings.seed * 10 + i
            )
            cfg_path = cfg_dir / f"{agent_id}.yaml"
            cfg_path.write_text(safe_yaml.dump(cfg, sort_keys=False), encoding="utf-8")
            kids.spawn(agent_id, [*agent, "run", "--config", str(cfg_path)])
        note(f"agents {', '.join(AGENTS)} started; path time 0 (t0) = {t0:.0f}")

        # Record from before t0 until a little after the last video frame.
        t_end = t0 + settings.duration_s + 1.0
        t_start = clock()
        while (now := clock()) < t_end:
            kids.check_alive()
            if progress is not None:
                progress("capture", int(min(now, t_end) - t_start), int(math.ceil(t_end - t_start)))
            time.sleep(min(0.25, max(t_end - now, 0.0)))
        if progress is not None:
            progress("capture", int(math.ceil(t_end - t_start)), int(math.ceil(t_end - t_start)))
        kids.check_alive()
        run_dir = Path(
            run_cli([*collector, "stop", *control], "collector stop").splitlines()[-1].strip()
        )
        for child in [c for c in kids.children if c is not server]:
            rc = kids.stop(child)
            if rc not in (0, -signal.SIGINT):
                raise DemoError(
                    f"{child.name} exited with code {rc} when stopped: {log_tail(child.log_path)}"
                )
        kids.stop(server)

    if not run_dir.is_absolute():
        run_dir = Path.cwd() / run_dir
    if not (run_dir / "run.yaml").is_file():
        raise DemoError(f"collector stop named {run_dir}, which holds no run.yaml")
    files = summarize_run(run_dir)
    if not files:
        raise DemoError(f"the capture wrote no .mbd files into {run_dir / 'rssi'}")
    first_cover_ns = round((t0 + settings.cover_s[0]) * 1e9)
    late = [f.sensor for f in files if f.first_ns is None or f.first_ns > first_cover_ns]
    if late:
        # The agents skip what they missed: a late one cannot contribute to the first event.
        note(
            f"warning: {len(late)} sensor(s) have no reading before the first cover event "
            f"({', '.join(late)}); their agent started late (a busy machine?)"
        )
    return Capture(run_dir, t0, files)


# --- render, annotate, score ------------------------------------------------------------------------


def render(
    settings: DemoSettings,
    path: PathModel,
    t0: float,
    run_dir: Path,
    progress: Progress | None = None,
) -> Path:
    """Two-camera video of the same walk; experiment.yaml with `sync: auto` and `rssi:` the run."""
    from annotator.render import render_experiment

    exp_dir = settings.out / "experiment"
    result = render_experiment(
        exp_dir,
        bundle_pose_at(path, t0),
        (t0, t0 + settings.duration_s),
        width=960,
        height=540,
        fps=30.0,
        start_offset=settings.start_offset_s,
        covers=settings.covers(),
        seed=settings.seed,
        jobs=settings.jobs,
        progress=progress,
    )
    with contextlib.suppress(OSError):
        (exp_dir / "rssi").rmdir()  # the renderer's empty placeholder; the RSSI is the run
    doc = {
        "markers": {"file": "marker_positions.dat", "dictionary": "DICT_6X6_50", "length": 0.298},
        "rig": "rig.yaml",
        "videos": {name: p.name for name, p in result.videos.items()},
        "rssi": os.path.relpath(run_dir, exp_dir),
        # No video_start: the annotator has to find each camera's start from the cover events.
        "sync": {"mode": "auto"},
    }
    header = "# Written by `annotator demo`: the simulated capture's run and the rendered videos.\n"
    result.experiment.write_text(header + safe_yaml.dump(doc, sort_keys=False), encoding="utf-8")
    return result.experiment


def score(
    run: Any,
    path: PathModel,
    t0: float,
    true_starts: dict[str, float],
    duration_s: float | None = None,
    antenna: np.ndarray | None = None,
) -> dict[str, Any]:
    """The annotation against the truth: position error of every labelled reading (truth = the
    path at that reading's own timestamp, moved to ``antenna`` in the bundle frame when given),
    coverage and each camera's sync error: at its first frame, and (given ``duration_s``) at its
    last, which differs when a drift was fitted."""
    labels, table, rep = run.labels, run.rssi, run.report
    lab = np.asarray(labels.labelled, bool)
    t_s = (np.asarray(table.t_ns, np.int64)[lab] - round(t0 * 1e9)) / 1e9
    if antenna is None or not t_s.size:
        truth = np.array([path.position_at(float(s)) for s in t_s]).reshape(-1, 3)
    else:
        pos, rot = bundle_pose_at(path, 0.0)(t_s)
        truth = pos.reshape(-1, 3) + rot.apply(antenna).reshape(-1, 3)
    err = np.linalg.norm(np.asarray(labels.positions)[lab] - truth, axis=1)
    cams = {}
    for name, cam in rep["sync"]["cameras"].items():
        found = float(cam["video_start"])
        sigma = cam.get("video_start_sigma_s")
        drift = float(cam.get("drift") or 0.0)
        # The true clocks do not drift: an error in the fitted drift grows along the video.
        end_ms = (
            None if duration_s is None else (found - true_starts[name] + duration_s * drift) * 1e3
        )
        cams[name] = {
            "found": found,
            "true": true_starts[name],
            "error_ms": (found - true_starts[name]) * 1e3,
            "error_end_ms": end_ms,
            "sigma_ms": None if sigma is None else float(sigma) * 1e3,
            "method": cam.get("method"),
            "drift": cam.get("drift"),
        }

    def cm(q: float) -> float | None:
        return float(np.percentile(err, q) * 100) if err.size else None

    return {
        "error_cm": {
            "n": int(err.size),
            "median": cm(50),
            "p95": cm(95),
            "max": float(err.max() * 100) if err.size else None,
        },
        "coverage": {
            "labelled_of_tracked_span": float(rep["coverage"]["labelled_of_tracked_span"]),
            "labelled": int(lab.sum()),
            "readings_of_beacon": len(table),
        },
        "mode": rep.get("mode", "beacon"),
        "counts": rep["counts"],
        "sync": cams,
        "rssi_events": len(rep["sync"].get("rssi_events", [])),
    }


@dataclass(frozen=True)
class DemoResult:
    capture: Capture
    experiment: Path
    results: Path
    summary: dict[str, Any]
    summary_path: Path


def run_demo(
    settings: DemoSettings,
    progress: Progress | None = None,
    note: Note | None = None,
    on_capture: Callable[[Capture], None] | None = None,
) -> DemoResult:
    """The whole demo; writes OUT/capture, OUT/experiment, OUT/results and OUT/demo_summary.json."""
    from annotator.commands.run import write_run_outputs
    from annotator.io.experiment import load_experiment
    from annotator.pipeline import RunSettings, TrackSettings, run_experiment

    out = prepare_out(settings)
    path = demo_path(settings.speed_mps)
    started = time.monotonic()

    cap = capture(settings, path, progress, note)
    if on_capture is not None:
        on_capture(cap)
    exp_path = render(settings, path, cap.t0, cap.run_dir, progress)
    results = out / "results"
    experiment = load_experiment(exp_path)
    run = run_experiment(experiment, RunSettings(track=TrackSettings(jobs=settings.jobs)), progress)
    report = write_run_outputs(results, experiment, run)
    true_starts = {"front": cap.t0, "back": cap.t0 + settings.start_offset_s}
    summary = score(run, path, cap.t0, true_starts, settings.duration_s)
    summary.update(
        {
            "duration_s": settings.duration_s,
            "t0": cap.t0,
            "covers": [{"start_s": s, "duration_s": d} for s, d in settings.covers()],
            "capture": {
                "run_dir": str(cap.run_dir),
                "files": [
                    {
                        "sensor": f.sensor,
                        "rows": f.rows,
                        "first_ns": f.first_ns,
                        "last_ns": f.last_ns,
                    }
                    for f in cap.files
                ],
            },
            "experiment": str(exp_path),
            "results": str(results),
            "plots": [str(results / p) for p in report.get("plots", {}).values()],
            "wall_time_s": time.monotonic() - started,
        }
    )
    return DemoResult(cap, exp_path, results, summary, write_summary(out, summary))


def prepare_out(settings: DemoSettings) -> Path:
    """The demo's folder, made; DemoError if it holds an earlier demo or the duration is short."""
    out = settings.out
    for sub in ("capture", "experiment", "results"):
        if (out / sub).exists() and (not (out / sub).is_dir() or any((out / sub).iterdir())):
            raise DemoError(f"{out / sub} already holds files; give a new --out or remove it")
    if settings.duration_s < 8.0:
        raise DemoError(
            f"--duration must be at least 8 s (a cover event and tracking on both "
            f"sides of it), got {settings.duration_s:g}"
        )
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_summary(out: Path, summary: dict[str, Any]) -> Path:
    path = out / "demo_summary.json"
    path.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return path
