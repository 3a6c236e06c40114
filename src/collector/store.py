"""Run directories on disk: run ids, run.yaml, state.json (crash recovery), and the per-sensor
.mbd appenders with buffered writes, periodic fsync and rollback of failed writes.
Only the collector's writer thread touches a RunWriter."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from collector.errors import CollectorError

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"[^A-Za-z0-9_.-]+")
FLUSH_BYTES = 1 << 20  # a sensor's buffer is written out once it holds this much text
STATE_FILE = "state.json"
STATE_VERSION = 1
FileWrite = Callable[[int, bytes], int]  # os.write's shape


def iso_utc(t_ns: int) -> str:
    return datetime.fromtimestamp(t_ns / 1e9, tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


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
    from ble_groundtruth.safe_yaml import dump

    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", encoding="utf-8") as f:
        dump(data, f, sort_keys=False)  # no anchors: safe_yaml refuses them on reading
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Temp file, fsync, rename, directory fsync: after a crash either the old or the new file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        with tmp.open("w", encoding="utf-8") as f:
            json.dump(data, f, separators=(",", ":"))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # a half-written temp file must not eat the space we lack
        raise
    _fsync_dir(path.parent)


def is_disk_full(err: OSError) -> bool:
    return err.errno in (errno.ENOSPC, errno.EDQUOT)


class SensorAppender:
    """One sensor's .mbd file: text is buffered in memory and written in large chunks.

    ``size`` is the length of the file made only of whole lines. A write that fails part-way
    (disk full) is cut back to ``size`` and its text stays buffered for the next attempt, so the
    file never holds a torn line while the collector is alive.
    """

    def __init__(self, path: Path, size: int | None = None, write: FileWrite = os.write) -> None:
        self.path = path
        self._write = write  # os.write; tests inject a failing one (disk full)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        self.size = os.fstat(self._fd).st_size if size is None else size
        self._buf: list[str] = []
        self.buffered = 0
        self._failing = False
        self.rows = 0

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
        done = 0
        try:
            while done < len(data):
                done += self._write(self._fd, data[done:])
        except OSError:
            if done:
                try:  # roll back to the last whole line; the text is still in the buffer
                    os.ftruncate(self._fd, self.size)
                except OSError as e:
                    log.error("cannot cut %s back to %d bytes after a failed write: %s",  # noqa: TRY400
                              self.path, self.size, e)
            raise
        self.size += len(data)
        self._buf.clear()
        self.buffered = 0
        self._failing = False

    def fsync(self) -> None:
        self.flush()
        os.fsync(self._fd)

    def close(self) -> None:
        try:
            self.fsync()
        finally:
            os.close(self._fd)


@dataclass(slots=True)
class SensorStats:
    agent_id: str
    readings: int = 0
    batches: int = 0


def repair_file(path: Path, size: int | None) -> int:
    """Cut an .mbd file back to `size` bytes (what the state says is durable) and to its last
    whole line; returns how many bytes were removed. The removed tail is kept beside the run as
    ``recovered/<name>.tail`` (it was never acknowledged, so agents with a spool send it again)."""
    actual = path.stat().st_size
    keep = actual if size is None or size > actual else size
    if size is not None and size > actual:
        log.error("%s is shorter (%d bytes) than its last recorded state (%d bytes)", path, actual, size)
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
            rec = path.parent.parent / "recovered"
            rec.mkdir(exist_ok=True)
            with (rec / f"{path.name}.tail").open("ab") as t:
                t.write(tail)
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    return removed


class RunWriter:
    """An open run: its directory, appenders per sensor, and what run.yaml will say about it."""

    def __init__(self, data_dir: Path, run_id: str, name: str, start_ns: int, meta: dict[str, Any],
                 *, resume: dict[str, Any] | None = None, write: FileWrite = os.write) -> None:
        self.run_id = run_id
        self._write = write
        self.name = name
        self.dir = Path(data_dir) / run_id
        self.start_ns = start_ns
        self.meta = meta  # software version, site, ...
        self.appenders: dict[str, SensorAppender] = {}
        self.sensors: dict[str, SensorStats] = {}
        self.readings = 0
        self.disk_full = False
        if resume is None:
            try:
                (self.dir / "rssi").mkdir(parents=True, exist_ok=False)
            except FileExistsError:
                raise CollectorError(f"run directory {self.dir} already exists") from None
            except OSError as e:
                raise CollectorError(f"cannot create run directory {self.dir}: {e.strerror}") from None
            self.write_yaml(stop_ns=None, agents={}, extra={})
        else:
            self._resume(resume)

    def _resume(self, state: dict[str, Any]) -> None:
        """Reopen the files of a run a killed collector left, cut to what its state covers."""
        files = {str(k): int(v) for k, v in state.get("files", {}).items()}
        rssi = self.dir / "rssi"
        rssi.mkdir(parents=True, exist_ok=True)
        for path in sorted(rssi.glob("*.mbd")):
            sensor = path.stem
            removed = repair_file(path, files.get(sensor, 0))
            if removed:
                log.warning("run %s: cut %d bytes past the last recorded state from %s "
                            "(kept in recovered/; agents re-send them)", self.run_id, removed, path.name)
        for sensor, st in state.get("sensors", {}).items():
            self.sensors[sensor] = SensorStats(st["agent"], int(st["readings"]), int(st["batches"]))
            path = rssi / f"{sensor}.mbd"
            if path.exists():
                self.appenders[sensor] = SensorAppender(path, write=self._write)
        self.readings = int(state.get("readings", 0))

    def append(self, agent_id: str, sensor: str, text: str, nrows: int) -> None:
        app = self.appenders.get(sensor)
        if app is None:
            app = self.appenders[sensor] = SensorAppender(self.dir / "rssi" / f"{sensor}.mbd",
                                                         write=self._write)
        st = self.sensors.get(sensor)
        if st is None:
            st = self.sensors[sensor] = SensorStats(agent_id)
        app.append(text, nrows)
        st.readings += nrows
        st.batches += 1
        self.readings += nrows

    @property
    def buffered(self) -> int:
        """Bytes of rows held in memory, not yet written (grows while the disk is full)."""
        return sum(a.buffered for a in self.appenders.values())

    def flush(self) -> None:
        for a in self.appenders.values():
            a.flush()

    def fsync(self) -> None:
        for a in self.appenders.values():
            a.fsync()

    def close(self) -> None:
        for a in self.appenders.values():
            a.close()

    def state(self, extra: dict[str, Any]) -> dict[str, Any]:
        """The crash-recovery record; call right after fsync() so the sizes are durable."""
        return {"version": STATE_VERSION, "active": True, "run_id": self.run_id, "name": self.name,
                "start_ns": self.start_ns, "meta": self.meta, "readings": self.readings,
                "files": {s: a.size for s, a in self.appenders.items()},
                "sensors": {s: {"agent": st.agent_id, "readings": st.readings, "batches": st.batches}
                            for s, st in self.sensors.items()},
                **extra}

    def write_state(self, state: dict[str, Any]) -> None:
        write_json_atomic(self.dir / STATE_FILE, state)

    def write_yaml(self, *, stop_ns: int | None, agents: dict[str, Any], extra: dict[str, Any]) -> None:
        doc: dict[str, Any] = {
            "id": self.run_id,
            "name": self.name,
            "start": iso_utc(self.start_ns),
            "start_ns": self.start_ns,
            "stop": iso_utc(stop_ns) if stop_ns is not None else None,
            "stop_ns": stop_ns,
            **self.meta,
            "readings": self.readings,
            **extra,
            "agents": agents,
        }
        write_yaml_atomic(self.dir / "run.yaml", doc)


def find_active_state(data_dir: Path) -> list[tuple[Path, dict[str, Any]]]:
    """Run directories whose state.json says the run is still active (the collector was killed),
    newest first. Unreadable state files are reported and skipped."""
    out = []
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        return out
    for p in sorted(data_dir.glob(f"*/{STATE_FILE}"), reverse=True):
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            log.warning("ignoring unreadable %s: %s", p, e)
            continue
        if not isinstance(doc, dict) or doc.get("version") != STATE_VERSION:
            log.warning("ignoring %s: not a state file of version %d", p, STATE_VERSION)
            continue
        if doc.get("active"):
            out.append((p.parent, doc))
    return out


def list_runs(data_dir: Path) -> list[dict[str, Any]]:
    """Every run under data_dir (oldest first) with id, name, start, stop and reading count."""
    from ble_groundtruth.safe_yaml import YamlError, load_file

    out = []
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        return out
    for p in sorted(data_dir.glob("*/run.yaml")):
        try:
            doc = load_file(p) or {}
        except YamlError as e:
            log.warning("skipping unreadable %s: %s", p, e)
            continue
        if not isinstance(doc, dict):
            log.warning("skipping %s: not a mapping", p)
            continue
        out.append({"run_id": doc.get("id", p.parent.name), "name": doc.get("name"),
                    "start": doc.get("start"), "stop": doc.get("stop"),
                    "readings": doc.get("readings")})
    return out
