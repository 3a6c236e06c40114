"""Is the automatic sync biased? Every edge and every fitted video start against known truth, over
seeds of the `annotator demo` scenario.

    python bench/sync_bias.py                          # 20 seeds, 12 s and 30 s captures
    python bench/sync_bias.py --seeds 200 --durations 30
    python bench/sync_bias.py --width 960 --height 540 # the demo's own video size (slower render)

Per duration, the demo's walk is rendered once with `annotator.render.render_experiment` (both
cameras, the back one 0.35 s late, the demo's hands-cover events: the hands close in 0.15 s and the
radio sees the cover from the middle of that ramp to the middle of the opening one). Per seed, the
three simulated agents' readings are generated exactly as `annotator demo`'s agents make them
(`Simulation`, seed*10+i, 10 adverts/s, -20 dB and 60 % loss while covered). `annotator.core.sync`
finds the events on both sides and fits each camera's clock map, as `annotator run` does.

Printed:
- RSSI edges: signed error against the true edge per edge kind (mean +- its standard error, sd),
  the mean reported sigma and the share within 1 and 2 sigma; the "common" row is the mean of an
  event's cover and release error, which is what the video start inherits (a widening or narrowing
  of the interval cancels between cover and release; a lag does not).
- the oracle: the middle of the gap between the last advert heard before a true edge and the
  first after it (no detector knows more than that), and the length of that gap; and a second
  oracle that also knows every advert the agents sent, lost or not (a lossless twin of the
  simulation: the simulator draws the same random numbers whatever survives).
- video edges of the render (PTS against the truth): the picture darkens before the hand is
  halfway closed, so the interval widens symmetrically; that too cancels.
- the video start per camera over seeds: mean +- standard error, sd, median reported sigma and
  coverage of the 1- and 2-sigma intervals (68 % / 95 % for an honest sigma), at the first and at
  the last frame.
  The front camera is fitted a second time with a flat prior on the drift (`drift_prior=None`,
  the plain least-squares fit used before the mixture prior), for comparison.
- seed 0, the demo's default, edge by edge.
- the drift prior against the flat fit on synthetic edges, over capture spans and true drifts
  (--drift-trials per cell).
- a check of the check: the same fits with every RSSI timestamp delayed by --lag-ms (13 ms by
  default, the demo's seed-0 error), which a real detector lag would look like.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from sync_accuracy import T0, demo_readings

from annotator import demo
from annotator.core.sync import (
    DRIFT_PRIOR,
    CoverEvent,
    detect_rssi_events,
    detect_video_events,
    fit_clock_map,
)
from annotator.io.sync import brightness_series
from annotator.render import render_experiment

CAMERAS = {"front": 0.0, "back": demo.DemoSettings(out=None).start_offset_s}  # type: ignore[arg-type]


def stats(x: np.ndarray) -> str:
    x = np.asarray(x, float) * 1e3
    sem = x.std(ddof=1) / math.sqrt(x.size) if x.size > 1 else math.nan
    return f"mean {x.mean():+6.2f} +- {sem:4.2f} ms   sd {x.std(ddof=1) if x.size > 1 else 0.0:5.2f} ms"


def coverage(err: np.ndarray, sig: np.ndarray) -> str:
    z = np.abs(err) / sig
    return (
        f"median sigma {1e3 * np.median(sig):5.2f} ms   within 1 sigma {100 * np.mean(z <= 1):5.1f} %   "
        f"within 2 sigma {100 * np.mean(z <= 2):5.1f} %"
    )


def true_edges(settings: demo.DemoSettings) -> list[tuple[float, float]]:
    """(cover, release) in seconds after t0: when the radio sees the hands (mid-ramp to mid-ramp)."""
    return [(e.start_s, e.start_s + e.duration_s) for e in demo.rssi_events(settings)]


def sent_adverts(seed: int, duration: float) -> np.ndarray:
    """Times (s after t0) of every advert the demo's agents sent with this seed, heard or lost."""
    from sensor_agent.scanning.simulated import RadioModel, simulate_fleet

    radio = RadioModel(drop_prob=0.0, floor_dbm=-1000.0)
    out = []
    for sim in simulate_fleet(
        "tetam", demo.split_sensors(), demo.demo_path(), round(T0 * 1e9), seed=seed, radio=radio
    ):
        out.append([r.t_ns / 1e9 - T0 for _, r in sim.generate(duration + 1.0)])
    return np.unique(np.concatenate(out))


def render_video(
    settings: demo.DemoSettings, width: int, height: int, work: Path
) -> dict[str, list[CoverEvent]]:
    """Cover events found in each camera of one render of the demo walk (PTS seconds)."""
    out = work / f"render-{settings.duration_s:g}"
    render_experiment(
        out,
        demo.bundle_pose_at(demo.demo_path(settings.speed_mps), T0),
        (T0, T0 + settings.duration_s),
        width=width,
        height=height,
        start_offset=settings.start_offset_s,
        covers=settings.covers(),
        seed=0,
        jobs=1,
    )
    return {
        cam: detect_video_events(*brightness_series(out / f"{cam}.mp4"), name=cam)
        for cam in CAMERAS
    }


