"""How long an outage the agent's spool covers, and how fast it appends, on this machine.

Spools realistic batches (as the publisher encodes them: sent_ns set, monotonic time set, seq in
the hundred-thousands as after a few hours) for 12 sensors at 10 Hz each, measures the bytes on
disk per batch and prints the outage the default 256 MiB spool covers before it drops anything.
Then appends as fast as it can with the default fsync policy (and, for comparison, an fsync
after every record) and reads everything back with pending().

    python bench/spool_capacity.py [--sensors 12] [--hz 10] [--seconds 3] [--dir DIR]

--dir chooses the filesystem measured (default: a temporary directory); use the Pi's SD card.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from bgt_core import wire
from sensor_agent.spool import DEFAULT_FSYNC_INTERVAL_S, Spool

MIB = 1024 * 1024
AGENT, BOOT = "pi-01", "3f9c2a7be1d04c55"
T0 = 1_790_000_000 * 10**9
IB = wire.IBeacon("f7826da64fa24e988024bc5b71e0893e", 1, 42, -59)


def sensor_mac(i: int) -> str:
    return f"b827eb{0x4521B0 + i:06x}"


def batch_payload(sensor: int, seq: int, readings: int, ibeacon: bool) -> bytes:
    t = T0 + seq * 100_000_000
    rows = tuple(
        wire.Reading(
            t + j * 37_000_000 + sensor * 1_000,
            "e78f135624ce",
            -55 - (seq + j + sensor) % 30,
            mono_ns=123_456_789_000_000 + t % 10**12,
            ibeacon=IB if ibeacon else None,
        )
        for j in range(readings)
    )
    b = wire.Batch(AGENT, BOOT, sensor_mac(sensor), 100_000 + seq, rows, sent_ns=t + 2_000_000)
    return wire.to_wire(b)


def bytes_per_batch(root: Path, sensors: int, readings: int, ibeacon: bool) -> float:
    """Spool a simulated minute (at batch_ms 100) and measure the segment bytes per batch."""
    d = Path(tempfile.mkdtemp(dir=root))
    try:
        n = 0
        with Spool(d, 256 * MIB) as sp:
            for seq in range(600):
                for s in range(sensors):
                    sp.append(
                        f"{BOOT}/{sensor_mac(s)}",
                        100_000 + seq,
                        batch_payload(s, seq, readings, ibeacon),
                    )
                    n += 1
            size = sp.stats().bytes
        return size / n
    finally:
        shutil.rmtree(d)


def append_rate(
    root: Path, sensors: int, seconds: float, fsync_interval_s: float
) -> tuple[float, float]:
    """(records/s appended, records/s read back by pending())."""
    d = Path(tempfile.mkdtemp(dir=root))
    pool = [batch_payload(s, seq, 1, False) for seq in range(50) for s in range(sensors)]
    try:
        with Spool(d, 256 * MIB, fsync_interval_s=fsync_interval_s) as sp:
            n, t0 = 0, time.perf_counter()
            end = t0 + seconds
            while time.perf_counter() < end:
                for k in range(100):
                    s = (n + k) % sensors
                    sp.append(f"{BOOT}/{sensor_mac(s)}", n + k, pool[(n + k) % len(pool)])
                n += 100
            write_rate = n / (time.perf_counter() - t0)
            t1 = time.perf_counter()
            back = sum(1 for _ in sp.pending())
            read_rate = back / (time.perf_counter() - t1)
            assert back == n, (back, n)
        return write_rate, read_rate
    finally:
        shutil.rmtree(d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", type=int, default=12)
    ap.add_argument("--hz", type=float, default=10.0, help="adverts per second per sensor")
    ap.add_argument("--seconds", type=float, default=3.0, help="length of each throughput phase")
    ap.add_argument("--max-mb", type=int, default=256, help="spool size (spool.max_mb, MiB)")
    ap.add_argument("--dir", type=Path, default=None, help="where to spool (default: temp dir)")
    args = ap.parse_args()
    root = args.dir or Path(tempfile.gettempdir())
    budget = args.max_mb * MIB
    segment = min(8 * MIB, budget // 16)

    print(
        f"spool {args.max_mb} MiB = {budget} bytes, segments {segment} bytes; "
        f"{args.sensors} sensors x {args.hz:g} Hz"
    )
    print(
        f"{'batch_ms':>8} {'readings/batch':>14} {'iBeacon':>7} {'bytes/batch':>11} "
        f"{'batches/s':>9} {'KiB/s':>7} {'outage covered':>15} {'kept after a drop':>18}"
    )
    for batch_ms in (100, 200):
        readings = max(1, round(args.hz * batch_ms / 1000))
        batches_per_s = args.sensors * 1000 / batch_ms
        for ibeacon in (False, True):
            per = bytes_per_batch(root, args.sensors, readings, ibeacon)
            rate = per * batches_per_s
            covered_h = budget / rate / 3600
            kept_h = (budget - segment) / rate / 3600
            print(
                f"{batch_ms:>8} {readings:>14} {'yes' if ibeacon else 'no':>7} {per:>11.1f} "
                f"{batches_per_s:>9.0f} {rate / 1024:>7.1f} {covered_h:>13.1f} h "
                f"{kept_h:>16.1f} h"
            )

    for label, interval in (
        (
            f"fsync every {DEFAULT_FSYNC_INTERVAL_S * 1000:.0f} ms (default)",
            DEFAULT_FSYNC_INTERVAL_S,
        ),
        ("fsync every record", 0.0),
    ):
        w, r = append_rate(root, args.sensors, args.seconds, interval)
        print(
            f"append, {label}: {w:,.0f} records/s  "
            f"(needed: {args.sensors * args.hz:,.0f}/s at batch_ms 100); pending() reads {r:,.0f}/s"
        )


if __name__ == "__main__":
    main()
