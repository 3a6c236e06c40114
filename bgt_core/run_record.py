"""run.yaml: what a run directory says about itself, as a typed, versioned record.

The collector writes it when a run starts and again, with the summary, when it stops
(``collector.store.RunWriter.write_yaml``); `annotator simulate` writes one for its simulated
runs; the collector's run list, crash recovery and the annotator read it back with
:meth:`RunRecord.from_dict`, which takes every run.yaml written so far (version 1; files from
before the version key have none and read as version 1) and gives one-line errors naming the
file. Keys it does not know (the software version, the site, a simulator's parameters, ...)
are kept in ``meta`` and written back as they were.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, TypedDict

from bgt_core.message_fields import is_int, is_num

RUN_VERSION = 1


class BeaconCount(TypedDict):
    """One beacon as one sensor heard it over the run."""

    readings: int
    rate_hz: float | None  # readings per second of the run's span


class SensorEntry(TypedDict, total=False):
    """One sensor (adapter) of one agent: its file and what the run's accounting says of it."""

    adapter: str | None
    mac: str
    file: str  # relative to the run directory
    backend: str | None
    mode: str | None
    readings: int
    batches: int
    beacons: dict[str, BeaconCount]  # the most heard first
    gaps: int
    missing_batches: int
    lost_batches: int


class AgentEntry(TypedDict, total=False):
    """One agent of the run."""

    hostname: str | None
    version: str | None
    backend: str | None
    boot_ids: list[str]
    sensors: dict[str, SensorEntry]
    clock: list[dict[str, Any]]  # bgt_core.messages.ClockSample.to_dict() per measurement


# The summary a stopped run gains (collector.summary.run_summary), in the order it is written.
SUMMARY_KEYS = (
    "layout",
    "shared_sensors",
    "refused_streams",
    "stopped_by",
    "gaps",
    "missing_batches",
    "lost_batches",
    "duplicates_dropped",
    "rejected_payloads",
    "restarts",
)
_OWN_KEYS = frozenset(
    {"version", "id", "name", "start", "start_ns", "stop", "stop_ns", "readings", "agents"}
)


class RunRecordError(ValueError):
    """A run.yaml that is not one; the message is one line naming the file."""


def iso_utc(ns: int) -> str:
    """A nanosecond Unix time as run.yaml writes it: ISO 8601 UTC to the millisecond."""
    return (
        datetime.fromtimestamp(ns / 1e9, tz=UTC)
        .isoformat(timespec="milliseconds")
        .replace("+00:00", "Z")
    )


@dataclass(frozen=True, slots=True)
class RunRecord:
    """What run.yaml holds. ``start`` and ``stop`` are written from the nanosecond times;
    ``meta`` holds the keys written at the top level beside the record's own (software
    version, site, notes), ``summary`` those of SUMMARY_KEYS a stopped run has."""

    run_id: str
    name: str | None = None
    start_ns: int | None = None
    stop_ns: int | None = None
    readings: int | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    summary: Mapping[str, Any] = field(default_factory=dict)
    agents: Mapping[str, AgentEntry] = field(default_factory=dict)
    version: int = RUN_VERSION

    @property
    def stopped(self) -> bool:
        return self.stop_ns is not None

    def to_dict(self) -> dict[str, Any]:
        """The document, in the order run.yaml has always been written."""
        start = self.start_ns
        stop = self.stop_ns
        return {
            "version": self.version,
            "id": self.run_id,
            "name": self.name,
            "start": iso_utc(start) if start is not None else None,
            "start_ns": start,
            "stop": iso_utc(stop) if stop is not None else None,
            "stop_ns": stop,
            **{k: v for k, v in self.meta.items() if k not in _OWN_KEYS},
            "readings": self.readings,
            **{k: self.summary[k] for k in SUMMARY_KEYS if k in self.summary},
            **{k: v for k, v in self.summary.items() if k not in SUMMARY_KEYS + tuple(_OWN_KEYS)},
            "agents": {a: dict(e) for a, e in self.agents.items()},
        }

    def listing(self) -> dict[str, Any]:
        """The run as the collector's run list shows it."""
        d = self.to_dict()
        return {k: d[k] for k in ("name", "start", "stop", "readings")} | {"run_id": self.run_id}

    @classmethod
    def from_dict(cls, d: object, where: str, *, default_id: str = "") -> RunRecord:
        """The record of a run.yaml document; RunRecordError (one line, naming ``where``) when a
        key present has the wrong type. ``default_id``: the id of a file that states none (its
        directory's name)."""
        if d is None:
            d = {}
        if not isinstance(d, dict):
            raise RunRecordError(f"{where}: not a run.yaml (a mapping of keys)")
        version = d.get("version", RUN_VERSION)
        if version != RUN_VERSION:
            raise RunRecordError(
                f"{where}: run.yaml version {version!r}; this suite reads version {RUN_VERSION}"
            )
        run_id = d.get("id", default_id)
        if not isinstance(run_id, str | int) or isinstance(run_id, bool):
            raise RunRecordError(f"{where}: id must be a string, got {run_id!r}")
        name = d.get("name")
        if name is not None and not isinstance(name, str | int):
            raise RunRecordError(f"{where}: name must be a string, got {name!r}")
        agents = d.get("agents") or {}
        if not isinstance(agents, dict) or not all(
            isinstance(a, dict | type(None)) for a in agents.values()
        ):
            raise RunRecordError(f"{where}: agents must map each agent to its keys")
        for agent, entry in agents.items():
            sensors = (entry or {}).get("sensors") or {}
            if not isinstance(sensors, dict):
                raise RunRecordError(f"{where}: agents.{agent}.sensors must be a mapping")
        return cls(
            run_id=str(run_id),
            name=None if name is None else str(name),
            start_ns=_count(d, "start_ns", where),
            stop_ns=_count(d, "stop_ns", where),
            readings=_count(d, "readings", where),
            meta={k: v for k, v in d.items() if k not in _OWN_KEYS and k not in SUMMARY_KEYS},
            summary={k: d[k] for k in SUMMARY_KEYS if k in d},
            agents={str(a): (e or {}) for a, e in agents.items()},
            version=RUN_VERSION,
        )


def _count(d: Mapping[str, Any], key: str, where: str) -> int | None:
    v = d.get(key)
    if v is None:
        return None
    if is_num(v) and not is_int(v) and float(v).is_integer():
        v = int(v)
    if not is_int(v) or v < 0:
        raise RunRecordError(f"{where}: {key} must be a whole number >= 0, got {v!r}")
    return v