def score_rssi(
    acc: dict[str, list],
    seed: int,
    t: np.ndarray,
    found: list[CoverEvent],
    truth: list[tuple[float, float]],
    sent: np.ndarray,
    seed0: list[str],
) -> None:
    """Each RSSI edge against the truth, the two oracles and the gap round each true edge."""
    adverts = np.unique(t) - T0
    for i, (ev, (c, rel)) in enumerate(zip(found, truth, strict=True)):
        errs = []
        for kind, got, sig, true in (
            ("cover", ev.cover, ev.cover_sigma, c),
            ("release", ev.release, ev.release_sigma, rel),
        ):
            key = f"{kind} {i + 1}"
            before, after = adverts[adverts < true].max(), adverts[adverts >= true].min()
            acc[f"err {key}"].append(got - T0 - true)
            acc[f"sig {key}"].append(sig)
            acc["oracle"].append(0.5 * (before + after) - true)
            acc["sent"].append(0.5 * (sent[sent < true].max() + sent[sent >= true].min()) - true)
            acc["gaps"].append(after - before)
            errs.append(got - T0 - true)
            if seed == 0:
                seed0.append(
                    f"    RSSI {key:<9} error {1e3 * (got - T0 - true):+7.1f} ms (sigma "
                    f"{1e3 * sig:5.1f})   adverts heard {1e3 * (before - true):+6.1f} / "
                    f"{1e3 * (after - true):+6.1f} ms around the true edge"
                )
        acc["common"].append(float(np.mean(errs)))


def score_clocks(
    acc: dict[str, list],
    seed: int,
    video: dict[str, list[CoverEvent]],
    found: list[CoverEvent],
    duration: float,
    seed0: list[str],
) -> None:
    """Each camera's clock map against the truth at its first and last frame; the front camera
    also with the flat drift prior of the fit before the mixture prior."""
    for cam, offset in CAMERAS.items():
        for label, prior in (("", DRIFT_PRIOR), (" flat", None)):
            if label and cam != "front":
                continue
            cm = fit_clock_map(video[cam], found, name=cam, drift_prior=prior)
            for where, pts in (("first", 0.0), ("last", duration - offset)):
                acc[f"{cam}{label} {where} err"].append(float(cm.to_rssi(pts)) - T0 - offset - pts)
                acc[f"{cam}{label} {where} sig"].append(float(cm.sigma_at(pts)))
            if seed == 0 and not label:
                seed0.append(
                    f"    {cam} video start error {1e3 * (cm.video_start - T0 - offset):+6.1f} ms "
                    f"(sigma {1e3 * cm.video_start_sigma:4.1f}), drift {cm.drift:+.1e}, "
                    f"edge bias {1e3 * cm.edge_bias:+5.1f} ms"
                )


def report(
    acc: dict[str, list],
    kinds: list[str],
    video: dict[str, list[CoverEvent]],
    truth: list[tuple[float, float]],
    seed0: list[str],
    lag: float,
) -> None:
    print(
        "RSSI edges against the truth (seconds after t0 when the hands are halfway over the beacon):"
    )
    for k in kinds:
        e, sg = np.array(acc[f"err {k}"]), np.array(acc[f"sig {k}"])
        print(f"  {k:<10} {stats(e)}   {coverage(e, sg)}")
    print(f"  {'common':<10} {stats(np.array(acc['common']))}   (what the video start inherits)")
    gaps = np.array(acc["gaps"])
    print(
        f"  oracle gap middle: {stats(np.array(acc['oracle']))}; gap round a true edge: median "
        f"{1e3 * np.median(gaps):.0f} ms, p95 {1e3 * np.percentile(gaps, 95):.0f} ms, max {1e3 * gaps.max():.0f} ms"
    )
    print(f"  oracle knowing every advert sent: {stats(np.array(acc['sent']))}")
    print("video edges of the render against the truth (PTS):")
    for cam, offset in CAMERAS.items():
        parts = []
        for ev in video[cam]:
            c, rel = min(
                truth,
                key=lambda cr, ev=ev: (
                    abs(cr[0] - offset - ev.cover)
                    if math.isfinite(ev.cover)
                    else abs(cr[1] - offset - ev.release)
                ),
            )
            parts.append(
                f"cover {1e3 * (ev.cover - (c - offset)):+6.1f} / release "
                f"{1e3 * (ev.release - (rel - offset)):+6.1f} ms (sigma {1e3 * ev.cover_sigma:.1f})"
            )
        print(f"  {cam:<6} " + ";  ".join(parts))
    print("video clock map over seeds (error of the mapped time at the first / last frame):")
    for cam, label in (*((c, "") for c in CAMERAS), ("front", " flat")):
        for where in ("first", "last"):
            e, sg = (
                np.array(acc[f"{cam}{label} {where} err"]),
                np.array(acc[f"{cam}{label} {where} sig"]),
            )
            note = "   (flat drift prior: the fit before)" if label else ""
            print(f"  {cam:<6} {where + ' frame':<11} {stats(e)}   {coverage(e, sg)}{note}")
    print("seed 0 (the demo's default):")
    print("\n".join(seed0))
    if acc["lag"]:
        print(
            f"check: every RSSI timestamp {1e3 * lag:g} ms late -> front start {stats(np.array(acc['lag']))}"
        )


