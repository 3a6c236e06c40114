"""Harness for the cross-process reliability scenarios (issue 5): real `collector serve` and
`sensor-agent run` processes on loopback Zenoh, faults injected from outside, and a checker
that compares a run's rssi/<agent>/*.mbd files with the exact readings the agents were given.

Both tests/system/test_reliability_scenarios.py and bench/reliability_scenarios.py drive the scenarios below;
the tests assert zero lost / zero duplicated, the bench prints the counts at a larger scale.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import zlib
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from bgt_core import wire
from bgt_core.formats.mbd import format_row, parse_line
from collector.errors import CollectorError
from loopback import free_port  # noqa: F401 - also the bench's port helper
from polling import wait_for

log = logging.getLogger(__name__)

SITE = "default"
BIN = Path(sys.executable).parent


def _command(script: str, module: str) -> list[str]:
    """The console script next to this interpreter, else the same entry point via -c."""
    exe = BIN / script
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-c", f"from {module} import main; main()"]


def wait_until(cond: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    """Poll cond() until it returns something truthy; AssertionError naming `what` at the deadline."""
    return wait_for(cond, timeout, what, step=interval)


def _tail(path: Path, n: int = 40) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return "(no log)"
    return "\n".join(lines[-n:])


# ---------------------------------------------------------------------------------------------
# Deterministic replay inputs


@dataclass(frozen=True, slots=True)
class ReplaySet:
    """Replay files and the exact rows (as the collector must write them) they contain."""

    paths: tuple[Path, ...]
    rows: frozenset[str]  # format_row(...) without the newline
    sensors: tuple[str, ...]
    first_ns: int
    last_ns: int


def sensor_macs(n: int, prefix: str = "b827eb") -> tuple[str, ...]:
    return tuple(f"{prefix}{0x100000 + i:06x}" for i in range(n))


def beacon_macs(n: int) -> tuple[str, ...]:
    return tuple(f"e78f13{0x560000 + i:06x}" for i in range(n))


def make_replay(
    folder: Path,
    *,
    sensors: Sequence[str],
    beacons: Sequence[str],
    rate_hz: float,
    duration_s: float,
    t0_ns: int,
    tag: str = "a",
) -> ReplaySet:
    """One .mbd file per sensor: every beacon heard by every sensor `rate_hz` times a second.

    Timestamps carry small per-sensor/per-beacon offsets so every row of the set is unique, and
    the RSSI follows a fixed pattern, so a row identifies one reading exactly.
    """
    folder.mkdir(parents=True, exist_ok=True)
    period = int(1e9 / rate_hz)
    ticks = int(duration_s * rate_hz)
    rows: set[str] = set()
    paths = []
    last = t0_ns
    for si, s in enumerate(sensors):
        p = folder / f"{tag}-{s}.mbd"
        with p.open("w", encoding="utf-8") as f:
            for i in range(ticks):
                for bi, b in enumerate(beacons):
                    t = t0_ns + i * period + si * 1_000_003 + bi * 10_007
                    line = format_row(t, s, b, -40 - (i * 7 + si * 3 + bi) % 55)
                    f.write(line)
                    rows.add(line.rstrip("\n"))
                    last = max(last, t)
        paths.append(p)
    return ReplaySet(tuple(paths), frozenset(rows), tuple(sensors), t0_ns, last)


# ---------------------------------------------------------------------------------------------
# Processes


class Proc:
    """One child process with its own log file; killed (whole group) on close."""

    def __init__(self, argv: list[str], log_path: Path, env: dict[str, str] | None = None) -> None:
        self.argv = argv
        self.log_path = log_path
        self.env = env
        self.p: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        fh = self.log_path.open("ab")
        env = dict(os.environ, **(self.env or {}))
        env.setdefault("PYTHONUNBUFFERED", "1")
        self.p = subprocess.Popen(
            self.argv, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
        fh.close()

    @property
    def pid(self) -> int:
        assert self.p is not None
        return self.p.pid

    def alive(self) -> bool:
        return self.p is not None and self.p.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.kill(self.pid, sig)

    def kill9(self) -> None:
        if self.p is not None and self.p.poll() is None:
            os.kill(self.pid, signal.SIGKILL)
            self.p.wait(10)

    def wait(self, timeout: float) -> int:
        assert self.p is not None
        try:
            return self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{self.argv[0]} still running after {timeout:g} s; log:\n{self.tail()}"
            ) from None

    def terminate(self, timeout: float = 30.0) -> int | None:
        """SIGCONT (in case it is stopped) + SIGTERM, then SIGKILL if it does not go."""
        if self.p is None:
            return None
        if self.p.poll() is None:
            os.kill(self.pid, signal.SIGCONT)
            os.kill(self.pid, signal.SIGTERM)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill9()
        return self.p.returncode

    def tail(self, n: int = 40) -> str:
        return _tail(self.log_path, n)


class CollectorProc(Proc):
    """`collector serve` on a fixed port and data directory; restartable."""

    def __init__(
        self, data_dir: Path, port: int, logs: Path, site: str = SITE, config: Path | None = None
    ) -> None:
        self.data_dir, self.port, self.site = data_dir, port, site
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.starts = 0
        argv = [
            *_command("collector", "collector.cli"),
            "serve",
            "--data-dir",
            str(data_dir),
            "--listen",
            self.endpoint,
            "--site",
            site,
        ]
        if config is not None:
            argv += ["--config", str(config)]
        super().__init__(argv, logs / "collector.log")

    def start(self, timeout: float = 60.0) -> None:
        self.starts += 1
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("a") as f:
            f.write(f"===== start #{self.starts} at {time.time():.3f}\n")
        super().start()
        wait_until(lambda: not self.alive() or self.listening(), timeout, "collector to listen")
        if not self.alive():
            raise AssertionError(f"collector exited at start:\n{self.tail()}")
        wait_until(self._answers, timeout, "collector to answer status")

    def listening(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                return True
        except OSError:
            return False

    def _answers(self) -> bool:
        try:
            self.control("status")
            return True
        except Exception:  # noqa: BLE001 - not up yet, whatever the reason
            return False

    def control(self, cmd: str, request: dict[str, Any] | None = None) -> dict[str, Any]:
        from collector.client import CollectorClient

        with CollectorClient(self.endpoint, self.site, connect_timeout_s=5.0) as c:
            return c.call(cmd, request)


class AgentProc(Proc):
    """`sensor-agent run` with a YAML config (replay backend, spool dir) written by the harness."""

    def __init__(
        self,
        folder: Path,
        *,
        agent_id: str,
        endpoint: str,
        replay: Iterable[Path],
        spool_dir: Path | None,
        speed: float = 1.0,
        ack_timeout_s: float = 60.0,
        spool_max_mb: int = 256,
        name: str = "agent",
        site: str = SITE,
    ) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.spool_dir = spool_dir
        cfg = {
            "agent_id": agent_id,
            "site": site,
            "connect": [endpoint],
            "backend": "replay",
            "batch_ms": 100,
            "replay": {"paths": [str(p) for p in replay], "speed": speed, "keep_time": True},
            "spool": {"dir": None if spool_dir is None else str(spool_dir), "max_mb": spool_max_mb},
            "status_interval_s": 1,
            "ack_timeout_s": ack_timeout_s,
        }
        self.config = folder / f"{name}.yaml"
        self.config.write_text(yaml.safe_dump(cfg, sort_keys=False), encoding="utf-8")
        super().__init__(
            [*_command("sensor-agent", "sensor_agent.cli"), "run", "--config", str(self.config)],
            folder / f"{name}.log",
        )


# ---------------------------------------------------------------------------------------------
# Reading what ended up on disk


@dataclass
class Tally:
    """How a run's rssi files compare with the readings that should be in them."""

    expected: int = 0
    recorded: int = 0  # lines that parse, counting duplicates
    lost: int = 0  # expected readings not in any file
    duplicated: int = 0  # extra copies of readings that are in a file
    unexpected: int = 0  # lines that are not an expected reading
    torn: int = 0  # lines that do not parse, or a last line without a newline
    lost_examples: list[str] = field(default_factory=list)
    dup_examples: list[str] = field(default_factory=list)
    unexpected_examples: list[str] = field(default_factory=list)

    def ok(self) -> bool:
        return not (self.lost or self.duplicated or self.unexpected or self.torn)

    def __str__(self) -> str:
        s = (
            f"expected {self.expected}, recorded {self.recorded}, lost {self.lost}, "
            f"duplicated {self.duplicated}, unexpected {self.unexpected}, torn {self.torn}"
        )
        for label, ex in (
            ("lost e.g.", self.lost_examples),
            ("duplicated e.g.", self.dup_examples),
            ("unexpected e.g.", self.unexpected_examples),
        ):
            if ex:
                s += f"\n  {label} {ex[:3]}"
        return s


