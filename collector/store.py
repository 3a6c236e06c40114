"""Run directories on disk: run ids, run.yaml, state.json (crash recovery), and the per-stream
.mbd appenders with buffered writes, periodic fsync and rollback of failed writes.

A run keeps one file per (agent, sensor MAC) stream, ``rssi/<agent>/<sensor_mac>.mbd``: the agent
is the one named by the Zenoh key it published on (which the ACL checks), so no agent can add
rows to another's file. Files are opened lazily and at most ``open_files`` stay open (least
recently used first out, fsynced as they close). ``export_merged`` writes the published
one-file-per-sensor layout. Only the collector's writer thread touches a RunWriter."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from bgt_core.atomic import write_atomic
from bgt_core.messages import ClockSample
from bgt_core.run_record import AgentEntry, RunRecord, RunRecordError
from bgt_core.safe_open import FileRefused, open_regular, read_limited
from collector.errors import CollectorError
from collector.run_state import RunState, SensorRecord

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"[^A-Za-z0-9_.-]+")
FLUSH_BYTES = 1 << 20  # a sensor's buffer is written out once it holds this much text
STATE_FILE = "state.json"
OPEN_FILES = 256  # .mbd files kept open at once (see RunWriter); more are closed and reopened
FileWrite = Callable[[int, bytes], int]  # os.write's shape


def clean_name(name: str | None) -> str:
    """A user's run name made filesystem-safe: 'hall walk #2' -> 'hall-walk-2'."""
    cleaned = _NAME_RE.sub("-", (name or "").strip()).strip("-.")[:48]
    return cleaned or "run"


