"""The operator console under a large fleet: 100 sensors x 10 readings/s into a real collector, the
console (`collector web`, its own process) polling it, and a page's event stream read here.

Prints the console process's CPU (share of one core), the size of each pushed message, and how
old each snapshot is when the page receives it (median and max); the server aggregates, so the
page gets one message a second whatever the reading rate.

    python bench/console_scale.py [--seconds 30] [--sensors 100] [--rate 10] [--browser]

With --browser the page is also opened in a real headless chromium (driven over DevTools) and
the redraw is timed there: how old each snapshot is when the browser has painted it, and how
long the page's drawing takes (from the message's arrival to the next frame).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))
from collector.config import CollectorConfig  # noqa: E402
from collector.service import Collector  # noqa: E402
from collector_helpers import FakeAgent, make_batch, with_floor  # noqa: E402
from loopback import free_port  # noqa: E402

# Wraps the page's message handler: each snapshot's age (server time to the frame that shows it)
# and the time from its arrival to that frame.
HOOK = """
window.bgtRedraw = [];
const bgtOriginal = events.onmessage;
events.onmessage = (ev) => {
  const t0 = performance.now();
  bgtOriginal(ev);
  const snap = JSON.parse(ev.data);
  requestAnimationFrame(() => window.bgtRedraw.push(
    {age: Date.now() / 1000 - snap.t, draw: performance.now() - t0}));
};
"""


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--sensors", type=int, default=100)
    ap.add_argument("--browser", action="store_true", help="also time the redraw in chromium")
    ap.add_argument("--rate", type=float, default=10.0, help="readings/s per sensor")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data = Path(tempfile.mkdtemp())
    collector = Collector(
        CollectorConfig(data_dir=data / "data", listen=(endpoint,), fsync_interval_s=0.5),
        drain_timeout_s=2.0,
    ).open()
    # A Pi carries a handful of sensors: 25 per agent, as many agents as that takes.
    agents = [FakeAgent(endpoint, agent=f"pi-{k}") for k in range((args.sensors + 24) // 25)]
    for a in agents:
        a.declare_token()
    macs = [f"0000000{i:05x}" for i in range(args.sensors)]
    stop = threading.Event()

    def publish() -> None:  # one reading per sensor per tick, args.rate ticks a second
        seq, t_next = 0, time.monotonic()
        while not stop.is_set():
            for i, mac in enumerate(macs):
                a = agents[i // 25]
                a.put(with_floor(make_batch(seq, n=1, agent=a.agent, sensor=mac), 0))
            seq += 1
            t_next += 1 / args.rate
            time.sleep(max(0.0, t_next - time.monotonic()))

    threading.Thread(target=publish, daemon=True).start()
    port = free_port()
    exe = Path(sys.executable).parent / "collector"
    web = subprocess.Popen(
        [str(exe), "web", "--connect", endpoint, "--listen", f"127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    lags: list[float] = []
    sizes: list[int] = []
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                stream = urllib.request.urlopen(f"http://127.0.0.1:{port}/events", timeout=10)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.3)
        with contextlib.ExitStack() as stack:
            page = None
            if args.browser:
                from cdp import browser_page

                page = stack.enter_context(browser_page(f"http://127.0.0.1:{port}/", free_port()))
                time.sleep(2)  # the page loaded, its stream open
                page.evaluate(HOOK)
            cpu0, t0 = cpu_seconds(web.pid), time.monotonic()
            while time.monotonic() - t0 < args.seconds:
                line = stream.readline().decode()
                if line.startswith("data: "):
                    snap = json.loads(line[6:])
                    if "t" in snap:
                        lags.append(time.time() - snap["t"])
                        sizes.append(len(line))
            cpu = (cpu_seconds(web.pid) - cpu0) / (time.monotonic() - t0)
            painted = page.evaluate("JSON.stringify(window.bgtRedraw)") if page else None
        heard = sum(len(a["sensors"]) for a in snap.get("agents", []))
    finally:
        stop.set()
        stream.close()
        web.terminate()
        web.wait(10)
        for a in agents:
            a.close()
        collector.close()
    print(
        f"fleet: {args.sensors} sensors x {args.rate:g} readings/s = "
        f"{args.sensors * args.rate:,.0f} readings/s into the collector; the page shows {heard} sensors"
    )
    print(f"console process CPU: {cpu:.1%} of one core over {args.seconds:g} s")
    print(
        f"messages to the page: {len(lags)} ({len(lags) / args.seconds:.2f}/s), "
        f"{statistics.median(sizes) / 1024:.1f} KiB each (median)"
    )
    print(
        f"snapshot age at the page: median {statistics.median(lags) * 1000:.0f} ms, "
        f"max {max(lags) * 1000:.0f} ms"
    )
    if painted is not None:
        rows = json.loads(str(painted))
        ages = [r["age"] for r in rows]
        draws = [r["draw"] for r in rows]

        def p95(v: list[float]) -> float:
            return sorted(v)[min(len(v) - 1, int(0.95 * len(v)))]

        print(
            f"in chromium ({len(rows)} messages): snapshot age when painted median "
            f"{statistics.median(ages) * 1000:.0f} ms, p95 {p95(ages) * 1000:.0f} ms, max "
            f"{max(ages) * 1000:.0f} ms; drawing median {statistics.median(draws):.1f} ms, p95 "
            f"{p95(draws):.1f} ms, max {max(draws):.1f} ms"
        )


if __name__ == "__main__":
    main()