def read_rows(run_dir: Path, sensors: Iterable[str] | None = None) -> tuple[Counter[str], int]:
    """Every row of the run's rssi files (only these sensors' files if given) and the torn count."""
    files = sorted((run_dir / "rssi").glob("*/*.mbd"))
    if sensors is not None:
        wanted = set(sensors)
        files = [f for f in files if f.stem in wanted]
    rows: Counter[str] = Counter()
    torn = 0
    for f in files:
        data = f.read_bytes().decode("utf-8", errors="replace")
        lines = data.split("\n")
        if lines and lines[-1] != "":
            torn += 1  # a last line without its newline
        for line in lines[:-1]:
            if not line.strip():
                continue
            try:
                r = parse_line(line)
            except ValueError:
                torn += 1
                continue
            if r.sensor != f.stem:
                torn += 1  # a row in another sensor's file is as broken as a torn one
                continue
            rows[line.strip()] += 1
    return rows, torn


def tally(
    run_dir: Path,
    expected: Iterable[str],
    sensors: Iterable[str] | None = None,
    allowed: Iterable[str] = (),
) -> Tally:
    """Compare the run's rows with `expected` (each must appear exactly once).

    `allowed` rows may appear at most once without counting as unexpected (readings that may or
    may not have been taken before a kill -9, for instance)."""
    exp = set(expected)
    ok_extra = set(allowed)
    rows, torn = read_rows(run_dir, sensors)
    t = Tally(expected=len(exp), recorded=sum(rows.values()), torn=torn)
    lost = sorted(exp - rows.keys())
    t.lost, t.lost_examples = len(lost), lost[:5]
    dups = sorted(r for r, c in rows.items() if c > 1)
    t.duplicated = sum(rows[r] - 1 for r in dups)
    t.dup_examples = dups[:5]
    unexp = sorted(r for r in rows if r not in exp and r not in ok_extra)
    t.unexpected, t.unexpected_examples = len(unexp), unexp[:5]
    return t


