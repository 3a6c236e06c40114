"""One misbehaving agent against `collector serve` on loopback, while two honest agents record.

    python bench/collector_floods.py [--scenario macs|maxsize|both] [--macs 5000] [--seconds 20]
                                     [--nofile 1024] [--streams-per-agent N] [--streams-total N]

Scenarios (issue 11):
  macs     the flooder publishes one batch on each of `--macs` distinct sensor MACs, under a
           RLIMIT_NOFILE of `--nofile` for the collector;
  maxsize  the flooder publishes maximum-size batches (100,000 readings) as fast as the
           collector takes them for `--seconds`.
Meanwhile two honest agents publish 10 batches/s of 10 readings each and re-send whatever is
not acknowledged, as a real agent's spool does.

Prints per scenario: the collector's peak RSS (sampled every 50 ms, and VmHWM), honest readings
lost and duplicated in the run files, the time from the end of the flood until every honest
batch is acknowledged (drain), the time `collector stop` took, the refused-stream and rejected
counts from `collector status`, and the size of that status reply.
"""

from __future__ import annotations

import argparse
import json
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import zenoh

from ble_groundtruth import wire
from ble_groundtruth.zenoh_config import SessionSpec, build_config
from collector.client import CollectorClient

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from loopback import free_port  # noqa: E402 - the tests' port helper, on the path above

T0 = 1_795_318_500 * 10**9


