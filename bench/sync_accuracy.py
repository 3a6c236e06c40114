"""Accuracy of the automatic sync stages on synthetic signals with known truth (Monte Carlo).

Prints, per condition, the error of the video edges (brightness, sub-frame), of the RSSI edges
(pooled readings of all sensors) and of the fitted video start, with the reported sigma beside
it. Signed means show a bias: a symmetric one (cover early, release late) cancels in the fit; a
common one shifts the video start. The `annotator demo` scenario (its simulated agents, seeds
varied) is compared with an oracle that knows which readings were covered and takes the middle of
the gap around each true edge: no detector can beat the advert spacing.
Usage: python bench/sync_accuracy.py [--trials 200]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from annotator.core.sync import CoverEvent, detect_rssi_events, detect_video_events, fit_clock_map

T0 = 1_700_000_000.0


def video(
    rng: np.random.Generator,
    cover: float,
    release: float,
    fps: float,
    noise: float,
    ramp: float,
    duration: float = 10.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box-exposure frames of a moving scene; the lens covered over [cover, release] (ramp midpoints)."""
    pts = np.arange(0.0, duration, 1.0 / fps)
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    s = pts[:, None] + sub[None, :] / fps
    if ramp > 0:
        f = np.minimum(
            np.clip((s - cover + ramp / 2) / ramp, 0, 1),
            np.clip((release + ramp / 2 - s) / ramp, 0, 1),
        )
    else:
        f = ((s >= cover) & (s < release)).astype(float)
    f = f.mean(axis=1)
    scene = 110.0 * (1 + 0.14 * np.sin(0.7 * pts))
    b = scene * (1 - f) + 10.0 * f + rng.normal(0, noise, pts.size)
    return pts, b, np.where(f > 0.4, 0, 4)


def rssi(
    rng: np.random.Generator,
    cover: float,
    release: float,
    rate: float,
    keep: float,
    drop_db: float,
    sensors: int = 12,
    duration: float = 30.0,
) -> tuple[np.ndarray, ...]:
    ts, rs, ss = [], [], []
    for k in range(sensors):
        n = rng.poisson(rate * duration)
        t = np.sort(rng.uniform(0, duration, n))
        lv = -60.0 - 2.0 * k + rng.normal(0, 4, n)
        inside = (t >= cover) & (t < release)
        lv[inside] -= drop_db
        ok = ~inside | (rng.random(n) < keep)
        ts.append(t[ok] + T0)
        rs.append(np.round(lv[ok]))
        ss.append(np.full(ok.sum(), k))
    return np.concatenate(ts), np.concatenate(rs), np.concatenate(ss)


def row(label: str, err: np.ndarray, sig: np.ndarray | None = None) -> None:
    e = np.abs(err) * 1e3
    extra = f"   mean reported sigma {np.mean(sig) * 1e3:6.2f} ms" if sig is not None else ""
    print(
        f"  {label:<34} mean {np.mean(err) * 1e3:+6.2f} ms   median |err| {np.median(e):6.2f} ms"
        f"   p95 {np.percentile(e, 95):6.2f} ms   max {e.max():6.2f} ms{extra}"
    )


def demo_readings(
    seed: int, duration: float
) -> tuple[tuple[np.ndarray, ...], list[tuple[float, float]]]:
    """The pooled readings `annotator demo` records (three simulated agents, four sensors each) and
    the true (cover, release) times, both in seconds after T0."""
    from annotator import demo
    from sensor_agent.scanning.simulated import simulate_fleet

    settings = demo.DemoSettings(out=None, duration_s=duration, seed=seed)  # type: ignore[arg-type]
    events = demo.rssi_events(settings)
    ts, rs, ss = [], [], []
    fleet = simulate_fleet(
        "tetam", demo.split_sensors(), demo.demo_path(), round(T0 * 1e9), seed=seed, events=events
    )
    for sim in fleet:
        for mac, r in sim.generate(duration + 1.0):
            ts.append(r.t_ns / 1e9)
            rs.append(r.rssi)
            ss.append(mac)
    truth = [(e.start_s, e.start_s + e.duration_s) for e in events]
    return (np.array(ts), np.array(rs, float), np.array(ss)), truth