def count_lines(run_dir: Path) -> int:
    n = 0
    for f in (run_dir / "rssi").glob("*/*.mbd"):
        try:
            n += f.read_bytes().count(b"\n")
        except OSError:
            pass
    return n


def spool_batches(spool_dir: Path) -> list[tuple[str, int, bytes]]:
    """Every whole record in a spool directory's segments, read by the documented format
    (docs/reliability.md), independently of sensor_agent.spool: (stream, seq, payload)."""
    head, rec, body = struct.Struct("<8sHHQ"), struct.Struct("<4sII"), struct.Struct("<qqB")
    out = []
    for seg in sorted(spool_dir.glob("*.seg")):
        data = seg.read_bytes()
        if len(data) < head.size or data[:8] != b"BGTSPOOL":
            continue
        off = head.size
        while off + rec.size <= len(data):
            magic, n, crc = rec.unpack_from(data, off)
            end = off + rec.size + n
            if magic != b"BGTR" or end > len(data) or n < body.size:
                break
            b = data[off + rec.size : end]
            if zlib.crc32(b, zlib.crc32(struct.pack("<I", n))) != crc:
                break
            seq, _t, slen = body.unpack_from(b, 0)
            stream = b[body.size : body.size + slen].decode()
            out.append((stream, seq, b[body.size + slen :]))
            off = end
    return out


def spool_size(spool_dir: Path | None) -> dict[str, float]:
    """Bytes on disk per spooled batch right now (the outage the spool budget covers follows)."""
    if spool_dir is None or not spool_dir.is_dir():
        return {}
    segs = list(spool_dir.glob("*.seg"))
    n = len(spool_batches(spool_dir))
    size = sum(f.stat().st_size for f in segs)
    return {"spool_batches": n, "spool_bytes_per_batch": round(size / n, 1) if n else 0.0}


def batch_rows(payloads: Iterable[bytes]) -> set[str]:
    rows = set()
    for p in payloads:
        b = wire.from_wire(p)
        for r in b.readings:
            rows.add(format_row(r.t_ns, b.sensor, r.beacon, r.rssi).rstrip("\n"))
    return rows


def check_run_files(run_dir: Path) -> list[str]:
    """Problems with the run's metadata files: run.yaml must load, rejected.jsonl lines parse."""
    problems = []
    try:
        meta = yaml.safe_load((run_dir / "run.yaml").read_text(encoding="utf-8"))
        if not isinstance(meta, dict):
            problems.append("run.yaml is not a mapping")
    except (OSError, yaml.YAMLError) as e:
        problems.append(f"run.yaml: {e}")
    rej = run_dir / "rejected.jsonl"
    if rej.exists():
        for i, line in enumerate(rej.read_bytes().split(b"\n")[:-1], 1):
            try:
                json.loads(line)
            except ValueError:
                problems.append(f"rejected.jsonl:{i} does not parse")
    return problems


# ---------------------------------------------------------------------------------------------
# Scenarios


@dataclass
class Result:
    name: str
    tally: Tally
    notes: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    def line(self) -> str:
        t = self.tally
        extra = ", ".join(f"{k} {v}" for k, v in self.notes.items())
        return (
            f"{self.name:<28} expected {t.expected:>7}  lost {t.lost:>5}  duplicated "
            f"{t.duplicated:>5}  unexpected {t.unexpected:>4}  torn {t.torn:>3}"
            + (f"  ({extra})" if extra else "")
        )


@dataclass
class Scale:
    """Sizes of one scenario: the tests use small ones, the bench larger ones."""

    sensors: int = 4
    beacons: int = 3
    rate_hz: float = 10.0
    duration_s: float = 20.0
    speed: float = 1.0


class Rig:
    """A collector plus agents in one folder; everything is stopped by close()."""

    def __init__(
        self, root: Path, data_dir: Path | None = None, spool_root: Path | None = None
    ) -> None:
        self.root = root
        self.spool_root = spool_root or root
        self.logs = root / "logs"
        self.port = free_port()
        self.collector = CollectorProc(data_dir or root / "data", self.port, self.logs)
        self.agents: list[AgentProc] = []

    @property
    def endpoint(self) -> str:
        return self.collector.endpoint

    def agent(
        self,
        replay: Iterable[Path],
        *,
        agent_id: str = "pi-01",
        name: str = "agent",
        spool: bool = True,
        speed: float = 1.0,
        ack_timeout_s: float = 90.0,
    ) -> AgentProc:
        a = AgentProc(
            self.root / "agents",
            agent_id=agent_id,
            endpoint=self.endpoint,
            replay=replay,
            spool_dir=(self.spool_root / f"spool-{agent_id}") if spool else None,
            speed=speed,
            ack_timeout_s=ack_timeout_s,
            name=name,
        )
        self.agents.append(a)
        return a

    def start_run(self, name: str) -> Path:
        reply = self.collector.control("start", {"name": name})
        return Path(reply["run_dir"])

    def stop_run(self) -> dict[str, Any]:
        return self.collector.control("stop")

    def wait_recording(self, run_dir: Path, lines: int, timeout: float = 60.0) -> None:
        wait_until(
            lambda: count_lines(run_dir) >= lines, timeout, f"{lines} rows in {run_dir.name}"
        )

    def wait_agent(self, a: AgentProc, timeout: float) -> int:
        return a.wait(timeout)

    def diagnostics(self) -> str:
        parts = [f"--- collector log ---\n{self.collector.tail()}"]
        parts += [f"--- {a.log_path.name} ---\n{a.tail(25)}" for a in self.agents]
        return "\n".join(parts)

    def close(self) -> None:
        for a in self.agents:
            a.terminate(10)
        self.collector.terminate(30)