def status_kb(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


class Honest:
    """A well-behaved agent: steady batches on one sensor, re-sends what is not acknowledged."""

    def __init__(self, ep: str, agent: str, sensor: str) -> None:
        self.agent, self.sensor, self.boot = agent, sensor, f"{abs(hash(agent)) % 16**16:016x}"
        self.session = zenoh.open(build_config(SessionSpec(mode="client", connect=[ep])))
        self.acked = -1
        self.batches: list[bytes] = []
        self.rows: list[str] = []
        self._sub = self.session.declare_subscriber(wire.ack_key("default", agent), self._on_ack)
        self._key = wire.data_key("default", agent, sensor)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _on_ack(self, sample) -> None:
        msg = json.loads(sample.payload.to_bytes())
        if msg.get("boot") == self.boot:
            self.acked = max(self.acked, msg["streams"].get(self.sensor, -1))

    def _put(self, payload: bytes) -> None:
        self.session.put(self._key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _loop(self) -> None:
        last_resend = time.monotonic()
        while not self._stop.wait(0.1):
            seq = len(self.batches)
            rs = tuple(wire.Reading(T0 + seq * 10**8 + k * 10**6, "e78f135624ce", -50 - k)
                       for k in range(10))
            payload = wire.to_wire(wire.Batch(self.agent, self.boot, self.sensor, seq, rs, floor=0))
            self.batches.append(payload)
            self.rows += [f"{wire.format_ts(r.t_ns)},{self.sensor},{r.beacon},{r.rssi}" for r in rs]
            self._put(payload)
            if time.monotonic() - last_resend > 2.0:
                last_resend = time.monotonic()
                self.resend()

    def resend(self) -> None:
        for p in self.batches[self.acked + 1:]:
            self._put(p)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def settled(self) -> bool:
        return self.acked == len(self.batches) - 1

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def flood_macs(ep: str, n: int) -> None:
    s = zenoh.open(build_config(SessionSpec(mode="client", connect=[ep])))
    try:
        for i in range(n):
            mac = f"ff{i:010x}"
            rs = tuple(wire.Reading(T0 + k, "e78f135624ce", -60) for k in range(2))
            s.put(wire.data_key("default", "pi-bad", mac),
                  wire.to_wire(wire.Batch("pi-bad", "b" * 16, mac, 0, rs, floor=0)),
                  congestion_control=zenoh.CongestionControl.BLOCK)
    finally:
        s.close()


def flood_maxsize(ep: str, seconds: float) -> int:
    s = zenoh.open(build_config(SessionSpec(mode="client", connect=[ep])))
    rs = tuple(wire.Reading(T0 + k, "e78f135624ce", -60) for k in range(wire.MAX_READINGS))
    sent = 0
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            payload = wire.to_wire(wire.Batch("pi-bad", "b" * 16, "ff0000000000", sent, rs, floor=0))
            s.put(wire.data_key("default", "pi-bad", "ff0000000000"), payload,
                  congestion_control=zenoh.CongestionControl.BLOCK)
            sent += 1
    finally:
        s.close()
    return sent


def scenario(name: str, args: argparse.Namespace) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="bgt-flood-"))
    limits = {}
    if args.streams_per_agent:
        limits["streams_per_agent"] = args.streams_per_agent
    if args.streams_total:
        limits["streams_total"] = args.streams_total
    cfg = tmp / "collector.yaml"
    cfg.write_text(f"data_dir: data\nlisten: [{ep}]\n" + (f"limits: {json.dumps(limits)}\n" if limits else ""))

    def low_nofile() -> None:
        if name == "macs":
            resource.setrlimit(resource.RLIMIT_NOFILE, (args.nofile, args.nofile))

    proc = subprocess.Popen([sys.executable, "-m", "collector.cli", "serve", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=low_nofile)
    peak = [0]
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.wait(0.05):
            peak[0] = max(peak[0], status_kb(proc.pid, "VmRSS"))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out: dict = {"scenario": name}
    honest: list[Honest] = []
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                with CollectorClient(ep, connect_timeout_s=0.5) as c:
                    c.status()
                break
            except Exception:  # noqa: BLE001 - not up yet
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise SystemExit(f"collector did not start: {proc.stderr.read()}") from None
                time.sleep(0.2)
        with CollectorClient(ep) as c:
            c.start(name)
        honest = [Honest(ep, "pi-01", "b827eb000001"), Honest(ep, "pi-02", "b827eb000002")]
        for h in honest:
            h.start()
        time.sleep(1.0)
        t_flood = time.monotonic()
        if name == "macs":
            flood_macs(ep, args.macs)
            out["flood"] = f"{args.macs} MACs, RLIMIT_NOFILE {args.nofile}"
        else:
            n = flood_maxsize(ep, args.seconds)
            out["flood"] = f"{n} batches of {wire.MAX_READINGS} readings in {args.seconds:g} s"
        t_end = time.monotonic()
        out["flood_s"] = round(t_end - t_flood, 2)
        time.sleep(1.0)
        for h in honest:
            h.stop()
        deadline = time.monotonic() + 300
        while not all(h.settled() for h in honest) and time.monotonic() < deadline:
            for h in honest:
                h.resend()
            time.sleep(0.5)
        out["drain_s"] = round(time.monotonic() - t_end, 2)
        with CollectorClient(ep) as c:
            st = c.status()
            out["status_bytes"] = len(json.dumps(st))
            t0 = time.monotonic()
            stopped = c.stop()
            out["stop_s"] = round(time.monotonic() - t0, 2)
        out["refused_streams"] = st["refused_streams"]
        out["rejected"] = st["rejected_payloads"]
        out["queue_overflow"] = st["queue_overflow"]
        run_dir = Path(stopped["run_dir"])
        for h in honest:
            f = run_dir / "rssi" / h.agent / f"{h.sensor}.mbd"
            got = Counter(f.read_text().splitlines()) if f.exists() else Counter()
            exp = set(h.rows)
            out[f"{h.agent}_lost"] = len(exp - got.keys())
            out[f"{h.agent}_dup"] = sum(c - 1 for c in got.values() if c > 1)
            out[f"{h.agent}_readings"] = len(h.rows)
    finally:
        for h in honest:
            h.close()
        sampling.set()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(120)
        except subprocess.TimeoutExpired:
            proc.kill()
        out["shutdown_s"] = round(time.monotonic() - t0, 2)
        out["hwm_mib"] = round(status_kb(proc.pid, "VmHWM") / 1024, 1)
    out["rss_peak_mib"] = round(peak[0] / 1024, 1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", choices=("macs", "maxsize", "both"), default="both")
    ap.add_argument("--macs", type=int, default=5000)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--nofile", type=int, default=1024)
    ap.add_argument("--streams-per-agent", type=int, default=0, help="limits.streams_per_agent (default: the collector's)")
    ap.add_argument("--streams-total", type=int, default=0, help="limits.streams_total (default: the collector's)")
    args = ap.parse_args()
    for name in (("macs", "maxsize") if args.scenario == "both" else (args.scenario,)):
        r = scenario(name, args)
        print(f"{name}: {r['flood']} (flood {r['flood_s']} s)")
        print(f"  collector RSS peak {r['rss_peak_mib']} MiB (sampled every 50 ms)")
        for a in ("pi-01", "pi-02"):
            print(f"  honest {a}: {r[f'{a}_readings']} readings, lost {r[f'{a}_lost']}, "
                  f"duplicated {r[f'{a}_dup']}")
        print(f"  drain (flood end -> every honest batch acknowledged) {r['drain_s']} s; "
              f"collector stop {r['stop_s']} s; SIGINT to exit {r['shutdown_s']} s")
        print(f"  refused streams {r['refused_streams']}; rejected {r['rejected']}; "
              f"queue overflow {r['queue_overflow']}; status reply {r['status_bytes']} bytes")


if __name__ == "__main__":
    main()
