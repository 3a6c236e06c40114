"""What mutual TLS and the generated ACL cost on the agent -> collector link.

Publishes realistic reading batches (wire.to_wire, 100 readings each) from a client to a router
on loopback and times until the router's subscriber has them all, for: plain TCP, mTLS, and
mTLS + ACL (the production setup). Prints batches/s and readings/s per setup.

    python bench/deploy_link_overhead.py [--batches 50000] [--readings 100] [--repeat 3]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config
from deploy import pki
from deploy.acl import build_acl

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))
from loopback import free_port  # noqa: E402 - the tests' port helper, on the path above

SITE = "default"


def make_payload(seq: int, n: int) -> bytes:
    t0 = 1_763_780_000 * 10**9
    readings = tuple(
        wire.Reading(t_ns=t0 + i * 1_000_000, mono_ns=0, beacon="e78f135624ce", rssi=-60 - i % 30)
        for i in range(n)
    )
    return wire.to_wire(
        wire.Batch(
            agent_id="a1",
            boot_id="0123456789abcdef",
            sensor="aabbccddee01",
            seq=seq,
            readings=readings,
        )
    )


def run(setup: str, d: Path, batches: int, per_batch: int) -> float:
    def tls(cn: str) -> TlsFiles:
        return TlsFiles(str(d / "ca.crt"), str(d / f"{cn}.crt"), str(d / f"{cn}.key"))

    proto = "tcp" if setup == "plain tcp" else "tls"
    ep = f"{proto}/127.0.0.1:{free_port()}"
    acl = (
        json.dumps(build_acl(SITE, ["a1"], ["collector", "operator"]))
        if setup == "mtls + acl"
        else None
    )
    rtls, ctls = (None, None) if proto == "tcp" else (tls("collector"), tls("a1"))
    router = zenoh.open(build_config(SessionSpec(mode="router", listen=[ep], tls=rtls, acl=acl)))
    got = 0
    done = threading.Event()

    def on_sample(_s: zenoh.Sample) -> None:
        nonlocal got
        got += 1
        if got >= batches:
            done.set()

    sub = router.declare_subscriber(wire.data_selector(SITE), on_sample)
    client = zenoh.open(build_config(SessionSpec(mode="client", connect=[ep], tls=ctls)))
    key = wire.data_key(SITE, "a1", "aabbccddee01")
    pub = client.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    payloads = [make_payload(i, per_batch) for i in range(batches)]
    # Warm up until the route exists, let stragglers land, then count only the timed batches.
    while got == 0:
        pub.put(payloads[0])
        time.sleep(0.05)
    time.sleep(0.2)
    got = 0
    t0 = time.perf_counter()
    for p in payloads:
        pub.put(p)
    ok = done.wait(120)
    elapsed = time.perf_counter() - t0
    for obj in (pub, sub):
        obj.undeclare()
    client.close()
    router.close()
    if not ok:
        raise SystemExit(f"{setup}: only {got} of {batches} batches arrived")
    return elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=50000)
    ap.add_argument("--repeat", type=int, default=3, help="runs per setup; the median is shown")
    ap.add_argument("--readings", type=int, default=100, help="readings per batch")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        now = dt.datetime.now(dt.UTC)
        pki.issue(d, "collector", ["collector", "127.0.0.1"], now)
        pki.issue(d, "a1", ["a1"], now)
        size = len(make_payload(0, args.readings))
        print(f"{args.batches} batches x {args.readings} readings ({size} bytes each), loopback")
        for setup in ("plain tcp", "mtls", "mtls + acl"):
            el = sorted(run(setup, d, args.batches, args.readings) for _ in range(args.repeat))[
                args.repeat // 2
            ]
            print(
                f"{setup:12s} {el:6.2f} s  {args.batches / el:8.0f} batches/s  "
                f"{args.batches * args.readings / el / 1e3:8.1f} k readings/s"
            )


if __name__ == "__main__":
    main()