def _finish(rig: Rig, run_dir: Path, agent: AgentProc, timeout: float, res: Result) -> None:
    rc = rig.wait_agent(agent, timeout)
    res.notes["agent_exit"] = rc
    if rc != 0:
        res.problems.append(f"agent exited {rc}")
    try:
        stopped = rig.stop_run()
    except CollectorError as e:
        res.problems.append(f"collector stop failed: {e}")
        return
    if Path(stopped["run_dir"]) != run_dir:
        res.problems.append(f"stop closed {stopped['run_dir']}, not the run started ({run_dir})")
    if stopped.get("missing_batches"):
        res.notes["missing_batches"] = stopped["missing_batches"]  # the collector's own count
    res.problems += check_run_files(run_dir)


def collector_outage(
    root: Path,
    scale: Scale,
    *,
    mode: str,
    outage_s: float,
    name: str | None = None,
    fault_at: float = 0.25,
) -> Result:
    """The collector goes away mid-stream for `outage_s` and comes back on the same data dir.

    mode "kill9": kill -9, restart after outage_s. mode "sigstop": SIGSTOP, SIGCONT after
    outage_s (the router is unreachable but its process and TCP sockets stay). The fault comes
    once `fault_at` of the readings are in the run's files."""
    assert mode in ("kill9", "sigstop")
    rig = Rig(root)
    data = make_replay(
        root / "replay",
        sensors=sensor_macs(scale.sensors),
        beacons=beacon_macs(scale.beacons),
        rate_hz=scale.rate_hz,
        duration_s=scale.duration_s,
        t0_ns=time.time_ns(),
    )
    res = Result(name or f"collector {mode} {outage_s:g}s", Tally())
    run_dir: Path | None = None
    try:
        rig.collector.start()
        run_dir = rig.start_run(f"outage-{mode}")
        agent = rig.agent(data.paths, speed=scale.speed)
        agent.start()
        # Fault once `fault_at` of the readings are on disk: well inside the stream.
        rig.wait_recording(
            run_dir, max(1, int(len(data.rows) * fault_at)), timeout=60 + scale.duration_s
        )
        before = count_lines(run_dir)
        if mode == "kill9":
            rig.collector.kill9()
            time.sleep(outage_s)
            res.notes.update(spool_size(agent.spool_dir))
            rig.collector.start()
        else:
            rig.collector.signal(signal.SIGSTOP)
            time.sleep(outage_s)
            res.notes.update(spool_size(agent.spool_dir))
            rig.collector.signal(signal.SIGCONT)
        res.notes["rows_at_fault"] = before
        try:
            run = rig.collector.control("status").get("run") or {}
        except CollectorError as e:
            run = {}
            res.problems.append(f"status after the {mode}: {e}")
        if run.get("run_id") != run_dir.name:
            res.problems.append(
                f"after the {mode} the active run is {run.get('run_id')!r}, not {run_dir.name!r}"
            )
        _finish(rig, run_dir, agent, scale.duration_s / max(scale.speed, 0.1) + 150, res)
    except (AssertionError, CollectorError) as e:
        res.problems.append(f"{e}\n{rig.diagnostics()}")
    finally:
        rig.close()
    if run_dir is not None:
        res.tally = tally(run_dir, data.rows, data.sensors)
    return res


