"""Issue 11's floods: one misbehaving agent against a `collector serve` process on loopback while
two honest agents record. Shared by tests/collector/test_collector_limits.py (which asserts on
the outcome) and bench/collector_floods.py (which prints it).

Every party is a separate process or Zenoh session: the collector runs as `collector serve`
(optionally under a lower RLIMIT_NOFILE), the honest agents and the flooder are client sessions.
With `pki_dir` the collector listens on tls/... with mutual TLS and the ACL that deploy/
generates, and each agent publishes under its own certificate (the flooder is authenticated too).
"""

from __future__ import annotations

import datetime as dt
import json
import resource
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config
from collector.client import CollectorClient
from collector.errors import CollectorError
from deploy import pki
from deploy.acl import build_acl
from loopback import free_port

T0 = 1_795_318_500 * 10**9
HONEST = (("pi-01", "b827eb000001"), ("pi-02", "b827eb000002"))
FLOODER = "pi-bad"


def flood_mac(i: int) -> str:
    return f"ff{i:010x}"


def status_kb(pid: int, field_name: str) -> int:
    """A `VmRSS`/`VmHWM`-style figure of /proc/<pid>/status in KiB (0 once the process is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def make_site_pki(d: Path) -> Path:
    """A site CA with certificates for the collector, the operator, both honest agents and the flooder."""
    now = dt.datetime.now(dt.UTC)
    pki.issue(d, "collector", ["collector", "localhost", "127.0.0.1"], now)
    for cn in ("operator", FLOODER, *(a for a, _ in HONEST)):
        pki.issue(d, cn, [cn], now)
    return d


def tls_files(pki_dir: Path | None, cn: str) -> TlsFiles | None:
    if pki_dir is None:
        return None
    return TlsFiles(str(pki_dir / "ca.crt"), str(pki_dir / f"{cn}.crt"), str(pki_dir / f"{cn}.key"))


def open_session(ep: str, tls: TlsFiles | None) -> zenoh.Session:
    return zenoh.open(build_config(SessionSpec(mode="client", connect=[ep], tls=tls)))


class Honest:
    """A well-behaved agent: 10 batches/s of 10 readings on one sensor; re-sends whatever is not
    acknowledged (every 2 s while running, on demand afterwards), as a real agent's spool does."""

    def __init__(self, ep: str, agent: str, sensor: str, tls: TlsFiles | None = None) -> None:
        self.agent, self.sensor, self.boot = agent, sensor, f"{abs(hash(agent)) % 16**16:016x}"
        self.session = open_session(ep, tls)
        self.acked = -1
        self.batches: list[bytes] = []
        self.rows: list[str] = []
        self._sub = self.session.declare_subscriber(wire.ack_key("default", agent), self._on_ack)
        self._key = wire.data_key("default", agent, sensor)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        msg = json.loads(sample.payload.to_bytes())
        if msg.get("boot") == self.boot:
            self.acked = max(self.acked, msg["streams"].get(self.sensor, -1))

    def _put(self, payload: bytes) -> None:
        self.session.put(self._key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _loop(self) -> None:
        last_resend = time.monotonic()
        while not self._stop.wait(0.1):
            seq = len(self.batches)
            rs = tuple(
                wire.Reading(T0 + seq * 10**8 + k * 10**6, "e78f135624ce", -50 - k)
                for k in range(10)
            )
            payload = wire.to_wire(wire.Batch(self.agent, self.boot, self.sensor, seq, rs, floor=0))
            self.batches.append(payload)
            self.rows += [f"{wire.format_ts(r.t_ns)},{self.sensor},{r.beacon},{r.rssi}" for r in rs]
            self._put(payload)
            if time.monotonic() - last_resend > 2.0:
                last_resend = time.monotonic()
                self.resend()

    def resend(self) -> None:
        for p in self.batches[self.acked + 1 :]:
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


def flood_macs(ep: str, n: int, tls: TlsFiles | None = None) -> None:
    """One two-reading batch on each of `n` distinct sensor MACs, as fast as the collector takes them."""
    s = open_session(ep, tls)
    try:
        rs = tuple(wire.Reading(T0 + k, "e78f135624ce", -60) for k in range(2))
        for i in range(n):
            mac = flood_mac(i)
            s.put(
                wire.data_key("default", FLOODER, mac),
                wire.to_wire(wire.Batch(FLOODER, "b" * 16, mac, 0, rs, floor=0)),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
    finally:
        s.close()


def flood_maxsize(ep: str, seconds: float, tls: TlsFiles | None = None) -> int:
    """Maximum-size batches (wire.MAX_READINGS readings) for `seconds`; returns how many were sent."""
    s = open_session(ep, tls)
    rs = tuple(wire.Reading(T0 + k, "e78f135624ce", -60) for k in range(wire.MAX_READINGS))
    sent = 0
    end = time.monotonic() + seconds
    mac = flood_mac(0)
    try:
        while time.monotonic() < end:
            payload = wire.to_wire(wire.Batch(FLOODER, "b" * 16, mac, sent, rs, floor=0))
            s.put(
                wire.data_key("default", FLOODER, mac),
                payload,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            sent += 1
    finally:
        s.close()
    return sent


@dataclass
class HonestOutcome:
    readings: int  # what the agent published
    lost: int  # of those, missing from its run file
    dup: int  # extra copies in its run file
    foreign: int  # rows in its run file that it never published
    batches: int  # batches published
    acked: int  # highest seq acknowledged (batches - 1 when settled)


@dataclass
class FloodOutcome:
    kind: str
    flood: str  # what was sent, in words
    flood_s: float
    drain_s: float  # flood end -> every honest batch acknowledged
    stop_s: float  # `collector stop` round trip
    shutdown_s: float  # SIGINT -> process exit
    rss_peak_kib: int  # VmRSS sampled every 50 ms
    hwm_kib: int  # the kernel's VmHWM, last read before the process exited
    returncode: int | None
    stderr: str
    honest: dict[str, HonestOutcome]
    status: dict  # `collector status` after the drain
    status_bytes: int
    run_dir: Path
    flood_files: int  # .mbd files written for the flooder
    settled: bool  # every honest batch was acknowledged before the drain deadline
    extra: dict = field(default_factory=dict)

    def summary(self) -> str:
        """One line of figures: what the tests print (run them with -s) and the bench expands on."""
        honest = ", ".join(
            f"{a} {h.readings} readings lost {h.lost} dup {h.dup}" for a, h in self.honest.items()
        )
        return (
            f"{self.kind}: {self.flood}; RSS peak {self.rss_peak_kib / 1024:.1f} MiB "
            f"(VmHWM {self.hwm_kib / 1024:.1f}); {honest}; drain {self.drain_s} s; "
            f"stop {self.stop_s} s; exit {self.shutdown_s} s; refused {self.status['refused_streams']}"
        )


def _wait_reachable(
    ep: str, proc: subprocess.Popen, tls: TlsFiles | None, timeout: float = 30
) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with CollectorClient(ep, connect_timeout_s=0.5, tls=tls) as c:
                c.status()
            return
        except CollectorError:
            if proc.poll() is not None:
                raise RuntimeError(f"collector serve exited: {proc.stderr.read()}") from None
            if time.monotonic() > deadline:
                raise RuntimeError("collector serve did not answer within 30 s") from None
            time.sleep(0.2)


def _write_config(workdir: Path, ep: str, limits: dict | None, pki_dir: Path | None) -> Path:
    """collector.yaml (and, with a PKI, the ACL file) for `collector serve` on `ep`."""
    cfg = workdir / "collector.yaml"
    text = f"data_dir: data\nlisten: [{ep}]\n"
    if limits:
        text += f"limits: {json.dumps(limits)}\n"
    if pki_dir:
        acl = workdir / "acl.json5"
        acl.write_text(
            json.dumps(
                build_acl("default", [FLOODER, *(a for a, _ in HONEST)], ["collector", "operator"])
            )
        )
        col = tls_files(pki_dir, "collector")
        text += f"tls: {json.dumps({'root_ca': col.root_ca, 'cert': col.cert, 'key': col.key})}\n"
        text += f"acl: {json.dumps(str(acl))}\n"
    cfg.write_text(text)
    return cfg


def _flood(
    kind: str, ep: str, macs: int, seconds: float, nofile: int | None, bad: TlsFiles | None
) -> str:
    """Run the flood of `kind`; a description of what was sent."""
    if kind == "macs":
        flood_macs(ep, macs, bad)
        return f"{macs} MACs, RLIMIT_NOFILE {nofile or 'unchanged'}"
    if kind == "maxsize":
        n = flood_maxsize(ep, seconds, bad)
        return f"{n} batches of {wire.MAX_READINGS} readings in {seconds:g} s"
    raise ValueError(f"unknown flood {kind!r}")


def _drain(honest: list[Honest], timeout_s: float) -> None:
    """Let the honest agents re-send until everything is acknowledged or `timeout_s` passes."""
    deadline = time.monotonic() + timeout_s
    while not all(h.settled() for h in honest) and time.monotonic() < deadline:
        for h in honest:
            h.resend()
        time.sleep(0.5)


def _wait_counted(c: CollectorClient, batches: int, timeout_s: float = 60) -> None:
    """Wait until the collector has refused or admitted `batches` streams' first batches."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = c.status()
        if st["refused_streams"]["batches"] + st["streams"]["admitted"] >= batches:
            return
        time.sleep(0.2)


def _interrupt(proc: subprocess.Popen) -> tuple[str, float]:
    """SIGINT the collector; its stderr and seconds to exit (-1.0, and its threads' stacks, when
    it does not exit within 60 s)."""
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    try:
        _out, err = proc.communicate(timeout=60)
        return err, time.monotonic() - t0
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            _out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            _out, err = proc.communicate()
        return f"collector serve still running 60 s after SIGINT; its threads:\n{err}", -1.0


def _honest_outcome(run_dir: Path, h: Honest) -> HonestOutcome:
    """What the run recorded of one honest agent against what it sent."""
    f = run_dir / "rssi" / h.agent / f"{h.sensor}.mbd"
    got = Counter(f.read_text().splitlines()) if f.exists() else Counter()
    sent = set(h.rows)
    return HonestOutcome(
        len(h.rows),
        len(sent - got.keys()),
        sum(c - 1 for c in got.values() if c > 1),
        sum(c for k, c in got.items() if k not in sent),
        len(h.batches),
        h.acked,
    )


def run_flood(
    kind: str,
    workdir: Path,
    *,
    macs: int = 5000,
    seconds: float = 20.0,
    nofile: int | None = None,
    limits: dict | None = None,
    pki_dir: Path | None = None,
    drain_timeout_s: float = 300.0,
) -> FloodOutcome:
    """Start `collector serve` in `workdir`, record a run with two honest agents, flood it from a
    third (kind "macs": one batch on each of `macs` MACs; "maxsize": maximum-size batches for
    `seconds`), let the honest agents re-send until everything is acknowledged, stop the run,
    SIGINT the collector, and measure everything on the way."""
    port = free_port()
    ep = f"tls/127.0.0.1:{port}" if pki_dir else f"tcp/127.0.0.1:{port}"
    cfg = _write_config(workdir, ep, limits, pki_dir)
    op = tls_files(pki_dir, "operator")

    def limit_fds() -> None:
        if nofile:
            resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

    # -X faulthandler: a collector that does not exit is sent SIGABRT below and prints every
    # thread's stack to stderr, which the outcome carries.
    proc = subprocess.Popen(
        [
            sys.executable,
            "-X",
            "faulthandler",
            "-m",
            "collector.cli",
            "serve",
            "--config",
            str(cfg),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=limit_fds,
    )
    peak, hwm = [0], [0]
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.wait(0.05) and proc.returncode is None:
            peak[0] = max(peak[0], status_kb(proc.pid, "VmRSS"))
            hwm[0] = max(hwm[0], status_kb(proc.pid, "VmHWM"))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    honest: list[Honest] = []
    try:
        _wait_reachable(ep, proc, op)
        with CollectorClient(ep, tls=op) as c:
            c.start(kind)
        honest = [Honest(ep, a, s, tls_files(pki_dir, a)) for a, s in HONEST]
        for h in honest:
            h.start()
        time.sleep(1.0)
        t_flood = time.monotonic()
        flood = _flood(kind, ep, macs, seconds, nofile, tls_files(pki_dir, FLOODER))
        t_end = time.monotonic()
        time.sleep(1.0)
        for h in honest:
            h.stop()
        _drain(honest, drain_timeout_s)
        drain_s = time.monotonic() - t_end
        settled = all(h.settled() for h in honest)
        with CollectorClient(ep, tls=op) as c:
            if (
                kind == "macs"
            ):  # the flood's last batches may still be queued behind the honest ones
                _wait_counted(c, macs + len(honest))
            st = c.status()
            status_bytes = len(json.dumps({"ok": True, **st}).encode())
            t0 = time.monotonic()
            stopped = c.stop()
            stop_s = time.monotonic() - t0
    finally:
        for h in honest:
            h.close()
        err, shutdown_s = _interrupt(proc)
        sampling.set()
        sampler.join()
    run_dir = Path(stopped["run_dir"])
    outcomes = {h.agent: _honest_outcome(run_dir, h) for h in honest}
    flood_dir = run_dir / "rssi" / FLOODER
    return FloodOutcome(
        kind,
        flood,
        round(t_end - t_flood, 2),
        round(drain_s, 2),
        round(stop_s, 2),
        round(shutdown_s, 2),
        peak[0],
        hwm[0],
        proc.returncode,
        err,
        outcomes,
        st,
        status_bytes,
        run_dir,
        len(list(flood_dir.glob("*.mbd"))),
        settled,
    )
