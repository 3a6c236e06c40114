"""Bench: CPU and memory of a real `sensor-agent run` replaying 200 adverts/s.

Writes a synthetic recording (4 sensors x 50 adverts/s by default), opens a Zenoh router
session in this process (no collector: a plain subscriber counts what arrives), starts the
agent as a child process and samples its /proc entries. Targets: CPU <= 5 % of one core,
RSS <= 80 MB.

    python bench/agent_replay.py [--rate 200] [--seconds 40] [--warmup 8]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from bgt_core import wire
from bgt_core.formats.mbd import format_row
from bgt_core.zenoh_config import SessionSpec, build_config

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))
from loopback import free_port  # noqa: E402 - the tests' port helper, on the path above

CLK_TCK = os.sysconf("SC_CLK_TCK")


def write_recording(path: Path, rate: float, seconds: float, sensors: int = 4) -> int:
    """Evenly spaced rows, round-robin over the sensors; returns the row count."""
    t0 = 1_700_000_000 * 10**9
    n = int(rate * seconds)
    step = int(1e9 / rate)
    with path.open("w") as f:
        for i in range(n):
            sensor = f"b827eb0000{i % sensors:02x}"
            f.write(format_row(t0 + i * step, sensor, "e78f135624ce", -60 - (i * 7) % 30))
    return n


def cpu_ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


def status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def agent_command() -> list[str]:
    exe = Path(sys.executable).with_name("sensor-agent")
    if exe.exists():
        return [str(exe)]
    found = shutil.which("sensor-agent")
    return [found] if found else [sys.executable, "-c", "from sensor_agent.cli import main; main()"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=200.0, help="adverts per second (all sensors)")
    ap.add_argument("--seconds", type=float, default=40.0, help="length of the recording")
    ap.add_argument("--warmup", type=float, default=8.0, help="seconds ignored at the start")
    args = ap.parse_args()

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(SessionSpec(mode="router", listen=[endpoint])))
    received = {"batches": 0, "readings": 0, "repeats": 0}
    seen: dict[tuple[str, str], set[int]] = {}  # (boot, sensor) -> seqs

    def on_batch(sample: zenoh.Sample) -> None:
        b = wire.from_wire(sample.payload.to_bytes())
        seqs = seen.setdefault((b.boot_id, b.sensor), set())
        if b.seq in seqs:  # a re-send: counted apart, as the collector would drop it
            received["repeats"] += 1
            return
        seqs.add(b.seq)
        received["batches"] += 1
        received["readings"] += len(b.readings)

    def send_acks() -> None:
        """Acknowledge like the collector (highest contiguous seq per stream), so the agent
        does not re-send what arrived."""
        by_boot: dict[str, dict[str, int]] = {}
        for (boot, sensor), seqs in list(seen.items()):
            n = -1
            while n + 1 in seqs:
                n += 1
            by_boot.setdefault(boot, {})[sensor] = n
        for boot, streams in by_boot.items():
            router.put(
                wire.ack_key("default", "bench"), wire.to_json({"boot": boot, "streams": streams})
            )

    sub = router.declare_subscriber(wire.data_selector("default"), on_batch)
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "bench.mbd"
        rows = write_recording(rec, args.rate, args.seconds)
        log = Path(tmp) / "agent.log"
        cmd = agent_command() + [
            "run",
            "--agent-id",
            "bench",
            "--connect",
            endpoint,
            "--replay",
            str(rec),
            "--replay-speed",
            "1",
            "--no-wait-ack",
        ]
        with log.open("w") as f:
            proc = subprocess.Popen(cmd, stdout=f, stderr=f)
            start = time.monotonic()
            time.sleep(args.warmup)
            t_a, c_a = time.monotonic(), cpu_ticks(proc.pid)
            rss_peak = 0
            end_window = start + args.seconds - 1.0
            while time.monotonic() < end_window and proc.poll() is None:
                rss_peak = max(rss_peak, status_kb(proc.pid, "VmRSS"))
                send_acks()
                time.sleep(0.5)
            t_b, c_b = time.monotonic(), cpu_ticks(proc.pid)
            hwm = status_kb(proc.pid, "VmHWM")
            while proc.poll() is None and time.monotonic() < end_window + 60:
                send_acks()
                time.sleep(0.2)
            rc = proc.wait(10)
        total_s = time.monotonic() - start
        if rc != 0:
            print(log.read_text())
    sub.undeclare()
    router.close()

    cpu_pct = 100.0 * (c_b - c_a) / CLK_TCK / (t_b - t_a)
    print(
        f"replay: {rows} rows at {args.rate:g} adverts/s over {args.seconds:g} s "
        f"(4 sensors, batch 100 ms), agent exit code {rc}, wall {total_s:.1f} s"
    )
    print(
        f"received by the router session: {received['readings']} readings "
        f"in {received['batches']} batches ({received['repeats']} re-sent batches seen again)"
    )
    print(
        f"agent CPU (steady state, {t_b - t_a:.1f} s window): {cpu_pct:.2f} % of one core "
        f"(target <= 5 %)"
    )
    print(
        f"agent RSS: peak sampled {rss_peak / 1024:.1f} MB, VmHWM {hwm / 1024:.1f} MB "
        f"(target <= 80 MB)"
    )
    ok = cpu_pct <= 5.0 and hwm / 1024 <= 80.0 and rc == 0 and received["readings"] == rows
    print("RESULT:", "within targets" if ok else "OUTSIDE targets")


if __name__ == "__main__":
    main()
