"""Typed messages of the collector's control: start, stop, status and runs, the reply
envelope, and the status reply with its parts (what `collector status`, `live` and the web
console read). Same conventions as bgt_core.messages."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from bgt_core.message_fields import (
    int_field,
    is_int,
    is_num,
    mapping,
    num_field,
    obj_field,
    str_field,
)
from bgt_core.messages import ClockSample
from bgt_core.wire import InvalidField

# -- collector control (start, stop, status, runs) ---------------------------------------------


# A run's name: what an operator types, stored as given in run.yaml and shown escaped.
RUN_NAME_MAX = 200


def check_run_name(name: object) -> None:
    """InvalidField unless ``name`` is None or a string of at most RUN_NAME_MAX printable
    characters (no control characters: a terminal would run them when the name is shown)."""
    if name is None:
        return
    if not isinstance(name, str):
        raise InvalidField("start: name must be a string or null")
    if len(name) > RUN_NAME_MAX or not name.isprintable():
        raise InvalidField(
            f"start: name must be at most {RUN_NAME_MAX} printable characters "
            f"(got {len(name)} characters{'' if name.isprintable() else ', some not printable'})"
        )


# Free-text notes of a run (the operator console's start form), stored in run.yaml.
RUN_NOTES_MAX = 2000


def check_run_notes(notes: object) -> None:
    """InvalidField unless ``notes`` is None or at most RUN_NOTES_MAX characters of text, where
    line breaks and tabs are the only control characters."""
    if notes is None:
        return
    if not isinstance(notes, str):
        raise InvalidField("start: notes must be a string or null")
    plain = notes.replace("\n", "").replace("\t", "")
    if len(notes) > RUN_NOTES_MAX or not plain.isprintable():
        raise InvalidField(
            f"start: notes must be at most {RUN_NOTES_MAX} characters of text (line breaks allowed)"
        )


@dataclass(frozen=True, slots=True)
class StartRequest:
    name: str | None = None
    max_offset_ms: float | None = None  # warn about agents whose clock is off by more
    strict: bool = False  # ... and refuse to start instead
    notes: str | None = None  # free text, stored in run.yaml

    @classmethod
    def from_dict(cls, d: object) -> StartRequest:
        m = mapping(d, "start request")
        name = m.get("name")
        check_run_name(name)
        max_off = m.get("max_offset_ms")
        if max_off is not None and (
            not is_num(max_off) or not math.isfinite(max_off) or not 0 <= max_off <= 86_400_000
        ):
            raise InvalidField(
                "start: max_offset_ms must be a finite number of ms in 0..86400000, or null"
            )
        strict = m.get("strict", False)
        if not isinstance(strict, bool):
            raise InvalidField("start: strict must be true or false")
        notes = m.get("notes")
        check_run_notes(notes)
        return cls(name, None if max_off is None else float(max_off), strict, notes)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name}
        if self.max_offset_ms is not None:
            out["max_offset_ms"] = self.max_offset_ms
        if self.strict:
            out["strict"] = True
        if self.notes:
            out["notes"] = self.notes
        return out


@dataclass(frozen=True, slots=True)
class AgentClock:
    offset_ms: float
    rtt_ms: float


@dataclass(frozen=True, slots=True)
class StartReply:
    run_id: str
    run_dir: str
    clock: dict[str, AgentClock] = field(default_factory=dict)
    clock_warnings: tuple[str, ...] = ()

    @classmethod
    def from_dict(cls, d: object) -> StartReply:
        what = "start reply"
        m = mapping(d, what)
        clock = obj_field(m, "clock", what, {})
        warnings = m.get("clock_warnings") or []
        if not (isinstance(warnings, list) and all(isinstance(w, str) for w in warnings)):
            raise InvalidField(f"{what}: clock_warnings must be a list of strings")
        return cls(
            str_field(m, "run_id", what),
            str_field(m, "run_dir", what),
            {
                a: AgentClock(
                    num_field(mapping(v, f"{what}: clock.{a}"), "offset_ms", what),
                    num_field(v, "rtt_ms", what),
                )
                for a, v in clock.items()
            },
            tuple(warnings),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "run_dir": self.run_dir,
            "clock": {
                a: {"offset_ms": c.offset_ms, "rtt_ms": c.rtt_ms} for a, c in self.clock.items()
            },
            "clock_warnings": list(self.clock_warnings),
        }


@dataclass(frozen=True, slots=True)
class StopReply:
    run_id: str
    run_dir: str
    readings: int
    gaps: int = 0
    missing_batches: int = 0
    lost_batches: int = 0

    @classmethod
    def from_dict(cls, d: object) -> StopReply:
        what = "stop reply"
        m = mapping(d, what)
        return cls(
            str_field(m, "run_id", what),
            str_field(m, "run_dir", what),
            int_field(m, "readings", what),
            int_field(m, "gaps", what, 0),
            int_field(m, "missing_batches", what, 0),
            int_field(m, "lost_batches", what, 0),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "run_dir": self.run_dir,
            "readings": self.readings,
            "gaps": self.gaps,
            "missing_batches": self.missing_batches,
            "lost_batches": self.lost_batches,
        }


@dataclass(frozen=True, slots=True)
class Reply:
    """The envelope of every collector control reply: ``ok`` and either the body or an error."""

    ok: bool
    error: str | None = None
    body: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: object, command: str = "control") -> Reply:
        m = dict(mapping(d, f"{command} reply"))
        ok = m.pop("ok", None)
        if not isinstance(ok, bool):
            raise InvalidField(f"{command} reply: ok must be true or false")
        error = m.pop("error", None)
        if error is not None and not isinstance(error, str):
            raise InvalidField(f"{command} reply: error must be a string")
        return cls(ok, error, m)

    def to_dict(self) -> dict[str, Any]:
        if self.ok:
            return {"ok": True, **self.body}
        return {"ok": False, "error": self.error or "failed without a reason"}


# -- collector status ---------------------------------------------------------------------------


def _counts(d: Mapping[str, Any], key: str, what: str) -> dict[str, int]:
    m = obj_field(d, key, what, {})
    for k, v in m.items():
        if not is_int(v):
            raise InvalidField(f"{what}: {key}.{k} must be an integer, got {v!r}")
    return dict(m)


@dataclass(frozen=True, slots=True)
class SensorRate:
    """One sensor of one agent in the status reply (since the collector started)."""

    rate_hz: float = 0.0
    last_seen_age_s: float | None = None
    last_rssi: int | None = None
    readings: int = 0
    recent_rssi: tuple[int, ...] = ()  # the last readings' RSSI, oldest first (sparkline)
    beacons: dict[str, float] = field(default_factory=dict)  # readings/s of the most heard beacons
    beacon_rssi: dict[str, int] = field(
        default_factory=dict
    )  # last RSSI of each beacon heard lately

    @classmethod
    def from_dict(cls, d: object, what: str = "sensor") -> SensorRate:
        m = mapping(d, what)
        recent = m.get("recent_rssi") or []
        if not (isinstance(recent, list) and all(is_int(v) for v in recent)):
            raise InvalidField(f"{what}: recent_rssi must be a list of integers")
        beacons = m.get("beacons") or {}
        if not (
            isinstance(beacons, dict)
            and len(beacons) <= 64
            and all(
                isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool)
                for k, v in beacons.items()
            )
        ):
            raise InvalidField(f"{what}: beacons must map at most 64 MACs to rates")
        rssi = m.get("beacon_rssi") or {}
        if not (
            isinstance(rssi, dict)
            and len(rssi) <= 64
            and all(isinstance(k, str) and is_int(v) for k, v in rssi.items())
        ):
            raise InvalidField(f"{what}: beacon_rssi must map at most 64 MACs to integer dBm")
        return cls(
            num_field(m, "rate_hz", what, 0.0),
            num_field(m, "last_seen_age_s", what, None),
            int_field(m, "last_rssi", what, None),
            int_field(m, "readings", what, 0),
            tuple(recent),
            {str(k): float(v) for k, v in beacons.items()},
            {str(k): int(v) for k, v in rssi.items()},
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "rate_hz": self.rate_hz,
            "last_seen_age_s": self.last_seen_age_s,
            "last_rssi": self.last_rssi,
            "readings": self.readings,
            "recent_rssi": list(self.recent_rssi),
            "beacons": dict(self.beacons),
            "beacon_rssi": dict(self.beacon_rssi),
        }


@dataclass(frozen=True, slots=True)
class AgentLive:
    alive: bool = False  # its liveliness token is present
    sensors: dict[str, SensorRate] = field(default_factory=dict)
    # From the agent's status reply (when it answered one) and the last clock check.
    version: str | None = None
    backend: str | None = None
    hostname: str | None = None
    adapters: tuple[str, ...] = ()  # "hci0 b827eb4521b4 passive"
    clock_offset_ms: float | None = None
    # The agent's spool (records and bytes not yet acknowledged, from its status reply) and how
    # long ago the collector last acknowledged its batches, s.
    spool_records: int | None = None
    spool_bytes: int | None = None
    last_ack_age_s: float | None = None

    @classmethod
    def from_dict(cls, d: object, what: str = "agent") -> AgentLive:
        m = mapping(d, what)
        alive = m.get("alive", False)
        if not isinstance(alive, bool):
            raise InvalidField(f"{what}: alive must be true or false")
        sensors = obj_field(m, "sensors", what, {})
        adapters = m.get("adapters") or []
        if not (isinstance(adapters, list) and all(isinstance(a, str) for a in adapters)):
            raise InvalidField(f"{what}: adapters must be a list of text")
        text = {k: m.get(k) for k in ("version", "backend", "hostname")}
        for k, v in text.items():
            if v is not None and not isinstance(v, str):
                raise InvalidField(f"{what}: {k} must be text")
        return cls(
            alive,
            {mac: SensorRate.from_dict(s, f"{what}: sensors.{mac}") for mac, s in sensors.items()},
            text["version"],
            text["backend"],
            text["hostname"],
            tuple(adapters),
            num_field(m, "clock_offset_ms", what, None),
            num_field(m, "spool_records", what, None),
            num_field(m, "spool_bytes", what, None),
            num_field(m, "last_ack_age_s", what, None),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "alive": self.alive,
            "sensors": {k: s.to_dict() for k, s in self.sensors.items()},
            "version": self.version,
            "backend": self.backend,
            "hostname": self.hostname,
            "adapters": list(self.adapters),
            "clock_offset_ms": self.clock_offset_ms,
            "spool_records": self.spool_records,
            "spool_bytes": self.spool_bytes,
            "last_ack_age_s": self.last_ack_age_s,
        }


@dataclass(frozen=True, slots=True)
class RunStatus:
    """The active run in the status reply."""

    run_id: str
    readings: int = 0
    name: str = ""
    run_dir: str = ""
    start: str = ""  # ISO UTC
    sensors: int = 0
    stopping: bool = False
    restarts: int = 0  # unclean collector stops this run survived
    buffered_bytes: int = 0  # rows held in memory (the disk refuses them)
    clock: dict[str, ClockSample] = field(default_factory=dict)  # last sample per agent

    @classmethod
    def from_dict(cls, d: object) -> RunStatus:
        what = "status: run"
        m = mapping(d, what)
        stopping = m.get("stopping", False)
        if not isinstance(stopping, bool):
            raise InvalidField(f"{what}: stopping must be true or false")
        clock = obj_field(m, "clock", what, {})
        return cls(
            str_field(m, "run_id", what),
            int_field(m, "readings", what, 0),
            str_field(m, "name", what, ""),
            str_field(m, "run_dir", what, ""),
            str_field(m, "start", what, ""),
            int_field(m, "sensors", what, 0),
            stopping,
            int_field(m, "restarts", what, 0),
            int_field(m, "buffered_bytes", what, 0),
            {a: ClockSample.from_dict(v) for a, v in clock.items()},
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "name": self.name,
            "run_dir": self.run_dir,
            "start": self.start,
            "readings": self.readings,
            "sensors": self.sensors,
            "stopping": self.stopping,
            "restarts": self.restarts,
            "buffered_bytes": self.buffered_bytes,
            "clock": {a: c.to_dict() for a, c in self.clock.items()},
        }


@dataclass(frozen=True, slots=True)
class StreamCounts:
    total: int = 0  # streams with live state
    shown: int = 0  # of them, listed under agents
    admitted: int = 0  # accepted under the stream caps since the collector started
    open_files: int = 0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StreamCounts:
        what = "status: streams"
        return cls(
            int_field(d, "total", what, 0),
            int_field(d, "shown", what, 0),
            int_field(d, "admitted", what, 0),
            int_field(d, "open_files", what, 0),
        )

    def to_dict(self) -> dict[str, int]:
        return {
            "total": self.total,
            "shown": self.shown,
            "admitted": self.admitted,
            "open_files": self.open_files,
        }


@dataclass(frozen=True, slots=True)
class RefusedStreams:
    """Batches refused by the stream caps (total, streams, the worst agents) and by the per-agent
    quotas (``over_quota``: "agent: rate" or "agent: disk" -> batches, the worst first)."""

    batches: int = 0
    streams: int = 0
    by_agent: dict[str, int] = field(default_factory=dict)
    over_quota: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RefusedStreams:
        what = "status: refused_streams"
        return cls(
            int_field(d, "batches", what, 0),
            int_field(d, "streams", what, 0),
            _counts(d, "by_agent", what),
            _counts(d, "over_quota", what),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "batches": self.batches,
            "streams": self.streams,
            "by_agent": dict(self.by_agent),
            "over_quota": dict(self.over_quota),
        }


@dataclass(frozen=True, slots=True)
class CollectorStatus:
    """The collector's status reply. Every field but ``run`` and ``agents`` has a default, so a
    reply of an older collector still reads."""

    run: RunStatus | None = None
    agents: dict[str, AgentLive] = field(default_factory=dict)
    discarded_no_run: int = 0
    duplicates_dropped: int = 0
    rejected_payloads: dict[str, int] = field(default_factory=dict)  # reason -> count
    queue: int = 0
    write_errors: int = 0
    disk_full: bool = False
    deferred_batches: int = 0
    queue_overflow: int = 0
    unknown_agents: dict[str, int] = field(default_factory=dict)
    quarantine_dropped: int = 0
    streams: StreamCounts = field(default_factory=StreamCounts)
    refused_streams: RefusedStreams = field(default_factory=RefusedStreams)
    shared_sensors: dict[str, list[str]] = field(default_factory=dict)
    queue_bytes: int = 0

    @classmethod
    def from_dict(cls, d: object) -> CollectorStatus:
        what = "status"
        m = mapping(d, what)
        run = m.get("run")
        agents = obj_field(m, "agents", what, {})
        disk_full = m.get("disk_full", False)
        if not isinstance(disk_full, bool):
            raise InvalidField(f"{what}: disk_full must be true or false")
        shared = obj_field(m, "shared_sensors", what, {})
        for mac, names in shared.items():
            if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                raise InvalidField(f"{what}: shared_sensors.{mac} must be a list of agent ids")
        return cls(
            run=None if run is None else RunStatus.from_dict(run),
            agents={a: AgentLive.from_dict(v, f"{what}: agents.{a}") for a, v in agents.items()},
            discarded_no_run=int_field(m, "discarded_no_run", what, 0),
            duplicates_dropped=int_field(m, "duplicates_dropped", what, 0),
            rejected_payloads=_counts(m, "rejected_payloads", what),
            queue=int_field(m, "queue", what, 0),
            write_errors=int_field(m, "write_errors", what, 0),
            disk_full=disk_full,
            deferred_batches=int_field(m, "deferred_batches", what, 0),
            queue_overflow=int_field(m, "queue_overflow", what, 0),
            unknown_agents=_counts(m, "unknown_agents", what),
            quarantine_dropped=int_field(m, "quarantine_dropped", what, 0),
            streams=StreamCounts.from_dict(obj_field(m, "streams", what, {})),
            refused_streams=RefusedStreams.from_dict(obj_field(m, "refused_streams", what, {})),
            shared_sensors={k: list(v) for k, v in shared.items()},
            queue_bytes=int_field(m, "queue_bytes", what, 0),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "run": None if self.run is None else self.run.to_dict(),
            "agents": {a: v.to_dict() for a, v in self.agents.items()},
            "discarded_no_run": self.discarded_no_run,
            "duplicates_dropped": self.duplicates_dropped,
            "rejected_payloads": dict(self.rejected_payloads),
            "queue": self.queue,
            "write_errors": self.write_errors,
            "disk_full": self.disk_full,
            "deferred_batches": self.deferred_batches,
            "queue_overflow": self.queue_overflow,
            "unknown_agents": dict(self.unknown_agents),
            "quarantine_dropped": self.quarantine_dropped,
            "streams": self.streams.to_dict(),
            "refused_streams": self.refused_streams.to_dict(),
            "shared_sensors": {k: list(v) for k, v in self.shared_sensors.items()},
            "queue_bytes": self.queue_bytes,
        }
