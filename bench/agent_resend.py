"""How fast the agent catches up after an outage: re-sending a spooled backlog over loopback Zenoh.

Builds the backlog an outage of ``--outage-s`` seconds leaves in the spool (12 sensors x 10 Hz,
one reading per batch, as the publisher encodes them), attaches a Publisher to a loopback router
and times one re-send pass until the router has received every batch. Prints batches/s, the
catch-up time per hour of outage, and what the default spool holds.

    python bench/agent_resend.py [--sensors 12] [--hz 10] [--outage-s 600]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, build_config
from sensor_agent.publisher import Publisher, stream_id
from sensor_agent.spool import Spool

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))
from loopback import free_port  # noqa: E402 - the tests' port helper, on the path above

MIB = 1024 * 1024
BOOT = "3f9c2a7be1d04c55"
T0 = 1_790_000_000 * 10**9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", type=int, default=12)
    ap.add_argument("--hz", type=float, default=10.0)
    ap.add_argument("--outage-s", type=float, default=600.0)
    args = ap.parse_args()
    n_per = int(args.hz * args.outage_s)
    total = n_per * args.sensors
    with tempfile.TemporaryDirectory() as tmp:
        spool = Spool(Path(tmp) / "spool", 256 * MIB, fsync_interval_s=None)
        t = time.perf_counter()
        for seq in range(n_per):
            for k in range(args.sensors):
                sensor = f"b827eb{0x4521B0 + k:06x}"
                rows = (
                    wire.Reading(
                        T0 + seq * 100_000_000 + k, "e78f135624ce", -60 - seq % 30, 10**12 + seq
                    ),
                )
                b = wire.Batch("pi-01", BOOT, sensor, seq, rows, sent_ns=T0 + seq, floor=0)
                spool.append(stream_id(BOOT, sensor), seq, wire.to_wire(b))
        spool.sync()
        build_s = time.perf_counter() - t
        st = spool.stats()
        per_batch = st.bytes / total

        ep = f"tcp/127.0.0.1:{free_port()}"
        router = zenoh.open(build_config(SessionSpec(mode="router", listen=[ep])))
        got = 0
        done = threading.Event()
        lock = threading.Lock()

        def on_sample(_s: zenoh.Sample) -> None:
            nonlocal got
            with lock:
                got += 1
                if got >= total:
                    done.set()

        sub = router.declare_subscriber(wire.data_selector("bench"), on_sample)
        client = zenoh.open(build_config(SessionSpec(mode="client", connect=[ep])))
        pub = Publisher(
            client,
            site="bench",
            agent_id="pi-01",
            boot_id="ffffffffffffffff",
            wall_ns=time.time_ns,
            spool=spool,
            resend_s=0.0,
        )
        time.sleep(0.5)  # let the subscription reach the client
        t = time.perf_counter()
        sent = pub.resend_due()
        done.wait(300)
        resend_s = time.perf_counter() - t
        pub.close()
        client.close()
        sub.undeclare()
        router.close()
        spool.close()

    rate = args.sensors * args.hz
    print(
        f"backlog: {args.outage_s:g} s outage x {args.sensors} sensors x {args.hz:g} Hz = "
        f"{total} batches, {st.bytes / MIB:.1f} MiB on disk ({per_batch:.0f} B/batch; "
        f"built in {build_s:.1f} s)"
    )
    print(
        f"re-sent {sent} batches, received {got} in {resend_s:.2f} s = "
        f"{got / resend_s:,.0f} batches/s"
    )
    print(f"catch-up after 1 h of outage: {3600 * rate / (got / resend_s):.0f} s")
    hours = 256 * MIB / per_batch / rate / 3600
    print(f"default spool (256 MiB) covers {hours:.1f} h at this rate before dropping the oldest")


if __name__ == "__main__":
    main()
