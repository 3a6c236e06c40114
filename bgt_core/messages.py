"""Typed messages between agents and the collector: the clock exchange, acknowledgements and
an agent's status (the collector's control and status replies are bgt_core.control_messages).

Standard library only, beside ``wire`` (which has the keys and the JSON size checks). Each
message is a frozen dataclass; ``from_dict`` validates a decoded JSON object once and raises
``wire.InvalidField`` with a one-line error naming the field, ``to_dict`` gives what goes on the
wire. ``docs/protocol.md`` describes the same messages in prose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from bgt_core.message_fields import (
    int_field,
    is_int,
    mapping,
    num_field,
    obj_field,
    str_field,
)
from bgt_core.wire import InvalidField

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
        m = mapping(d, "clock request")
        t1 = m.get("t1")
        if not is_int(t1):
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
        m = mapping(d, "clock reply")
        if not (is_int(m.get("t1")) and is_int(m.get("t2")) and is_int(m.get("t3"))):
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
        m = mapping(d, "clock sample")
        return cls(
            str_field(m, "at", "clock sample"),
            num_field(m, "offset_ms", "clock sample"),
            num_field(m, "rtt_ms", "clock sample"),
            obj_field(m, "chrony", "clock sample", None),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "at": self.at,
            "offset_ms": self.offset_ms,
            "rtt_ms": self.rtt_ms,
            "chrony": self.chrony,
        }


# -- acknowledgements (contract 2) -------------------------------------------------------------


# A refusal's reason is at most this long on the wire (the agent logs it).
MAX_REASON = 200


@dataclass(frozen=True, slots=True)
class Refusal:
    """Batches of one stream the collector refused and will never write: every seq up to
    ``upto`` is either durable or refused, so the agent may drop them (spool.on_refused)."""

    upto: int
    reason: str

    @classmethod
    def from_dict(cls, d: object, what: str) -> Refusal:
        m = mapping(d, what)
        upto, reason = m.get("upto"), m.get("reason")
        if not is_int(upto):
            raise InvalidField(f"{what}.upto must be an integer, got {upto!r:.40}")
        if not isinstance(reason, str) or not 0 < len(reason) <= MAX_REASON:
            raise InvalidField(f"{what}.reason must be 1-{MAX_REASON} characters of text")
        return cls(int(upto), reason)

    def to_dict(self) -> dict[str, Any]:
        return {"upto": self.upto, "reason": self.reason}


@dataclass(frozen=True, slots=True)
class Ack:
    """The collector's durable watermark for one boot of an agent: sensor MAC -> last seq, and
    the streams whose batches it refused (the negative acknowledgement): sensor MAC -> Refusal."""

    boot: str
    streams: dict[str, int] = field(default_factory=dict)
    refused: dict[str, Refusal] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: object) -> Ack:
        m = mapping(d, "ack")
        boot = str_field(m, "boot", "ack")
        streams = m.get("streams")
        if not isinstance(streams, dict):
            raise InvalidField("ack: streams must be an object")
        for mac, seq in streams.items():
            if not (isinstance(mac, str) and is_int(seq)):
                raise InvalidField(f"ack: streams.{mac} must be an integer, got {seq!r}")
        raw = m.get("refused") or {}
        if not isinstance(raw, dict):
            raise InvalidField("ack: refused must be an object")
        refused = {
            str(mac): Refusal.from_dict(r, f"ack: refused.{str(mac)[:20]}")
            for mac, r in raw.items()
        }
        return cls(boot, dict(streams), refused)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"boot": self.boot, "streams": dict(self.streams)}
        if self.refused:
            out["refused"] = {mac: r.to_dict() for mac, r in self.refused.items()}
        return out


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
        m = mapping(d, what)
        return cls(
            name=str_field(m, "name", what, None),
            mac=str_field(m, "mac", what, ""),
            backend=str_field(m, "backend", what, None),
            mode=str_field(m, "mode", what, None),
            adverts_per_s=num_field(m, "adverts_per_s", what, None),
            last_advert_age_s=num_field(m, "last_advert_age_s", what, None),
            restarts=int_field(m, "restarts", what, 0),
            readings_total=int_field(m, "readings_total", what, 0),
            bad_readings=int_field(m, "bad_readings", what, 0),
            power_cycles=int_field(m, "power_cycles", what, 0),
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
        m = mapping(d, what)
        adapters = m.get("adapters") or []
        if not isinstance(adapters, list):
            raise InvalidField(f"{what}: adapters must be a list")
        version = m.get("version")
        return cls(
            agent_id=str_field(m, "agent_id", what),
            boot_id=str_field(m, "boot_id", what, None),
            # A version is text, but a hand-written YAML may make it a number (1.0): keep it.
            version=None if version is None else str(version),
            backend=str_field(m, "backend", what, None),
            hostname=str_field(m, "hostname", what, None),
            started_ns=int_field(m, "started_ns", what, None),
            now_ns=int_field(m, "now_ns", what, None),
            adapters=tuple(
                AdapterStatus.from_dict(a, f"{what}: adapters[{i}]") for i, a in enumerate(adapters)
            ),
            spool=obj_field(m, "spool", what, None),
            resent=int_field(m, "resent", what, 0),
            chrony=obj_field(m, "chrony", what, None),
            bad_readings=int_field(m, "bad_readings", what, 0),
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