def drift_grid(trials: int) -> None:
    """The drift prior against the flat fit on synthetic edges: two events `span` s apart, RSSI
    edges with 17 ms of noise (the demo's), a true drift; rms error of the mapped time at the first
    and last frame, and the share within 2 reported sigma."""
    print(
        f"\n=== drift prior vs flat fit: two events span s apart, 17 ms RSSI edges, {trials} trials ==="
    )
    print("  span    drift    flat: rms, within 2 sigma    prior: rms, within 2 sigma")
    for span in (25.0, 110.0, 590.0):
        for drift in (0.0, 50e-6, 300e-6, 1000e-6):
            rng = np.random.default_rng(5)
            res = {}
            for label, prior in (("flat", None), ("prior", DRIFT_PRIOR)):
                err, sig = [], []
                for _ in range(trials):
                    v = [
                        CoverEvent(2.0, 3.5, 0.0056, 0.0056),
                        CoverEvent(2.0 + span, 3.5 + span, 0.0056, 0.0056),
                    ]
                    r = [
                        CoverEvent(
                            T0 + e.cover * (1 + drift) + rng.normal(0, 0.017) - 0.02,
                            T0 + e.release * (1 + drift) + rng.normal(0, 0.017) + 0.02,
                            0.017,
                            0.017,
                        )
                        for e in v
                    ]
                    cm = fit_clock_map(v, r, drift_prior=prior)
                    for pts in (0.0, span + 5.0):
                        err.append(float(cm.to_rssi(pts)) - T0 - pts * (1 + drift))
                        sig.append(float(cm.sigma_at(pts)))
                e, sg = np.array(err), np.array(sig)
                res[label] = (
                    f"{1e3 * np.sqrt(np.mean(e**2)):5.1f} ms, {100 * np.mean(np.abs(e) <= 2 * sg):5.1f} %"
                )
            print(
                f"  {span:4.0f} s {1e6 * drift:5.0f} ppm    {res['flat']}            {res['prior']}"
            )


def one_duration(
    duration: float, seeds: int, width: int, height: int, lag: float, work: Path
) -> None:
    settings = demo.DemoSettings(out=None, duration_s=duration)  # type: ignore[arg-type]
    truth = true_edges(settings)
    t_render = time.perf_counter()
    video = render_video(settings, width, height, work)
    t_render = time.perf_counter() - t_render
    print(
        f"\n=== {duration:g} s captures, {len(truth)} cover event(s), {seeds} seeds "
        f"(render {width}x{height} in {t_render:.0f} s) ==="
    )
    kinds = [f"{k} {i + 1}" for i in range(len(truth)) for k in ("cover", "release")]
    acc: dict[str, list] = defaultdict(list)
    seed0: list[str] = []
    for seed in range(seeds):
        (t, r, s), _ = demo_readings(seed, duration)
        found = detect_rssi_events(t, r, s)
        if len(found) != len(truth):
            print(f"  seed {seed}: {len(found)} RSSI events found, {len(truth)} true; skipped")
            continue
        score_rssi(acc, seed, t, found, truth, sent_adverts(seed, duration), seed0)
        score_clocks(acc, seed, video, found, duration, seed0)
        if lag > 0:
            acc["lag"].append(
                fit_clock_map(video["front"], detect_rssi_events(t + lag, r, s)).video_start - T0
            )
    report(acc, kinds, video, truth, seed0, lag)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument(
        "--durations", default="12,30", help="comma-separated capture lengths, s (default 12,30)"
    )
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument(
        "--lag-ms", type=float, default=13.0, help="the check's RSSI delay (0: skip the check)"
    )
    ap.add_argument(
        "--drift-trials",
        type=int,
        default=300,
        help="trials per cell of the drift-prior table (0: skip)",
    )
    args = ap.parse_args()
    t_start = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="sync-bias-"))
    try:
        for d in (float(x) for x in args.durations.split(",") if x.strip()):
            one_duration(d, args.seeds, args.width, args.height, args.lag_ms / 1e3, work)
        if args.drift_trials > 0:
            drift_grid(args.drift_trials)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"({time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