def agent_restart(root: Path, scale: Scale, *, pause_s: float = 2.0) -> Result:
    """kill -9 of a streaming agent; restarted with the same id and spool dir (replaying a second,
    later file): everything in the spool at the kill and everything of the second file arrives
    exactly once.

    The collector is frozen (SIGSTOP) for `pause_s` before the kill and thawed right after it, so
    the agent dies with seconds of unacknowledged batches in its spool, not just the last few."""
    rig = Rig(root)
    sensors, beacons = sensor_macs(scale.sensors), beacon_macs(scale.beacons)
    t0 = time.time_ns()
    first = make_replay(
        root / "replay",
        sensors=sensors,
        beacons=beacons,
        rate_hz=scale.rate_hz,
        duration_s=scale.duration_s,
        t0_ns=t0,
        tag="first",
    )
    second = make_replay(
        root / "replay",
        sensors=sensors,
        beacons=beacons,
        rate_hz=scale.rate_hz,
        duration_s=scale.duration_s / 2,
        t0_ns=first.last_ns + 10**9,
        tag="second",
    )
    res = Result("agent kill9 + restart", Tally())
    run_dir: Path | None = None
    spooled_rows: set[str] = set()
    try:
        rig.collector.start()
        run_dir = rig.start_run("agent-restart")
        a1 = rig.agent(first.paths, speed=scale.speed, name="agent-boot1")
        a1.start()
        rig.wait_recording(run_dir, max(1, len(first.rows) // 3), timeout=60 + scale.duration_s)
        if pause_s > 0:
            rig.collector.signal(signal.SIGSTOP)
            time.sleep(pause_s)
        a1.kill9()
        on_disk_at_kill = sum(read_rows(run_dir)[0].values())
        rig.collector.signal(signal.SIGCONT)
        assert a1.spool_dir is not None
        spooled = spool_batches(a1.spool_dir)
        boots = {s.split("/")[0] for s, _, _ in spooled}
        spooled_rows = batch_rows(p for _, _, p in spooled)
        res.notes.update(
            spooled_batches=len(spooled),
            spooled_rows=len(spooled_rows),
            rows_at_kill=on_disk_at_kill,
        )
        if not spooled_rows:
            res.problems.append("the agent's spool held nothing at the kill (is the spool wired?)")
        a2 = rig.agent(second.paths, speed=scale.speed, name="agent-boot2")
        a2.start()
        _finish(rig, run_dir, a2, scale.duration_s / max(scale.speed, 0.1) + 150, res)
        res.notes["boots_in_spool"] = len(boots)
    except (AssertionError, CollectorError) as e:
        res.problems.append(f"{e}\n{rig.diagnostics()}")
    finally:
        rig.close()
    if run_dir is not None:
        # Rows of the first file that were never spooled could only be in the run if the agent
        # published before spooling (it must not): they count as unexpected.
        res.tally = tally(run_dir, spooled_rows | second.rows, sensors)
    return res


# --- fuzz ------------------------------------------------------------------------------------


def _mutations(rng: Any, valid: bytes) -> list[tuple[str, bytes]]:
    """Kinds of broken payloads, each derived from a valid batch or made from scratch."""
    head = wire.BATCH_HEAD
    magic, ver, mlen, n = head.unpack_from(valid, 0)
    meta = valid[head.size : head.size + mlen]
    body = valid[head.size + mlen :]
    out = []
    flipped = bytearray(valid)
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(flipped))
        flipped[i] ^= 1 << rng.randrange(8)
    out.append(("bitflip", bytes(flipped)))
    out.append(("truncated", valid[: rng.randrange(len(valid))]))
    out.append(
        ("wrong_version", head.pack(magic, rng.choice([0, 2, 7, 65535]), mlen, n) + meta + body)
    )
    out.append(("bad_magic", b"XGTB" + valid[4:]))
    junk_meta = rng.choice(
        [
            b"{not json",
            b"[]",
            b'"x"',
            b"\xff\xfe\x00",
            b'{"agent": 5}',
            b'{"agent":"a","boot":"b","sensor":"zz","seq":-1}',
        ]
    )
    out.append(("garbage_meta", head.pack(magic, ver, len(junk_meta), n) + junk_meta + body))
    out.append(("count_lies", head.pack(magic, ver, mlen, n + rng.randint(1, 1000)) + meta + body))
    out.append(("random_bytes", rng.randbytes(rng.randint(0, 600))))
    out.append(("random_after_magic", b"BGTB" + rng.randbytes(rng.randint(0, 300))))
    out.append(("trailing_junk", valid + rng.randbytes(rng.randint(1, 40))))
    return out


def _absurd(rng: Any, agent: str, boot: str, sensor: str, seq: int) -> tuple[str, bytes]:
    """Valid to the wire format, absurd to a collector: a reading from 2001 or 2099, or RSSI +20."""
    if rng.random() < 0.5:
        t = rng.choice([978_307_200 * 10**9, 4_070_908_800 * 10**9])
        r = wire.Reading(t, "e78f13aaaaaa", -60)
    else:
        r = wire.Reading(time.time_ns(), "e78f13aaaaaa", 20)
    return "absurd", wire.to_wire(wire.Batch(agent, boot, sensor, seq, (r,)))


def _is_invalid(key: str, payload: bytes) -> bool:
    """True when `payload` cannot be taken for a batch of the agent and sensor `key` names."""
    try:
        b = wire.from_wire(payload)
        _, agent, sensor = wire.parse_data_key(key)
    except wire.WireError:
        return True
    return b.agent_id != agent or b.sensor != sensor


# Junk control-query payloads, sent to every command.
_JUNK_QUERIES: tuple[bytes, ...] = (
    b"",
    b"{",
    b"null",
    b"[]",
    b"42",
    b'"stop"',
    b"\xff\xfe",
    b"{}" * 50,
    b'{"name": 5}',
    b'{"name": "../../etc"}',
    b'{"name": "x/y"}',
    b"{" * 500,
    b'{"name": "' + b"n" * 5000 + b'"}',
)


def _junk_query(rng: Any, cmd: str) -> bytes:
    """A junk payload for control command `cmd`; for "stop" never a JSON object, so a
    well-behaved collector refuses it and the run goes on."""
    if rng.random() < 0.3:
        payload = rng.randbytes(rng.randint(1, 300))
    else:
        payload = rng.choice(_JUNK_QUERIES)
    if cmd == "stop":
        try:
            parsed = json.loads(payload) if payload.strip() else {}
        except ValueError:
            parsed = None
        if isinstance(parsed, dict):
            payload = b"\xff" + payload  # never a valid stop request
    return payload


@dataclass
class FuzzStats:
    data_sent: int = 0
    data_invalid: int = 0  # from_wire raises, or agent/sensor differ from the key
    queries_sent: int = 0
    replies: int = 0
    kinds: Counter[str] = field(default_factory=Counter)


def fuzz(
    endpoint: str,
    *,
    agent_id: str,
    valid_sensors: Sequence[str],
    n_data: int,
    n_queries: int,
    seed: int = 1,
    site: str = SITE,
    oversized: int = 2,
    should_stop: Callable[[], bool] = lambda: False,
) -> FuzzStats:
    """Publish `n_data` broken or hostile payloads on data keys and send `n_queries` junk control
    queries. Payloads on the real agent's own keys are always invalid (checked with from_wire),
    so the real stream cannot be impersonated; plausible-looking mutants go to a fuzz identity."""
    import random

    import zenoh

    from bgt_core.zenoh_config import SessionSpec, build_config

    rng = random.Random(seed)
    stats = FuzzStats()
    fuzz_agent, fuzz_boot = "fuzz-agent", "f0f0f0f0f0f0f0f0"
    fuzz_sensors = sensor_macs(2, prefix="fa11ed")
    session = zenoh.open(build_config(SessionSpec(mode="client", connect=[endpoint])))
    try:

        def put(key: str, payload: bytes) -> None:
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

        seq = 0
        while stats.data_sent < n_data and not should_stop():
            seq += 1
            fsensor = rng.choice(fuzz_sensors)
            readings = tuple(
                wire.Reading(time.time_ns(), "e78f13bbbbbb", -50 - k)
                for k in range(rng.randint(1, 5))
            )
            valid = wire.to_wire(wire.Batch(fuzz_agent, fuzz_boot, fsensor, seq, readings))
            cands = _mutations(rng, valid)
            cands.append(_absurd(rng, fuzz_agent, fuzz_boot, fsensor, seq))
            # A well-formed batch that claims the real agent's identity on someone else's key.
            cands.append(
                (
                    "impersonation",
                    wire.to_wire(
                        wire.Batch(agent_id, fuzz_boot, rng.choice(valid_sensors), seq, readings)
                    ),
                )
            )
            for kind, payload in cands:
                if stats.data_sent >= n_data:
                    break
                real_key = wire.data_key(site, agent_id, rng.choice(valid_sensors))
                fuzz_key = wire.data_key(site, fuzz_agent, fsensor)
                if kind == "impersonation":
                    key = fuzz_key
                elif _is_invalid(real_key, payload) and rng.random() < 0.5:
                    key = real_key  # only ever provably broken payloads on the real keys
                else:
                    key = fuzz_key
                put(key, payload)
                stats.data_sent += 1
                stats.kinds[kind] += 1
                stats.data_invalid += _is_invalid(key, payload)
        for _ in range(oversized):
            big = b"BGTB" + b"\x01\x00" + rng.randbytes(wire.MAX_PAYLOAD_BYTES + 1000)
            put(wire.data_key(site, fuzz_agent, fuzz_sensors[0]), big)
            stats.data_sent += 1
            stats.data_invalid += 1
            stats.kinds["oversized"] += 1

        # Control queries: junk for every command (see _junk_query).
        for i in range(n_queries):
            if should_stop():
                break
            cmd = ("start", "stop", "status", "runs", "bogus")[i % 5]
            payload = _junk_query(rng, cmd)
            replies = session.get(
                wire.collector_control_key(site, cmd), payload=payload, timeout=5.0
            )
            stats.queries_sent += 1
            stats.replies += sum(1 for _ in replies)
    finally:
        session.close()
    return stats


def fuzz_scenario(root: Path, scale: Scale, *, n_data: int, n_queries: int) -> Result:
    rig = Rig(root)
    sensors = sensor_macs(scale.sensors)
    data = make_replay(
        root / "replay",
        sensors=sensors,
        beacons=beacon_macs(scale.beacons),
        rate_hz=scale.rate_hz,
        duration_s=scale.duration_s,
        t0_ns=time.time_ns(),
    )
    res = Result("fuzz (data + control keys)", Tally())
    run_dir: Path | None = None
    try:
        rig.collector.start()
        run_dir = rig.start_run("fuzz")
        agent = rig.agent(data.paths, speed=scale.speed)
        agent.start()
        rig.wait_recording(run_dir, 1, timeout=60)
        stats = fuzz(
            rig.endpoint,
            agent_id="pi-01",
            valid_sensors=sensors,
            n_data=n_data,
            n_queries=n_queries,
            should_stop=lambda: not rig.collector.alive(),
        )
        res.notes.update(
            data_sent=stats.data_sent,
            provably_invalid=stats.data_invalid,
            queries=stats.queries_sent,
        )
        if not rig.collector.alive():
            res.problems.append(f"the collector died during the fuzz:\n{rig.collector.tail()}")
            return res
        status = rig.collector.control("status")
        counted = _sum_counts(status.get("rejected_payloads"))
        res.notes["rejected_counted"] = counted
        if counted < stats.data_invalid:
            res.problems.append(
                f"status counts {counted} rejected payloads, but "
                f"{stats.data_invalid} provably invalid ones were sent"
            )
        if (status.get("run") or {}).get("run_id") != run_dir.name:
            res.problems.append("the fuzz stopped or replaced the run")
        _finish(rig, run_dir, agent, scale.duration_s / max(scale.speed, 0.1) + 150, res)
        res.problems += check_rejected(run_dir, min(stats.data_invalid, 200))
        res.notes["rejected_lines"] = _lines(run_dir / "rejected.jsonl")
        reasons = rejected_reasons(run_dir)
        res.notes["reasons"] = dict(sorted(reasons.items()))
        # Bad magic, wrong version, truncated, invalid fields, oversized, absurd readings and
        # key/meta mismatches were all sent: a collector lumping them together counts "per reason"
        # in name only.
        if len(reasons) < 4:
            res.problems.append(f"rejected.jsonl names only these reasons: {sorted(reasons)}")
        if "Traceback" in rig.collector.log_path.read_text(errors="replace"):
            res.problems.append("the collector logged a traceback:\n" + rig.collector.tail(60))
    except (AssertionError, CollectorError) as e:
        res.problems.append(f"{e}\n{rig.diagnostics()}")
    finally:
        rig.close()
    if run_dir is not None:
        res.tally = tally(run_dir, data.rows, sensors)
    return res


def _sum_counts(v: Any) -> int:
    if isinstance(v, bool):
        return 0
    if isinstance(v, int):
        return v
    if isinstance(v, dict):
        return sum(_sum_counts(x) for x in v.values())
    return 0


def _lines(p: Path) -> int:
    return p.read_bytes().count(b"\n") if p.exists() else 0


def rejected_reasons(run_dir: Path) -> Counter[str]:
    out: Counter[str] = Counter()
    p = run_dir / "rejected.jsonl"
    if p.exists():
        for raw in p.read_bytes().split(b"\n")[:-1]:
            try:
                out[str(json.loads(raw).get("reason"))] += 1
            except (ValueError, AttributeError):
                out["(unparseable line)"] += 1
    return out


REJECT_FIELDS = ("at_ns", "key", "reason", "error", "size", "payload_b64")


def check_rejected(run_dir: Path, at_least: int) -> list[str]:
    """rejected.jsonl: at least `at_least` entries, each with the contract's fields."""
    p = run_dir / "rejected.jsonl"
    if not p.exists():
        return ["no rejected.jsonl in the run directory"]
    problems = []
    lines = p.read_bytes().split(b"\n")
    if lines[-1]:
        problems.append("rejected.jsonl ends in a torn line")
    n = 0
    for i, raw in enumerate(lines[:-1], 1):
        try:
            obj = json.loads(raw)
        except ValueError:
            problems.append(f"rejected.jsonl:{i} is not JSON")
            continue
        n += 1
        missing = [k for k in REJECT_FIELDS if k not in obj]
        if missing:
            problems.append(f"rejected.jsonl:{i} lacks {missing}")
            break
        if not str(obj["key"]).startswith(f"ble/{SITE}/"):
            problems.append(f"rejected.jsonl:{i} key {obj['key']!r}")
        if len(base64.b64decode(obj["payload_b64"])) > 4096:
            problems.append(f"rejected.jsonl:{i} keeps more than 4 KiB of payload")
    if n < at_least:
        problems.append(f"rejected.jsonl holds {n} entries, expected at least {at_least}")
    return problems


# --- full disk -------------------------------------------------------------------------------


def mount_tmpfs(where: Path, size: str) -> str | None:
    """Mount a small tmpfs; returns None, or why it cannot be done here (the test skips)."""
    if os.geteuid() != 0:
        return "needs root to mount a small tmpfs"
    if shutil.which("mount") is None:
        return "no mount(8) on this machine"
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0:
        return f"cannot mount a tmpfs here: {r.stderr.strip() or r.returncode}"
    return None


def umount(where: Path) -> None:
    subprocess.run(["umount", "-l", str(where)], capture_output=True, check=False)


def fill(where: Path, chunk: int = 64 * 1024) -> int:
    """Write one file until the file system is full; returns the bytes written."""
    n = 0
    buf = b"\0" * chunk
    with (where / "filler.bin").open("wb", buffering=0) as f:
        while True:
            try:
                n += f.write(buf)
            except OSError:
                if chunk <= 512:
                    break
                buf = buf[: len(buf) // 2]
                chunk = len(buf)
    return n


def _mentions_disk(v: Any, key: str = "") -> bool:
    """True when a status reply says anything truthy under a key about disk/space/full."""
    k = key.lower()
    if any(w in k for w in ("disk", "space", "full")) and v not in (None, False, 0, "", [], {}):
        return True
    if isinstance(v, dict):
        return any(_mentions_disk(x, str(kk)) for kk, x in v.items())
    if isinstance(v, list):
        return any(_mentions_disk(x, key) for x in v)
    return False


def agent_status(endpoint: str, agent_id: str, site: str = SITE) -> dict[str, Any]:
    """The agent's status reply ({} when it does not answer)."""
    import zenoh

    from bgt_core.zenoh_config import SessionSpec, build_config

    session = zenoh.open(build_config(SessionSpec(mode="client", connect=[endpoint])))
    try:
        for reply in session.get(wire.agent_status_key(site, agent_id), timeout=5.0):
            if reply.ok is not None:
                return wire.from_json(reply.ok.payload.to_bytes(), "agent status")
    finally:
        session.close()
    return {}


def full_disk(
    root: Path, scale: Scale, *, hold_s: float, size: str = "2m", side: str = "collector"
) -> Result:
    """The collector's data directory (side "collector") or the agent's spool (side "agent")
    sits on a small tmpfs that fills up mid-run and is freed again after `hold_s`."""
    assert side in ("collector", "agent")
    disk = root / "disk"
    why = mount_tmpfs(disk, size)
    res = Result(f"full disk ({side})", Tally())
    if why is not None:
        res.notes["skipped"] = why
        return res
    try:
        rig = Rig(
            root,
            data_dir=disk / "data" if side == "collector" else None,
            spool_root=disk if side == "agent" else None,
        )
        data = make_replay(
            root / "replay",
            sensors=sensor_macs(scale.sensors),
            beacons=beacon_macs(scale.beacons),
            rate_hz=scale.rate_hz,
            duration_s=scale.duration_s,
            t0_ns=time.time_ns(),
        )
        run_dir: Path | None = None
        try:
            rig.collector.start()
            run_dir = rig.start_run("fulldisk")
            agent = rig.agent(data.paths, speed=scale.speed)
            agent.start()
            rig.wait_recording(run_dir, max(1, len(data.rows) // 5), timeout=60 + scale.duration_s)
            res.notes["filler_bytes"] = fill(disk)

            def says_full() -> bool:
                if side == "collector":
                    return _mentions_disk(rig.collector.control("status"))
                return _mentions_disk(agent_status(rig.endpoint, "pi-01"))

            try:
                wait_until(says_full, 20, f"{side} status to report the full disk", interval=0.5)
                res.notes["status_says_full"] = True
            except AssertionError:
                res.notes["status_says_full"] = False
                res.problems.append(f"{side} status never mentioned the full disk")
            time.sleep(hold_s)
            if not rig.collector.alive():
                res.problems.append(f"the collector died on the full disk:\n{rig.diagnostics()}")
            (disk / "filler.bin").unlink()
            _finish(rig, run_dir, agent, scale.duration_s / max(scale.speed, 0.1) + 150, res)
        except (AssertionError, CollectorError) as e:
            res.problems.append(f"{e}\n{rig.diagnostics()}")
        finally:
            rig.close()
        if run_dir is not None:
            res.tally = tally(run_dir, data.rows, data.sensors)
    finally:
        umount(disk)
    return res


# --- absurd readings -------------------------------------------------------------------------


def absurd_readings(root: Path, *, batches: int = 40) -> Result:
    """Batches that are valid to the wire format but carry readings from 2090-2099, decades
    ahead of the collector's clock, on their own stream next to a sane one: the sane stream is
    recorded whole; the absurd readings end in rejected.jsonl, never in a run file.

    Only the future counts as absurd here: a reading years in the past is what
    `--replay-keep-time` of an old recording legitimately sends."""
    import zenoh

    from bgt_core.zenoh_config import SessionSpec, build_config

    rig = Rig(root)
    agent, boot = "pi-02", "a5a5a5a5a5a5a5a5"
    sane_sensor, odd_sensor = sensor_macs(2, prefix="5a5e00")
    res = Result("absurd timestamps", Tally())
    run_dir: Path | None = None
    expected: set[str] = set()
    now = time.time_ns()
    day = 86_400 * 10**9
    try:
        rig.collector.start()
        run_dir = rig.start_run("absurd")
        session = zenoh.open(build_config(SessionSpec(mode="client", connect=[rig.endpoint])))
        try:
            token = session.liveliness().declare_token(wire.agent_token_key(SITE, agent))
            block = zenoh.CongestionControl.BLOCK
            for seq in range(batches):
                rs = tuple(
                    wire.Reading(now + seq * 10**8 + k, "e78f13cccccc", -60 - k) for k in range(2)
                )
                expected |= {
                    format_row(r.t_ns, sane_sensor, r.beacon, r.rssi).rstrip("\n") for r in rs
                }
                session.put(
                    wire.data_key(SITE, agent, sane_sensor),
                    wire.to_wire(wire.Batch(agent, boot, sane_sensor, seq, rs)),
                    congestion_control=block,
                )
                t = (3_786_912_000 + seq * 7_000_000) * 10**9  # 2090 onwards
                odd = wire.Batch(
                    agent, boot, odd_sensor, seq, (wire.Reading(t, "e78f13cccccc", -70),)
                )
                session.put(
                    wire.data_key(SITE, agent, odd_sensor),
                    wire.to_wire(odd),
                    congestion_control=block,
                )
            wait_until(lambda: count_lines(run_dir) >= len(expected), 30, "the sane stream")
            token.undeclare()
        finally:
            session.close()
        stopped = rig.stop_run()  # drains whatever is still in flight
        res.notes["stop_readings"] = stopped.get("readings")
        rows, _ = read_rows(run_dir, [odd_sensor])
        far = [r for r in rows if parse_line(r).t_ns - now > day]
        res.notes["absurd_recorded"] = len(far)
        if far:
            res.problems.append(
                f"{len(far)} readings decades in the future were recorded, e.g. {far[0]}"
            )
        keys = (
            [
                json.loads(raw).get("key")
                for raw in (run_dir / "rejected.jsonl").read_bytes().split(b"\n")[:-1]
            ]
            if (run_dir / "rejected.jsonl").exists()
            else []
        )
        quarantined = sum(1 for k in keys if k == wire.data_key(SITE, agent, odd_sensor))
        res.notes["quarantined"] = quarantined
        if quarantined < batches:
            res.problems.append(
                f"only {quarantined} of {batches} absurd batches are in rejected.jsonl"
            )
    except (AssertionError, CollectorError) as e:
        res.problems.append(f"{e}\n{rig.diagnostics()}")
    finally:
        rig.close()
    if run_dir is not None:
        res.tally = tally(run_dir, expected, [sane_sensor])
    return res
