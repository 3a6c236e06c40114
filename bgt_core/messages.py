"""Typed control messages between agents, the collector and its operators.

Standard library only, beside ``wire`` (which has the keys and the JSON size checks). Each
message is a frozen dataclass; ``from_dict`` validates a decoded JSON object once and raises
``wire.InvalidField`` with a one-line error naming the field, ``to_dict`` gives what goes on the
wire. ``docs/protocol.md`` describes the same messages in prose.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeGuard

from bgt_core.wire import InvalidField

_REQUIRED: Any = object()


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _get(d: Mapping[str, Any], key: str, what: str, default: Any) -> Any:
    if key in d and d[key] is not None:
        return d[key]
    if default is _REQUIRED:
        raise InvalidField(f"{what}: {key} is missing")
    return default


def _int(d: Mapping[str, Any], key: str, what: str, default: Any = _REQUIRED) -> Any:
    v = _get(d, key, what, default)
    if v is not default and not _is_int(v):
        raise InvalidField(f"{what}: {key} must be an integer, got {v!r}")
    return v


def _num(d: Mapping[str, Any], key: str, what: str, default: Any = _REQUIRED) -> Any:
    v = _get(d, key, what, default)
    if v is not default and not _is_num(v):
        raise InvalidField(f"{what}: {key} must be a number, got {v!r}")
    return v if v is default or v is None else float(v)


def _str(d: Mapping[str, Any], key: str, what: str, default: Any = _REQUIRED) -> Any:
    v = _get(d, key, what, default)
    if v is not default and not isinstance(v, str):
        raise InvalidField(f"{what}: {key} must be a string, got {v!r}")
    return v


def _obj(d: Mapping[str, Any], key: str, what: str, default: Any = _REQUIRED) -> Any:
    v = _get(d, key, what, default)
    if v is not default and not isinstance(v, dict):
        raise InvalidField(f"{what}: {key} must be an object, got {type(v).__name__}")
    return v


def _mapping(d: object, what: str) -> Mapping[str, Any]:
    if not isinstance(d, Mapping):
        raise InvalidField(f"{what} must be a JSON object, got {type(d).__name__}")
    return d


# -- clock exchange (contract 4) ---------------------------------------------------------------


def clock_offset(t1: int, t2: int, t3: int, t4: int) -> tuple[float, int]:
    """The four-timestamp (NTP) estimate, all Unix ns: t1 we ask, t2 the peer receives, t3 the
    peer answers, t4 we receive. Returns (offset, rtt): offset = ((t2 - t1) + (t3 - t4)) / 2 is
    how far the peer's clock is ahead of ours, rtt = (t4 - t1) - (t3 - t2) the network round
    trip without the peer's own delay."""
    return ((t2 - t1) + (t3 - t4)) / 2, (t4 - t1) - (t3 - t2)


@dataclass(frozen=True, slots=True)
class ClockRequest:
    t1: int  # the asker's clock when it sent the request (Unix ns)

    @classmethod
    def from_dict(cls, d: object) -> ClockRequest:
        m = _mapping(d, "clock request")
        t1 = m.get("t1")
        if not _is_int(t1):
            raise InvalidField(f"t1 must be an integer (ns), got {t1!r}")
        return cls(t1)

    def to_dict(self) -> dict[str, Any]:
        return {"t1": self.t1}