def make_run_id(t_ns: int, name: str | None) -> str:
    """Sortable, filesystem-safe: '20261122T031500Z-hall-walk'."""
    stamp = datetime.fromtimestamp(t_ns // 10**9, tz=UTC).strftime("%Y%m%dT%H%M%SZ")
    return f"{stamp}-{clean_name(name)}"


def write_yaml_atomic(path: Path, data: dict[str, Any]) -> None:
    """Replace a YAML file in one rename, so a crash never leaves half a run.yaml."""
    from bgt_core.safe_yaml import dump

    # no anchors: safe_yaml refuses them on reading
    write_atomic(path, dump(data, sort_keys=False) or "")


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Temp file, fsync, rename, directory fsync: after a crash either the old or the new file."""
    write_atomic(path, json.dumps(data, separators=(",", ":")))


def is_disk_full(err: OSError) -> bool:
    return err.errno in (errno.ENOSPC, errno.EDQUOT)


class SensorAppender:
    """One stream's .mbd file: text is buffered in memory and written in large chunks.

    ``size`` is the length of the file made only of whole lines. A write that fails part-way
    (disk full) is cut back to ``size`` and its text stays buffered for the next attempt, so the
    file never holds a torn line while the collector is alive.

    The file descriptor is opened on the first write and may be given back with ``release()``
    (which fsyncs first), so a run with many streams needs only a bounded number of descriptors.
    """

    def __init__(
        self,
        path: Path,
        size: int | None = None,
        write: FileWrite = os.write,
        opener: Callable[[SensorAppender], int] | None = None,
    ) -> None:
        self.path = path
        self._write = write  # os.write; tests inject a failing one (disk full)
        self._opener = opener  # the RunWriter's LRU bookkeeping; None = open directly
        self._fd: int | None = None
        if size is None:
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                size = 0
        self.size = size
        self._buf: list[str] = []
        self.buffered = 0
        self._failing = False
        self._unsynced = False  # written since the last fsync
        self.rows = 0

    def open_fd(self) -> int:
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        return self._fd

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    def _fileno(self) -> int:
        if self._fd is not None:
            return self._fd
        return self._opener(self) if self._opener is not None else self.open_fd()

    def append(self, text: str, nrows: int) -> None:
        self._buf.append(text)
        self.buffered += len(text)
        self.rows += nrows
        if self.buffered >= FLUSH_BYTES and not self._failing:
            try:
                self.flush()
            except OSError:  # kept in memory; the writer's periodic flush retries and reports it
                self._failing = True

    def flush(self) -> None:
        if not self._buf:
            return
        data = "".join(self._buf).encode("ascii")
        self._buf = [data.decode("ascii")]
        fd = self._fileno()
        done = 0
        try:
            while done < len(data):
                done += self._write(fd, data[done:])
        except OSError:
            if done:
                try:  # roll back to the last whole line; the text is still in the buffer
                    os.ftruncate(fd, self.size)
                except OSError as e:
                    log.error(  # noqa: TRY400 (the OSError text says it all; no traceback)
                        "cannot cut %s back to %d bytes after a failed write: %s",
                        self.path,
                        self.size,
                        e,
                    )
            raise
        self.size += len(data)
        self._buf.clear()
        self.buffered = 0
        self._failing = False
        self._unsynced = True

    def fsync(self) -> None:
        self.flush()
        if self._unsynced and self._fd is not None:
            os.fsync(self._fd)
        self._unsynced = False

    def release(self) -> None:
        """Write, fsync and close the file; the next write opens it again."""
        if self._fd is None:
            return
        try:
            self.fsync()
        finally:
            os.close(self._fd)
            self._fd = None

    def close(self) -> None:
        if self._fd is None and self._buf:
            self._fileno()
        self.release()


# Beacons counted per sensor in run.yaml (a flood of random addresses is not listed whole).
MAX_BEACONS_LISTED = 256


@dataclass(slots=True)
class SensorStats:
    readings: int = 0
    batches: int = 0
    beacons: dict[str, int] = field(default_factory=dict)  # readings per beacon MAC

    def count(self, counts: dict[bytes, list[int]]) -> None:
        for mac, (n, _) in counts.items():
            key = mac.hex()
            if key in self.beacons:
                self.beacons[key] += n
            elif len(self.beacons) < MAX_BEACONS_LISTED:
                self.beacons[key] = n

    def to_state(self) -> SensorRecord:
        return SensorRecord(
            readings=self.readings, batches=self.batches, beacons=dict(self.beacons)
        )

    @classmethod
    def from_state(cls, st: SensorRecord) -> SensorStats:
        return cls(st["readings"], st["batches"], dict(st["beacons"]))


StreamKey = tuple[str, str]  # (agent id, sensor MAC)


def stream_name(key: StreamKey) -> str:
    """'agent/sensor': the stream's file under rssi/ without the suffix, and its state key."""
    return f"{key[0]}/{key[1]}"


def parse_stream_name(name: str) -> StreamKey:
    agent, sep, sensor = str(name).partition("/")
    if not sep or not agent or not sensor or "/" in sensor:
        raise ValueError(f"not an agent/sensor stream name: {name!r}")
    return agent, sensor


def repair_file(path: Path, size: int | None) -> int:
    """Cut an .mbd file back to `size` bytes (what the state says is durable) and to its last
    whole line; returns how many bytes were removed. The removed tail is kept beside the run as
    ``recovered/<name>.tail`` (it was never acknowledged, so agents with a spool send it again)."""
    actual = path.stat().st_size
    keep = actual if size is None or size > actual else size
    if size is not None and size > actual:
        log.error(
            "%s is shorter (%d bytes) than its last recorded state (%d bytes)", path, actual, size
        )
    with path.open("rb+") as f:
        if keep:
            # Back up to the last newline so a torn last line never survives.
            start = max(0, keep - 65536)
            while True:
                f.seek(start)
                chunk = f.read(keep - start)
                nl = chunk.rfind(b"\n")
                if nl >= 0:
                    keep = start + nl + 1
                    break
                if start == 0:
                    keep = 0
                    break
                start = max(0, start - 65536)
        removed = actual - keep
        if removed:
            f.seek(keep)
            tail = f.read()
            rec = path.parent.parent.parent / "recovered" / path.parent.name
            rec.mkdir(parents=True, exist_ok=True)
            with (rec / f"{path.name}.tail").open("ab") as t:
                t.write(tail)
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    return removed


class RunWriter:
    """An open run: its directory, one appender per (agent, sensor) stream, and what run.yaml
    will say about it. At most ``open_files`` files are open at once (an LRU)."""

    def __init__(
        self,
        data_dir: Path,
        run_id: str,
        name: str,
        start_ns: int,
        meta: dict[str, Any],
        *,
        resume: RunState | None = None,
        write: FileWrite = os.write,
        open_files: int = OPEN_FILES,
    ) -> None:
        self.run_id = run_id
        self._write = write
        self.name = name
        self.dir = Path(data_dir) / run_id
        self.start_ns = start_ns
        self.meta = meta  # software version, site, ...
        self.appenders: dict[StreamKey, SensorAppender] = {}
        self.sensors: dict[StreamKey, SensorStats] = {}
        self._open: OrderedDict[StreamKey, SensorAppender] = OrderedDict()  # LRU, newest last
        self.open_files = max(1, open_files)
        self.readings = 0
        self.disk_full = False
        if resume is None:
            try:
                (self.dir / "rssi").mkdir(parents=True, exist_ok=False)
            except FileExistsError:
                raise CollectorError(f"run directory {self.dir} already exists") from None
            except OSError as e:
                raise CollectorError(
                    f"cannot create run directory {self.dir}: {e.strerror}"
                ) from None
            self.write_yaml(stop_ns=None, agents={}, summary={})
        else:
            self._resume(resume)

    def path(self, key: StreamKey) -> Path:
        return self.dir / "rssi" / key[0] / f"{key[1]}.mbd"

    def _resume(self, state: RunState) -> None:
        """Reopen the files of a run a killed collector left, cut to what its state covers."""
        files = {parse_stream_name(k): v for k, v in state.files.items()}
        rssi = self.dir / "rssi"
        rssi.mkdir(parents=True, exist_ok=True)
        for path in sorted(rssi.glob("*/*.mbd")):
            key = (path.parent.name, path.stem)
            removed = repair_file(path, files.get(key, 0))
            if removed:
                log.warning(
                    "run %s: cut %d bytes past the last recorded state from %s "
                    "(kept in recovered/; agents re-send them)",
                    self.run_id,
                    removed,
                    stream_name(key) + ".mbd",
                )
        for name, st in state.sensors.items():
            key = parse_stream_name(name)
            self.sensors[key] = SensorStats.from_state(st)
            if self.path(key).exists():
                self.appenders[key] = self._appender(key)
        self.readings = state.readings

    def _appender(self, key: StreamKey) -> SensorAppender:
        def opener(app: SensorAppender) -> int:
            return self._open_lru(key, app)

        return SensorAppender(self.path(key), write=self._write, opener=opener)

    def _open_lru(self, key: StreamKey, app: SensorAppender) -> int:
        """Open a stream's file, first closing the least recently used ones over the budget."""
        while len(self._open) >= self.open_files:
            _k, old = self._open.popitem(last=False)
            old.release()
        try:
            app.path.parent.mkdir(exist_ok=True)
            fd = app.open_fd()
        except OSError as e:
            if e.errno not in (errno.EMFILE, errno.ENFILE) or not self._open:
                raise
            # Out of descriptors after all (Zenoh uses some too): give back half and retry once.
            for _ in range(max(1, len(self._open) // 2)):
                self._open.popitem(last=False)[1].release()
            fd = app.open_fd()
        self._open[key] = app
        return fd

    @property
    def open_count(self) -> int:
        return len(self._open)

    def append(
        self,
        agent_id: str,
        sensor: str,
        text: str,
        nrows: int,
        counts: dict[bytes, list[int]] | None = None,
    ) -> None:
        key = (agent_id, sensor)
        app = self.appenders.get(key)
        if app is None:
            app = self.appenders[key] = self._appender(key)
        elif key in self._open:
            self._open.move_to_end(key)
        st = self.sensors.get(key)
        if st is None:
            st = self.sensors[key] = SensorStats()
        app.append(text, nrows)
        st.readings += nrows
        st.batches += 1
        if counts:
            st.count(counts)
        self.readings += nrows

    @property
    def buffered(self) -> int:
        """Bytes of rows held in memory, not yet written (grows while the disk is full)."""
        return sum(a.buffered for a in self.appenders.values())

    def flush(self) -> None:
        for a in self.appenders.values():
            if a.buffered:
                a.flush()

    def fsync(self) -> None:
        for a in self.appenders.values():
            a.fsync()

    def close(self) -> None:
        err: OSError | None = None
        for a in self.appenders.values():
            try:
                a.close()
            except OSError as e:
                err = err or e
        self._open.clear()
        if err is not None:
            raise err

    def shared_sensors(self) -> dict[str, list[str]]:
        """Sensor MACs that more than one agent published in this run: mac -> agents."""
        by_mac: dict[str, list[str]] = {}
        for agent, mac in self.sensors:
            by_mac.setdefault(mac, []).append(agent)
        return {m: sorted(a) for m, a in sorted(by_mac.items()) if len(a) > 1}

    def state(
        self,
        *,
        tracker: dict[str, Any] | None = None,
        lost_base: dict[str, int] | None = None,
        clock: dict[str, tuple[ClockSample, ...]] | None = None,
        restarts: int = 0,
        quarantined_bytes: int = 0,
    ) -> RunState:
        """The crash-recovery record (with the writer's parts); call right after fsync() so the
        sizes are durable."""
        return RunState(
            run_id=self.run_id,
            name=self.name,
            start_ns=self.start_ns,
            meta=self.meta,
            readings=self.readings,
            files={stream_name(k): a.size for k, a in self.appenders.items()},
            sensors={stream_name(k): st.to_state() for k, st in self.sensors.items()},
            tracker=tracker or {},
            lost_base=lost_base or {},
            clock=clock or {},
            restarts=restarts,
            quarantined_bytes=quarantined_bytes,
        )

    def write_state(self, state: RunState) -> None:
        write_json_atomic(self.dir / STATE_FILE, state.to_dict())

    def write_yaml(
        self,
        *,
        stop_ns: int | None,
        agents: Mapping[str, AgentEntry],
        summary: Mapping[str, Any],
    ) -> None:
        """run.yaml as it stands (``summary``: the keys a stopped run gains), in one rename."""
        record = RunRecord(
            run_id=self.run_id,
            name=self.name,
            start_ns=self.start_ns,
            stop_ns=stop_ns,
            readings=self.readings,
            meta=self.meta,
            summary=summary,
            agents=agents,
        )
        write_yaml_atomic(self.dir / "run.yaml", record.to_dict())


def read_run_record(run_dir: Path) -> RunRecord:
    """A run directory's run.yaml; RunRecordError (one line) when it is unreadable or not one."""
    from bgt_core.safe_yaml import YamlError, load_file

    path = Path(run_dir) / "run.yaml"
    try:
        doc = load_file(path)
    except YamlError as e:
        raise RunRecordError(str(e)) from None
    return RunRecord.from_dict(doc, str(path), default_id=Path(run_dir).name)


def find_active_state(data_dir: Path) -> list[tuple[Path, dict[str, Any]]]:
    """Run directories whose state.json says the run is still active (the collector was killed),
    newest first. Unreadable state files are reported and skipped."""
    out: list[tuple[Path, dict[str, Any]]] = []
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        return out
    for p in sorted(data_dir.glob(f"*/{STATE_FILE}"), reverse=True):
        try:
            with open_regular(p, "yaml") as f:
                doc = json.loads(read_limited(f, p, "yaml").decode("utf-8"))
        except (OSError, ValueError) as e:
            log.warning("ignoring unreadable %s: %s", p, e)
            continue
        if not isinstance(doc, dict) or not isinstance(doc.get("version"), int):
            log.warning("ignoring %s: not a collector state file", p)
            continue
        if doc.get("active"):
            out.append((p.parent, doc))
    return out


def list_runs(data_dir: Path) -> list[dict[str, Any]]:
    """Every run under data_dir (oldest first) with id, name, start, stop and reading count."""
    out: list[dict[str, Any]] = []
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        return out
    for p in sorted(data_dir.glob("*/run.yaml")):
        try:
            rec = read_run_record(p.parent)
        except RunRecordError as e:
            log.warning("skipping unreadable %s: %s", p, e)
            continue
        out.append(rec.listing())
    return out


def export_merged(run_dir: Path, out_dir: Path) -> dict[str, int]:
    """Write the published layout, one ``<sensor_mac>.mbd`` per sensor, from a run's per-agent
    files: rows of the same MAC from several agents are merged in time order (stable). Returns
    sensor -> rows. Rows are copied as they are (same text, same format)."""
    from bgt_core.wire import parse_ts

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    rssi = run_dir / "rssi"
    if not rssi.is_dir():
        raise CollectorError(f"{run_dir}: not a run directory (no rssi/ folder)")
    by_mac: dict[str, list[Path]] = {}
    for p in sorted(rssi.glob("*/*.mbd")):
        by_mac.setdefault(p.stem, []).append(p)
    if not by_mac:
        raise CollectorError(f"{rssi}: no rssi/<agent>/<sensor>.mbd files")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CollectorError(f"cannot create {out_dir}: {e.strerror or e}") from None
    counts: dict[str, int] = {}
    for mac, paths in by_mac.items():
        rows: list[tuple[int, str]] = []
        for p in paths:
            try:
                with open_regular(p, "readings") as f:
                    text = read_limited(f, p, "readings").decode("ascii")
            except FileRefused as e:
                raise CollectorError(str(e)) from None
            except (OSError, UnicodeDecodeError) as e:
                raise CollectorError(f"{p}: cannot read: {e}") from None
            for lineno, line in enumerate(text.splitlines(), 1):
                if not line.strip():
                    continue
                try:
                    rows.append((parse_ts(line.split(",", 1)[0]), line))
                except ValueError as e:
                    raise CollectorError(f"{p}:{lineno}: bad timestamp: {e}") from None
        rows.sort(key=lambda r: r[0])
        dest = out_dir / f"{mac}.mbd"
        write_atomic(dest, "".join(line + "\n" for _t, line in rows))
        counts[mac] = len(rows)
    return counts
