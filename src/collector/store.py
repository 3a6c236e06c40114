"""Run directories on disk: run ids, run.yaml, and the per-sensor .mbd appenders with buffered
writes and periodic fsync. Only the collector's writer thread touches a RunWriter."""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from collector.errors import CollectorError

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"[^A-Za-z0-9_.-]+")
FLUSH_BYTES = 1 << 20  # a sensor's buffer is written out once it holds this much text


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
    import yaml

    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", encoding="utf-8") as f:
        yaml.safe_dump(data, f, sort_keys=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class SensorAppender:
    """One sensor's .mbd file: text is buffered in memory and written in large chunks."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._f = path.open("ab")
        self._buf: list[str] = []
        self._buffered = 0
        self._failing = False
        self.rows = 0

    def append(self, text: str, nrows: int) -> None:
        self._buf.append(text)
        self._buffered += len(text)
        self.rows += nrows
        if self._buffered >= FLUSH_BYTES and not self._failing:
            try:
                self.flush()
            except OSError:  # kept in memory; the writer's periodic flush retries and reports it
                self._failing = True

    def flush(self) -> None:
        if self._buf:
            text = "".join(self._buf)
            self._buf = [text]  # if the write fails, the text stays for the next attempt
            self._f.write(text.encode("ascii"))
            self._buf.clear()
            self._buffered = 0
        self._f.flush()
        self._failing = False

    def fsync(self) -> None:
        self.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self.fsync()
        self._f.close()


@dataclass(slots=True)
class SensorStats:
    agent_id: str
    readings: int = 0
    batches: int = 0


class RunWriter:
    """An open run: its directory, appenders per sensor, and what run.yaml will say about it."""

    def __init__(self, data_dir: Path, run_id: str, name: str, start_ns: int, meta: dict[str, Any]) -> None:
        self.run_id = run_id
        self.name = name
        self.dir = Path(data_dir) / run_id
        self.start_ns = start_ns
        self.meta = meta  # software version, site, ...
        try:
            (self.dir / "rssi").mkdir(parents=True, exist_ok=False)
        except FileExistsError:
            raise CollectorError(f"run directory {self.dir} already exists") from None
        except OSError as e:
            raise CollectorError(f"cannot create run directory {self.dir}: {e.strerror}") from None
        self.appenders: dict[str, SensorAppender] = {}
        self.sensors: dict[str, SensorStats] = {}
        self.readings = 0
        self.write_yaml(stop_ns=None, agents={}, extra={})

    def append(self, agent_id: str, sensor: str, text: str, nrows: int) -> None:
        app = self.appenders.get(sensor)
        if app is None:
            app = self.appenders[sensor] = SensorAppender(self.dir / "rssi" / f"{sensor}.mbd")
            self.sensors[sensor] = SensorStats(agent_id)
        app.append(text, nrows)
        st = self.sensors[sensor]
        st.readings += nrows
        st.batches += 1
        self.readings += nrows

    def flush(self) -> None:
        for a in self.appenders.values():
            a.flush()

    def fsync(self) -> None:
        for a in self.appenders.values():
            a.fsync()

    def close(self) -> None:
        for a in self.appenders.values():
            a.close()

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


def list_runs(data_dir: Path) -> list[dict[str, Any]]:
    """Every run under data_dir (oldest first) with id, name, start, stop and reading count."""
    import yaml

    out = []
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        return out
    for p in sorted(data_dir.glob("*/run.yaml")):
        try:
            doc = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
        except (OSError, yaml.YAMLError) as e:
            log.warning("skipping unreadable %s: %s", p, e)
            continue
        out.append({"run_id": doc.get("id", p.parent.name), "name": doc.get("name"),
                    "start": doc.get("start"), "stop": doc.get("stop"),
                    "readings": doc.get("readings")})
    return out