@dataclass(frozen=True, slots=True)
class ClockReply:
    t1: int  # echoed from the request
    t2: int  # the agent's clock when the request arrived
    t3: int  # the agent's clock when it answered
    chrony: dict[str, Any] | None = None  # the agent's `chronyc tracking`, if it has one

    @classmethod
    def from_dict(cls, d: object) -> ClockReply:
        m = _mapping(d, "clock reply")
        if not (_is_int(m.get("t1")) and _is_int(m.get("t2")) and _is_int(m.get("t3"))):
            raise InvalidField("clock reply needs integer t1, t2 and t3 (ns)")
        chrony = m.get("chrony")
        if chrony is not None and not isinstance(chrony, dict):
            raise InvalidField("clock reply chrony must be an object or null")
        return cls(m["t1"], m["t2"], m["t3"], chrony)

    def to_dict(self) -> dict[str, Any]:
        return {"t1": self.t1, "t2": self.t2, "t3": self.t3, "chrony": self.chrony}


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One clock measurement of an agent, as run.yaml and state.json keep it."""

    at: str  # ISO UTC time of t4
    offset_ms: float  # agent clock minus ours
    rtt_ms: float
    chrony: dict[str, Any] | None = None

    @classmethod
    def measure(cls, reply: ClockReply, t1: int, t4: int, at: str) -> ClockSample:
        if reply.t1 != t1:
            raise InvalidField("clock reply does not echo our t1")
        offset, rtt = clock_offset(t1, reply.t2, reply.t3, t4)
        return cls(at, round(offset / 1e6, 3), round(rtt / 1e6, 3), reply.chrony)

    @classmethod
    def from_dict(cls, d: object) -> ClockSample:
        m = _mapping(d, "clock sample")
        return cls(
            _str(m, "at", "clock sample"),
            _num(m, "offset_ms", "clock sample"),
            _num(m, "rtt_ms", "clock sample"),
            _obj(m, "chrony", "clock sample", None),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "at": self.at,
            "offset_ms": self.offset_ms,
            "rtt_ms": self.rtt_ms,
            "chrony": self.chrony,
        }


# -- acknowledgements (contract 2) -------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Ack:
    """The collector's durable watermark for one boot of an agent: sensor MAC -> last seq."""

    boot: str
    streams: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: object) -> Ack:
        m = _mapping(d, "ack")
        boot = _str(m, "boot", "ack")
        streams = m.get("streams")
        if not isinstance(streams, dict):
            raise InvalidField("ack: streams must be an object")
        for mac, seq in streams.items():
            if not (isinstance(mac, str) and _is_int(seq)):
                raise InvalidField(f"ack: streams.{mac} must be an integer, got {seq!r}")
        return cls(boot, dict(streams))

    def to_dict(self) -> dict[str, Any]:
        return {"boot": self.boot, "streams": dict(self.streams)}


# -- agent status -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class AdapterStatus:
    name: str | None
    mac: str  # as the agent reports it (any case, with or without colons)
    backend: str | None = None
    mode: str | None = None
    adverts_per_s: float | None = None
    last_advert_age_s: float | None = None
    restarts: int = 0
    readings_total: int = 0
    bad_readings: int = 0
    power_cycles: int = 0

    @classmethod
    def from_dict(cls, d: object, what: str = "adapter") -> AdapterStatus:
        m = _mapping(d, what)
        return cls(
            name=_str(m, "name", what, None),
            mac=_str(m, "mac", what, ""),
            backend=_str(m, "backend", what, None),
            mode=_str(m, "mode", what, None),
            adverts_per_s=_num(m, "adverts_per_s", what, None),
            last_advert_age_s=_num(m, "last_advert_age_s", what, None),
            restarts=_int(m, "restarts", what, 0),
            readings_total=_int(m, "readings_total", what, 0),
            bad_readings=_int(m, "bad_readings", what, 0),
            power_cycles=_int(m, "power_cycles", what, 0),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "mac": self.mac,
            "backend": self.backend,
            "mode": self.mode,
            "adverts_per_s": self.adverts_per_s,
            "last_advert_age_s": self.last_advert_age_s,
            "restarts": self.restarts,
            "readings_total": self.readings_total,
            "bad_readings": self.bad_readings,
            "power_cycles": self.power_cycles,
        }

    def matches(self, sensor: str) -> bool:
        """Whether this adapter is sensor ``sensor`` (a MAC in wire form: 12 lowercase hex)."""
        return self.mac.replace(":", "").lower() == sensor


