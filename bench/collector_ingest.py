"""Collector ingest throughput on this machine, beside a bare Zenoh subscriber's rate.

Both phases use the same publisher (a separate process publishing pre-encoded batches as fast as
Zenoh accepts them, congestion control BLOCK) and the same payloads. The collector phase counts a
reading only once it is in a run file; zero loss means every published row is in the files.

    python bench/collector_ingest.py [--seconds 30] [--batch 200] [--sensors 12] [--rate 0]
                                     [--rounds 3]

--rate paces the publisher (readings/s; 0 = as fast as it can). The collector phase also reports
the deepest its receive queue got, i.e. how far the writer fell behind. The two phases alternate
--rounds times, and the ratio's median and lowest are printed: on a 2-core machine the bare
rate alone moves by 10-15 % from one phase to the next.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))
from loopback import free_port  # noqa: E402 - the tests' port helper, on the path above

AGENT, BOOT = "bench", "00000000000000be"
T0 = 1_700_000_000 * 10**9


def sensor_mac(i: int) -> str:
    return f"b827eb{i:06x}"


def payloads(batch: int, sensors: int, count: int) -> list[tuple[str, bytes]]:
    """count batches round-robin over the sensors, each with `batch` distinct readings."""
    from bgt_core import wire

    out = []
    for k in range(count):
        s, seq = k % sensors, k // sensors
        rows = tuple(
            wire.Reading(T0 + (k * batch + j) * 1000, "e78f135624ce", -30 - (j % 70))
            for j in range(batch)
        )
        b = wire.Batch(AGENT, BOOT, sensor_mac(s), seq, rows)
        out.append((wire.data_key("default", AGENT, b.sensor), wire.to_wire(b)))
    return out


def publisher(connect: str, seconds: float, batch: int, sensors: int, rate: float) -> None:
    """Child process: publish until `seconds` elapse, then print how many batches went out."""
    import zenoh

    from bgt_core.zenoh_config import SessionSpec, build_config

    pool = payloads(batch, sensors, 4000)  # enough distinct keys/payloads; seq is re-encoded below
    from bgt_core import wire

    s = zenoh.open(build_config(SessionSpec(mode="client", connect=[connect])))
    pubs = {
        key: s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        for key, _ in pool[:sensors]
    }
    seqs = [0] * sensors
    sent = 0
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    sys.stdin.readline()  # parent says go
    start = time.monotonic()
    end = start + seconds
    template = [wire.from_wire(p) for _, p in pool[:sensors]]
    k = 0
    while time.monotonic() < end:
        i = k % sensors
        t = template[i]
        # Shift timestamps per batch so every row is distinct (loss shows up as missing rows).
        base = (k * batch) * 1000
        b = wire.Batch(
            AGENT,
            BOOT,
            t.sensor,
            seqs[i],
            tuple(
                wire.Reading(T0 + base + j * 1000, r.beacon, r.rssi)
                for j, r in enumerate(t.readings)
            ),
        )
        pubs[wire.data_key("default", AGENT, t.sensor)].put(wire.to_wire(b))
        seqs[i] += 1
        sent += batch
        k += 1
        if rate > 0:
            ahead = start + sent / rate - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
    sys.stdout.write(json.dumps({"readings": sent, "batches": k, "seqs": seqs}) + "\n")
    sys.stdout.flush()
    time.sleep(0.5)
    s.close()


def run_publisher(ep: str, args) -> tuple[subprocess.Popen, float]:
    p = subprocess.Popen(
        [
            sys.executable,
            __file__,
            "--role",
            "publisher",
            "--connect",
            ep,
            "--seconds",
            str(args.seconds),
            "--batch",
            str(args.batch),
            "--sensors",
            str(args.sensors),
            "--rate",
            str(args.rate),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert p.stdout.readline().strip() == "ready"
    time.sleep(0.5)
    t0 = time.monotonic()
    p.stdin.write("go\n")
    p.stdin.flush()
    return p, t0


def bare(args) -> dict:
    import zenoh

    from bgt_core.zenoh_config import SessionSpec, build_config

    ep = f"tcp/127.0.0.1:{free_port()}"
    s = zenoh.open(build_config(SessionSpec(mode="router", listen=[ep])))
    got = {"readings": 0, "last": 0.0}
    lock = threading.Lock()

    def on_sample(sample) -> None:
        n = int.from_bytes(sample.payload.to_bytes()[8:12], "little")  # reading count in the header
        with lock:
            got["readings"] += n
            got["last"] = time.monotonic()

    sub = s.declare_subscriber("ble/default/rssi/*/*", on_sample)
    p, t0 = run_publisher(ep, args)
    pub = json.loads(p.stdout.readline())
    p.wait()
    time.sleep(0.5)
    sub.undeclare()
    s.close()
    dt = got["last"] - t0
    return {
        "published": pub["readings"],
        "received": got["readings"],
        "seconds": round(dt, 2),
        "rate": round(got["readings"] / dt),
    }


def collector(args) -> dict:
    from collector.config import CollectorConfig, Limits
    from collector.service import Collector

    ep = f"tcp/127.0.0.1:{free_port()}"
    # One agent floods as fast as it can: the per-agent quotas (20,000 readings/s by default) are
    # lifted to their ceilings, or they, not the ingest path, would set the rate.
    limits = Limits(agent_readings_per_s=10_000_000, agent_mb_per_run=10_000_000)
    with tempfile.TemporaryDirectory() as tmp:
        c = Collector(CollectorConfig(data_dir=Path(tmp), listen=(ep,), limits=limits)).open()
        run = c.start_run("bench")
        p, t0 = run_publisher(ep, args)
        depth = [0]
        watching = threading.Event()

        def watch() -> None:
            while not watching.wait(0.5):
                depth[0] = max(depth[0], c.status()["queue"])

        watcher = threading.Thread(target=watch)
        watcher.start()
        pub = json.loads(p.stdout.readline())
        # Wait until the writer has handled every published batch (queue empty, counts equal).
        # The publisher lingers 0.5 s before it closes its session: not waited for here, as the
        # bare phase's clock also stops at the last reading.
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            st = c.status()
            if st["run"]["readings"] >= pub["readings"] and st["queue"] == 0:
                break
            time.sleep(0.01)
        t_done = time.monotonic()
        p.wait()
        watching.set()
        watcher.join()
        stopped = c.stop_run()
        c.close()
        lines = sum(sum(1 for _ in f.open("rb")) for f in Path(run["run_dir"]).glob("rssi/*/*.mbd"))
        dt = t_done - t0
        return {
            "published": pub["readings"],
            "written": stopped["readings"],
            "lines_in_files": lines,
            "lost": pub["readings"] - lines,
            "seconds": round(dt, 2),
            "rate": round(lines / dt),
            "duplicates": st["duplicates_dropped"],
            "rejected": st["rejected_payloads"],
            "missing_batches": stopped["missing_batches"],
            "max_queue_batches": depth[0],
        }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--role", default="bench", choices=["bench", "publisher"])
    ap.add_argument("--connect")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--batch", type=int, default=200, help="readings per batch")
    ap.add_argument("--sensors", type=int, default=12, help="streams (sensor MACs)")
    ap.add_argument("--rate", type=float, default=0.0, help="readings/s to publish (0 = unpaced)")
    ap.add_argument(
        "--rounds", type=int, default=3, help="bare/collector pairs (the ratio moves run to run)"
    )
    args = ap.parse_args()
    if args.role == "publisher":
        publisher(args.connect, args.seconds, args.batch, args.sensors, args.rate)
        return
    pace = f"paced at {args.rate:,.0f} readings/s" if args.rate > 0 else "unpaced"
    print(
        f"publisher: {args.seconds:.0f} s, {pace}, batches of {args.batch} readings over "
        f"{args.sensors} sensors; {args.rounds} round(s), each a bare subscriber then the collector"
    )
    ratios = []
    for k in range(args.rounds):
        b = bare(args)
        c = collector(args)
        ratios.append(c["rate"] / b["rate"])
        print(
            f"round {k + 1}: bare zenoh subscriber {b['rate']:>9,} readings/s "
            f"({b['received']:,} of {b['published']:,} in {b['seconds']} s); "
            f"collector (in files) {c['rate']:>9,} readings/s "
            f"({c['lines_in_files']:,} of {c['published']:,} in {c['seconds']} s): {ratios[-1]:.2f}x"
        )
        print(
            f"         collector loss {c['lost']} readings; missing batches {c['missing_batches']}; "
            f"duplicates dropped {c['duplicates']}; rejected {c['rejected']}; "
            f"deepest receive queue {c['max_queue_batches']} batches"
        )
    print(
        f"collector / bare subscriber: median {statistics.median(ratios):.2f}x, "
        f"lowest {min(ratios):.2f}x over {len(ratios)} round(s)"
    )


if __name__ == "__main__":
    main()
