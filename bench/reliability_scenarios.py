"""Lost / duplicated readings in each "nothing lost" scenario of issue 5, at a larger scale
than the tests: real `collector serve` and `sensor-agent run` processes on loopback Zenoh.

    python bench/reliability_scenarios.py [--sensors 8] [--beacons 3] [--seconds 60]
                                          [--only kill9,stop30,kill30,kill90,agent,fuzz,disk,adisk]

Scenarios: collector kill -9 restarted after 3 s; collector unreachable 30 s (SIGSTOP/SIGCONT);
collector kill -9 restarted after 30 s, and after 90 s (beyond the publisher's in-memory cache,
so only the spool covers it); agent kill -9 + restart on the same spool; a fuzz of hostile
payloads on data and control keys; the collector's data dir (2 MiB) or the agent's spool (1 MiB)
on a tmpfs that fills up mid-run and is freed 10 s later (root only). Then the outage the
default spool (256 MiB) covers at 12 sensors x 10 Hz, from the spool bytes per batch measured
during the outages.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent.parent / "tests"
sys.path.insert(0, str(TESTS / "support"))  # reliability_harness.py, and loopback.py it uses

from reliability_harness import (  # noqa: E402 - needs the path above
    Result,
    Scale,
    agent_restart,
    collector_outage,
    full_disk,
    fuzz_scenario,
)

MIB = 1024 * 1024


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", type=int, default=8)
    ap.add_argument("--beacons", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=60.0, help="stream length per scenario")
    ap.add_argument("--fuzz", type=int, default=10_000, help="hostile data payloads")
    ap.add_argument("--only", default="kill9,stop30,kill30,kill90,agent,fuzz,disk,adisk")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (logs, runs)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    scale = Scale(sensors=args.sensors, beacons=args.beacons, rate_hz=10, duration_s=args.seconds)
    long = Scale(
        sensors=args.sensors, beacons=args.beacons, rate_hz=10, duration_s=max(args.seconds, 50.0)
    )
    only = set(args.only.split(","))
    work = Path(tempfile.mkdtemp(prefix="bgt-reliability-"))
    runs = {
        "kill9": lambda d: collector_outage(
            d, scale, mode="kill9", outage_s=3.0, name="collector kill9, back 3s"
        ),
        "stop30": lambda d: collector_outage(
            d, long, mode="sigstop", outage_s=30.0, name="collector SIGSTOP 30s"
        ),
        "kill30": lambda d: collector_outage(
            d, long, mode="kill9", outage_s=30.0, name="collector kill9, back 30s"
        ),
        # Longer than the publisher's in-memory cache (600 batches = 60 s per stream): only the
        # spool and the re-send can fill this gap.
        "kill90": lambda d: collector_outage(
            d,
            Scale(args.sensors, args.beacons, 10, max(args.seconds, 110.0)),
            mode="kill9",
            outage_s=90.0,
            name="collector kill9, back 90s",
        ),
        "agent": lambda d: agent_restart(d, scale),
        "fuzz": lambda d: fuzz_scenario(d, scale, n_data=args.fuzz, n_queries=1000),
        "disk": lambda d: full_disk(d, scale, hold_s=10.0, side="collector"),
        "adisk": lambda d: full_disk(d, scale, hold_s=10.0, size="1m", side="agent"),
    }
    print(
        f"{args.sensors} sensors x {args.beacons} beacons x 10 Hz, {args.seconds:g} s streams; "
        f"work folder {work}"
    )
    results: list[Result] = []
    try:
        for key, fn in runs.items():
            if key not in only:
                continue
            t = time.monotonic()
            res = fn(work / key)
            res.notes["took_s"] = round(time.monotonic() - t, 1)
            results.append(res)
            print(res.line(), flush=True)
            for p in res.problems:
                print("   problem:", p.splitlines()[0])
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    bpb = [
        r.notes["spool_bytes_per_batch"] for r in results if r.notes.get("spool_bytes_per_batch")
    ]
    if bpb:
        b = max(bpb)
        hours = 256 * MIB / (b * 12 * 10) / 3600
        print(
            f"spool: {b:.0f} bytes per batch ({args.beacons} readings) -> the default 256 MiB "
            f"covers {hours:.1f} h of outage at 12 sensors x 10 batches/s"
        )
    return 0 if all(r.tally.ok() and not r.problems for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