@dataclass(frozen=True, slots=True)
class AgentStatus:
    """An agent's status reply. Only ``agent_id`` is required: older agents and tools send less."""

    agent_id: str
    boot_id: str | None = None
    version: str | None = None
    backend: str | None = None
    hostname: str | None = None
    started_ns: int | None = None
    now_ns: int | None = None  # the agent's wall clock when it answered
    adapters: tuple[AdapterStatus, ...] = ()
    spool: dict[str, Any] | None = None
    resent: int = 0
    chrony: dict[str, Any] | None = None
    bad_readings: int = 0

    @classmethod
    def from_dict(cls, d: object) -> AgentStatus:
        what = "agent status"
        m = _mapping(d, what)
        adapters = m.get("adapters") or []
        if not isinstance(adapters, list):
            raise InvalidField(f"{what}: adapters must be a list")
        version = m.get("version")
        return cls(
            agent_id=_str(m, "agent_id", what),
            boot_id=_str(m, "boot_id", what, None),
            # A version is text, but a hand-written YAML may make it a number (1.0): keep it.
            version=None if version is None else str(version),
            backend=_str(m, "backend", what, None),
            hostname=_str(m, "hostname", what, None),
            started_ns=_int(m, "started_ns", what, None),
            now_ns=_int(m, "now_ns", what, None),
            adapters=tuple(
                AdapterStatus.from_dict(a, f"{what}: adapters[{i}]") for i, a in enumerate(adapters)
            ),
            spool=_obj(m, "spool", what, None),
            resent=_int(m, "resent", what, 0),
            chrony=_obj(m, "chrony", what, None),
            bad_readings=_int(m, "bad_readings", what, 0),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "agent_id": self.agent_id,
            "boot_id": self.boot_id,
            "version": self.version,
            "backend": self.backend,
            "hostname": self.hostname,
            "started_ns": self.started_ns,
            "now_ns": self.now_ns,
            "adapters": [a.to_dict() for a in self.adapters],
            "spool": self.spool,
            "resent": self.resent,
            "chrony": self.chrony,
            "bad_readings": self.bad_readings,
        }

    def adapter(self, sensor: str) -> AdapterStatus | None:
        return next((a for a in self.adapters if a.matches(sensor)), None)


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


