"""Scoring speed: estimates scored per second by annotator.core.scoring.score; prints figures.

    python bench/score_speed.py [--estimates 1000000] [--truth-rate 30] [--repeat 3]

A synthetic walk sampled at --truth-rate Hz as the ground truth (one sample per video frame, as
an annotated run's trajectory.csv) and --estimates noisy estimates at random times over it.
Best of --repeat runs; the latency search (which re-scores once per candidate shift) separately.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from annotator.core.scoring import Truth, score


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimates", type=int, default=1_000_000)
    ap.add_argument("--truth-rate", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    duration = 3600.0
    tt = np.arange(0.0, duration, 1.0 / args.truth_rate) + 1.7e9
    tau = tt - tt[0]
    truth = Truth.from_samples(
        tt,
        np.column_stack(
            [10 + 5 * np.sin(tau / 20), 8 + 4 * np.cos(tau / 13), 1.5 + 0.1 * np.sin(tau)]
        ),
    )
    t = np.sort(rng.uniform(tt[0] - 10, tt[-1] + 10, args.estimates))
    est = rng.normal(0, 1.0, (len(t), 3))
    est[:, 0] += 10
    est[:, 1] += 8
    best = float("inf")
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        s = score(t, est, truth)
        _ = s.summary_2d, s.summary_3d
        best = min(best, time.perf_counter() - t0)
    print(
        f"truth: {len(tt)} samples ({args.truth_rate:g} Hz over {duration:g} s); "
        f"estimates: {len(t)}"
    )
    print(
        f"score (errors, coverage, both summaries): {best * 1e3:.0f} ms = "
        f"{len(t) / best / 1e6:.2f} M estimates/s"
    )
    n_lat = min(len(t), 100_000)
    t0 = time.perf_counter()
    s = score(t[:n_lat], est[:n_lat], truth, latency_max_s=3.0, latency_step_s=0.05)
    dt = time.perf_counter() - t0
    print(
        f"with the latency search (+-3 s in 0.05 s steps, 121 shifts) on {n_lat} estimates: "
        f"{dt:.2f} s = {n_lat / dt / 1e3:.0f} k estimates/s"
    )


if __name__ == "__main__":
    main()
