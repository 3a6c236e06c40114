"""Does the sync sigma mean what it says? Coverage of the reported 1- and 2-sigma intervals over seeds.

    python bench/sync_coverage.py                 # 200 seeds, 12 s demo captures
    python bench/sync_coverage.py --seeds 400 --duration 30

Each seed simulates what `annotator demo` records: three simulated agents (four tetam sensors
each, 10 adverts/s of the bundle beacon, every advert heard by each of an agent's sensors) with
hands over the beacon (-20 dB, 60 % of readings lost) for 1.5 s near the start and near the end;
and a 30 fps video of the same covers (brightness, noise 2 grey levels, hands closing in 0.15 s)
that starts at a random wall time and whose clock runs off by a random drift (--drift-ppm). `annotator.core.sync` finds the events on both sides and fits the
clock map. Printed per quantity: the median |error|, the median reported sigma, and the share of
seeds whose error lies within 1 and 2 reported sigma (68 % and 95 % if the sigma is honest).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from sync_accuracy import T0, demo_readings, video

from annotator.core.sync import detect_rssi_events, detect_video_events, fit_clock_map


def row(label: str, err: np.ndarray, sig: np.ndarray) -> None:
    z = np.abs(err) / sig
    print(
        f"  {label:<26} n {len(err):4d}   median |err| {1e3 * np.median(np.abs(err)):6.2f} ms   "
        f"median sigma {1e3 * np.median(sig):6.2f} ms   within 1 sigma {100 * np.mean(z <= 1):5.1f} %   "
        f"within 2 sigma {100 * np.mean(z <= 2):5.1f} %",
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument(
        "--drift-ppm",
        type=float,
        default=30.0,
        help="the video clock runs fast or slow by up to this much (uniform), default 30 ppm",
    )
    args = ap.parse_args()
    t_start = time.perf_counter()
    edge_err, edge_sig, off_err, off_sig, drift_z, fitted, mid_err, mid_sig = (
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
    )
    for seed in range(args.seeds):
        rng = np.random.default_rng(10_000 + seed)
        (t, r, s), truth = demo_readings(seed, args.duration)
        found = detect_rssi_events(t, r, s)
        for ev, (c, rel) in zip(found, truth, strict=False):
            edge_err += [ev.cover - T0 - c, ev.release - T0 - rel]
            edge_sig += [ev.cover_sigma, ev.release_sigma]
        start = rng.uniform(-1.5, -0.5)  # video_start - T0: the video starts before t0
        drift = rng.uniform(-1, 1) * args.drift_ppm * 1e-6

        def pts_of(t_rel: float, start: float = start, drift: float = drift) -> float:
            return (t_rel - start) / (1 + drift)  # t_rssi = start + pts (1 + drift)

        (c0, r0), *rest = truth
        pts, b, mc = video(rng, pts_of(c0), pts_of(r0), 30, 2, 0.15, duration=args.duration - start)
        if rest:  # the second cover as well (drift)
            c1, r1 = rest[0]
            pts, b2, mc2 = video(
                rng, pts_of(c1), pts_of(r1), 30, 2, 0.15, duration=args.duration - start
            )
            late = pts > pts_of(0.5 * (r0 + c1))
            b, mc = np.where(late, b2, b), np.where(late, mc2, mc)
        cm = fit_clock_map(detect_video_events(pts, b, mc), found)
        off_err.append(cm.video_start - T0 - start)
        off_sig.append(cm.video_start_sigma)
        if np.isfinite(cm.drift_sigma):
            drift_z.append(abs(cm.drift - drift) / cm.drift_sigma)
            fitted.append(cm.drift != 0.0)
        mid = 0.5 * args.duration  # the mapped time in the middle of the capture
        mid_err.append(float(cm.to_rssi(pts_of(mid))) - T0 - mid)
        mid_sig.append(float(cm.sigma_at(pts_of(mid))))
    print(f"{args.seeds} seeds, {args.duration:g} s captures:")
    row("RSSI edges", np.array(edge_err), np.array(edge_sig))
    row("video start (clock offset)", np.array(off_err), np.array(off_sig))
    row("mapped time mid-capture", np.array(mid_err), np.array(mid_sig))
    if drift_z:
        print(
            f"  drift sigma stated in {len(drift_z)} of {args.seeds} seeds, drift fitted in {sum(fitted)} "
            f"(true drift within +-{args.drift_ppm:g} ppm); drift error within 2 sigma in "
            f"{100 * np.mean(np.array(drift_z) <= 2):.1f} %"
        )
    print(f"({time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