@dataclass(frozen=True, slots=True)
class StartRequest:
    name: str | None = None
    max_offset_ms: float | None = None  # warn about agents whose clock is off by more
    strict: bool = False  # ... and refuse to start instead

    @classmethod
    def from_dict(cls, d: object) -> StartRequest:
        m = _mapping(d, "start request")
        name = m.get("name")
        check_run_name(name)
        max_off = m.get("max_offset_ms")
        if max_off is not None and (
            not _is_num(max_off) or not math.isfinite(max_off) or not 0 <= max_off <= 86_400_000
        ):
            raise InvalidField(
                "start: max_offset_ms must be a finite number of ms in 0..86400000, or null"
            )
        strict = m.get("strict", False)
        if not isinstance(strict, bool):
            raise InvalidField("start: strict must be true or false")
        return cls(name, None if max_off is None else float(max_off), strict)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name}
        if self.max_offset_ms is not None:
            out["max_offset_ms"] = self.max_offset_ms
        if self.strict:
            out["strict"] = True
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
        m = _mapping(d, what)
        clock = _obj(m, "clock", what, {})
        warnings = m.get("clock_warnings") or []
        if not (isinstance(warnings, list) and all(isinstance(w, str) for w in warnings)):
            raise InvalidField(f"{what}: clock_warnings must be a list of strings")
        return cls(
            _str(m, "run_id", what),
            _str(m, "run_dir", what),
            {
                a: AgentClock(
                    _num(_mapping(v, f"{what}: clock.{a}"), "offset_ms", what),
                    _num(v, "rtt_ms", what),
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
        m = _mapping(d, what)
        return cls(
            _str(m, "run_id", what),
            _str(m, "run_dir", what),
            _int(m, "readings", what),
            _int(m, "gaps", what, 0),
            _int(m, "missing_batches", what, 0),
            _int(m, "lost_batches", what, 0),
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
        m = dict(_mapping(d, f"{command} reply"))
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
    m = _obj(d, key, what, {})
    for k, v in m.items():
        if not _is_int(v):
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

    @classmethod
    def from_dict(cls, d: object, what: str = "sensor") -> SensorRate:
        m = _mapping(d, what)
        recent = m.get("recent_rssi") or []
        if not (isinstance(recent, list) and all(_is_int(v) for v in recent)):
            raise InvalidField(f"{what}: recent_rssi must be a list of integers")
        return cls(
            _num(m, "rate_hz", what, 0.0),
            _num(m, "last_seen_age_s", what, None),
            _int(m, "last_rssi", what, None),
            _int(m, "readings", what, 0),
            tuple(recent),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "rate_hz": self.rate_hz,
            "last_seen_age_s": self.last_seen_age_s,
            "last_rssi": self.last_rssi,
            "readings": self.readings,
            "recent_rssi": list(self.recent_rssi),
        }


@dataclass(frozen=True, slots=True)
class AgentLive:
    alive: bool = False  # its liveliness token is present
    sensors: dict[str, SensorRate] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: object, what: str = "agent") -> AgentLive:
        m = _mapping(d, what)
        alive = m.get("alive", False)
        if not isinstance(alive, bool):
            raise InvalidField(f"{what}: alive must be true or false")
        sensors = _obj(m, "sensors", what, {})
        return cls(
            alive,
            {mac: SensorRate.from_dict(s, f"{what}: sensors.{mac}") for mac, s in sensors.items()},
        )

    def to_dict(self) -> dict[str, Any]:
        return {"alive": self.alive, "sensors": {k: s.to_dict() for k, s in self.sensors.items()}}


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
        m = _mapping(d, what)
        stopping = m.get("stopping", False)
        if not isinstance(stopping, bool):
            raise InvalidField(f"{what}: stopping must be true or false")
        clock = _obj(m, "clock", what, {})
        return cls(
            _str(m, "run_id", what),
            _int(m, "readings", what, 0),
            _str(m, "name", what, ""),
            _str(m, "run_dir", what, ""),
            _str(m, "start", what, ""),
            _int(m, "sensors", what, 0),
            stopping,
            _int(m, "restarts", what, 0),
            _int(m, "buffered_bytes", what, 0),
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
            _int(d, "total", what, 0),
            _int(d, "shown", what, 0),
            _int(d, "admitted", what, 0),
            _int(d, "open_files", what, 0),
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
    """Batches refused by the stream caps: total, streams, and the worst agents."""

    batches: int = 0
    streams: int = 0
    by_agent: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RefusedStreams:
        what = "status: refused_streams"
        return cls(
            _int(d, "batches", what, 0), _int(d, "streams", what, 0), _counts(d, "by_agent", what)
        )

    def to_dict(self) -> dict[str, Any]:
        return {"batches": self.batches, "streams": self.streams, "by_agent": dict(self.by_agent)}


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
        m = _mapping(d, what)
        run = m.get("run")
        agents = _obj(m, "agents", what, {})
        disk_full = m.get("disk_full", False)
        if not isinstance(disk_full, bool):
            raise InvalidField(f"{what}: disk_full must be true or false")
        shared = _obj(m, "shared_sensors", what, {})
        for mac, names in shared.items():
            if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                raise InvalidField(f"{what}: shared_sensors.{mac} must be a list of agent ids")
        return cls(
            run=None if run is None else RunStatus.from_dict(run),
            agents={a: AgentLive.from_dict(v, f"{what}: agents.{a}") for a, v in agents.items()},
            discarded_no_run=_int(m, "discarded_no_run", what, 0),
            duplicates_dropped=_int(m, "duplicates_dropped", what, 0),
            rejected_payloads=_counts(m, "rejected_payloads", what),
            queue=_int(m, "queue", what, 0),
            write_errors=_int(m, "write_errors", what, 0),
            disk_full=disk_full,
            deferred_batches=_int(m, "deferred_batches", what, 0),
            queue_overflow=_int(m, "queue_overflow", what, 0),
            unknown_agents=_counts(m, "unknown_agents", what),
            quarantine_dropped=_int(m, "quarantine_dropped", what, 0),
            streams=StreamCounts.from_dict(_obj(m, "streams", what, {})),
            refused_streams=RefusedStreams.from_dict(_obj(m, "refused_streams", what, {})),
            shared_sensors={k: list(v) for k, v in shared.items()},
            queue_bytes=_int(m, "queue_bytes", what, 0),
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
