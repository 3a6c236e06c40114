"""What the collector's crash safety costs and how fast it recovers, on this machine's disk.

    python bench/collector_recovery.py [--sensors 12] [--rows 200000] [--boots 4] [--dir PATH]

Prints: the size of state.json and the time of one durable state write (temp file, fsync, rename,
directory fsync) for `sensors` streams per boot x `boots`; the time of one fsync round (all files
+ state) after 1 s of rows at 12 sensors x 10 Hz; and the time `open()`-style resume takes on a
run of `rows` rows per sensor with a torn last line in every file (repair + reopen).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from collector.ingest import StreamTracker
from collector.readings import Rows, format_rows, from_tuples
from collector.store import RunWriter

T0 = 1_795_318_500 * 10**9


def sensor_mac(i: int) -> str:
    return f"b827eb{i:06x}"


def rows(n: int, start: int) -> Rows:
    return from_tuples(
        (T0 + (start + k) * 1_000_003, 0, bytes.fromhex("e78f135624ce"), -40 - k % 50)
        for k in range(n)
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sensors", type=int, default=12)
    ap.add_argument("--rows", type=int, default=200_000, help="rows per sensor in the resumed run")
    ap.add_argument(
        "--boots", type=int, default=4, help="agent boots seen (streams = sensors x boots)"
    )
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: a temp dir)")
    args = ap.parse_args()
    logging.basicConfig(
        level=logging.ERROR
    )  # the resume's "cut N bytes" warnings are expected here
    base = Path(tempfile.mkdtemp(dir=args.dir))
    try:
        run(args, base)
    finally:
        shutil.rmtree(base, ignore_errors=True)


def run(args: argparse.Namespace, base: Path) -> None:

    tracker = StreamTracker()
    for b in range(args.boots):
        for s in range(args.sensors):
            st = ("pi-01", f"{b:016x}", sensor_mac(s))
            for q in range(0, 50):
                tracker.accept(st, q, floor=0)
            tracker.accept(st, 60, floor=0)  # one open gap each, so `ahead` is not empty
    w = RunWriter(base, "bench", "bench", T0, {"site": "default"})
    for s in range(args.sensors):
        w.append("pi-01", sensor_mac(s), format_rows(sensor_mac(s), rows(10, 0)), 10)
    w.fsync()
    state = w.state(tracker=tracker.to_state())
    times = []
    for _ in range(20):
        t = time.perf_counter()
        w.write_state(state)
        times.append(time.perf_counter() - t)
    size = (w.dir / "state.json").stat().st_size
    print(
        f"state.json: {size} bytes for {args.sensors * args.boots} streams; durable write "
        f"median {statistics.median(times) * 1e3:.2f} ms, max {max(times) * 1e3:.2f} ms"
    )

    rounds = []
    for r in range(10):
        for s in range(args.sensors):  # 1 s at 10 Hz, one reading per batch
            w.append("pi-01", sensor_mac(s), format_rows(sensor_mac(s), rows(10, 100 + 10 * r)), 10)
        t = time.perf_counter()
        w.fsync()
        w.write_state(w.state(tracker=tracker.to_state()))
        rounds.append(time.perf_counter() - t)
    print(
        f"fsync round (all {args.sensors} files + state): median "
        f"{statistics.median(rounds) * 1e3:.2f} ms, max {max(rounds) * 1e3:.2f} ms"
    )

    chunk = 20_000
    for s in range(args.sensors):
        for start in range(0, args.rows, chunk):
            n = min(chunk, args.rows - start)
            w.append("pi-01", sensor_mac(s), format_rows(sensor_mac(s), rows(n, 10_000 + start)), n)
    w.fsync()
    final = w.state({"tracker": tracker.to_state()})
    w.close()
    for s in range(args.sensors):
        with (w.dir / "rssi" / f"{sensor_mac(s)}.mbd").open("ab") as f:
            f.write(b"1795318500.1234,b827eb0000")  # torn by the crash
    mb = sum(p.stat().st_size for p in (w.dir / "rssi").glob("*.mbd")) / 2**20
    t = time.perf_counter()
    r = RunWriter(base, "bench", "bench", T0, {"site": "default"}, resume=final)
    StreamTracker.from_state(final["tracker"])
    dt = time.perf_counter() - t
    r.close()
    print(
        f"resume of a run with {args.sensors} files, {mb:.1f} MiB, torn last lines: {dt * 1e3:.1f} ms"
    )


if __name__ == "__main__":
    main()