def demo_scenario(trials: int, duration: float) -> None:
    errs, sigs, oracle, common = [], [], [], []
    for seed in range(trials):
        (t, r, s), truth = demo_readings(seed, duration)
        found = detect_rssi_events(t, r, s)
        advert_t = np.unique(t) - T0
        mine = []
        for ev, (c, rel) in zip(found, truth, strict=True):
            mine += [ev.cover - T0 - c, ev.release - T0 - rel]
            sigs += [ev.cover_sigma, ev.release_sigma]
            for edge in (c, rel):
                oracle.append(
                    0.5 * (advert_t[advert_t < edge].max() + advert_t[advert_t >= edge].min())
                    - edge
                )
        errs += mine
        common.append(np.mean(mine))  # what the video start inherits (video edges exact)
    row(f"demo {duration:g} s, RSSI edges", np.array(errs), np.array(sigs))
    row(f"demo {duration:g} s, oracle gap middle", np.array(oracle))
    row(f"demo {duration:g} s, common (-> start)", np.array(common))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    t_start = time.perf_counter()

    print("video edges (30 fps unless noted; noise in grey levels; ramp = hand closing time):")
    for fps, noise, ramp in ((30, 2, 0.0), (30, 2, 0.15), (30, 8, 0.15), (60, 2, 0.15)):
        errs, sigs = [], []
        for _ in range(args.trials):
            c = rng.uniform(2, 3)
            r = c + rng.uniform(1.0, 2.0)
            (ev,) = detect_video_events(*video(rng, c, r, fps, noise, ramp))
            errs += [ev.cover - c, ev.release - r]
            sigs += [ev.cover_sigma, ev.release_sigma]
        row(f"{fps} fps, noise {noise}, ramp {ramp:.2f} s", np.array(errs), np.array(sigs))

    print("RSSI edges (12 sensors; rate per sensor; keep = share of readings surviving the cover):")
    for rate, keep, drop in ((8, 0.3, 12), (8, 0.0, 15), (3, 0.3, 12), (8, 1.0, 8)):
        errs, sigs = [], []
        for _ in range(max(args.trials // 4, 10)):
            c = rng.uniform(8, 9)
            r = c + rng.uniform(1.0, 2.0)
            (ev,) = detect_rssi_events(*rssi(rng, c, r, rate, keep, drop))
            errs += [ev.cover - T0 - c, ev.release - T0 - r]
            sigs += [ev.cover_sigma, ev.release_sigma]
        row(f"{rate}/s, keep {keep}, drop {drop} dB", np.array(errs), np.array(sigs))

    print(
        "RSSI edges in the `annotator demo` scenario (3 agents x 4 sensors, 10 adverts/s each, "
        "-20 dB and 60 % loss while covered; one seed per trial):"
    )
    for duration in (12.0, 30.0):
        demo_scenario(max(args.trials // 4, 10), duration)

    print("video start (both detectors, one event, 30 fps, 8 readings/s/sensor):")
    errs, sigs = [], []
    for _ in range(max(args.trials // 4, 10)):
        start = rng.uniform(0, 5)  # video_start - T0
        c = rng.uniform(6, 8)
        r = c + rng.uniform(1.0, 2.0)
        pts, b, mc = video(rng, c - start, r - start, 30, 2, 0.15, duration=20.0)
        cm = fit_clock_map(
            detect_video_events(pts, b, mc), detect_rssi_events(*rssi(rng, c, r, 8, 0.3, 12))
        )
        errs.append(cm.video_start - T0 - start)
        sigs.append(cm.video_start_sigma)
    row("offset", np.array(errs), np.array(sigs))

    print("drift (two events 100 s apart, edges with 10 ms sigma):")
    errs = []
    for _ in range(args.trials):
        drift = rng.uniform(-1e-3, 1e-3)
        v = [CoverEvent(2.0, 3.5, 0.01, 0.01), CoverEvent(102.0, 103.2, 0.01, 0.01)]
        rr = [
            CoverEvent(
                T0 + e.cover * (1 + drift) + rng.normal(0, 0.01),
                T0 + e.release * (1 + drift) + rng.normal(0, 0.01),
                0.01,
                0.01,
            )
            for e in v
        ]
        errs.append(fit_clock_map(v, rr).drift - drift)
    e = np.abs(errs) * 1e6
    print(f"  drift error median {np.median(e):.1f} ppm, p95 {np.percentile(e, 95):.1f} ppm")
    print(f"({time.perf_counter() - t_start:.1f} s)")


if __name__ == "__main__":
    main()
