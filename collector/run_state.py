"""state.json: the crash-recovery record of an active run, as a typed, versioned record.

The writer replaces it atomically after every fsync (``RunWriter.write_state``); a collector
that was killed reads it back (``RunState.from_dict``) to reopen the run with its files cut to
what the record covers. Version 2 keys files by agent and sensor (``rssi/<agent>/<sensor>.mbd``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypedDict

from bgt_core.messages import ClockSample
from collector.errors import CollectorError

STATE_VERSION = 2


class SensorRecord(TypedDict):
    """One stream's counts in state.json (``store.SensorStats``)."""

    readings: int
    batches: int
    beacons: dict[str, int]  # readings per beacon MAC (hex)


@dataclass(frozen=True, slots=True)
class RunState:
    """What state.json holds. ``files`` and ``sensors`` are keyed by ``agent/sensor``;
    ``tracker`` is ``ingest.StreamTracker.to_state()``, which has its own converter."""

    run_id: str
    name: str
    start_ns: int
    meta: Mapping[str, Any]
    readings: int = 0
    files: Mapping[str, int] = field(default_factory=dict)  # durable bytes per stream file
    sensors: Mapping[str, SensorRecord] = field(default_factory=dict)
    tracker: Mapping[str, Any] = field(default_factory=dict)
    lost_base: Mapping[str, int] = field(default_factory=dict)
    clock: Mapping[str, tuple[ClockSample, ...]] = field(default_factory=dict)
    restarts: int = 0
    quarantined_bytes: int = 0
    active: bool = True
    version: int = STATE_VERSION

    def to_dict(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "active": self.active,
            "run_id": self.run_id,
            "name": self.name,
            "start_ns": self.start_ns,
            "meta": dict(self.meta),
            "readings": self.readings,
            "files": dict(self.files),
            "sensors": {k: dict(v) for k, v in self.sensors.items()},
            "tracker": dict(self.tracker),
            "lost_base": dict(self.lost_base),
            "clock": {a: [s.to_dict() for s in v] for a, v in self.clock.items()},
            "restarts": self.restarts,
            "quarantined_bytes": self.quarantined_bytes,
        }

    @classmethod
    def from_dict(cls, d: object, where: str) -> RunState:
        """The record of a state.json document; one-line CollectorError naming ``where``."""
        if not isinstance(d, dict):
            raise CollectorError(f"{where}: not a collector state file")
        if d.get("version") != STATE_VERSION:
            raise CollectorError(
                f"{where}: version {d.get('version')} state of an unfinished run, written by an "
                f"older collector (this one resumes version {STATE_VERSION}); finish the run with "
                "that collector, or move the file aside to start fresh"
            )
        try:
            sensors: dict[str, SensorRecord] = {}
            for name, st in _mapping(d.get("sensors", {}), "sensors").items():
                beacons = st.get("beacons") or {}
                sensors[str(name)] = SensorRecord(
                    readings=int(st["readings"]),
                    batches=int(st["batches"]),
                    beacons={str(k): int(v) for k, v in _mapping(beacons, "beacons").items()},
                )
            return cls(
                run_id=str(d["run_id"]),
                name=str(d["name"]),
                start_ns=int(d["start_ns"]),
                meta=dict(_mapping(d["meta"], "meta")),
                readings=int(d.get("readings", 0)),
                files={str(k): int(v) for k, v in _mapping(d.get("files", {}), "files").items()},
                sensors=sensors,
                tracker=dict(_mapping(d["tracker"], "tracker")),
                lost_base={
                    str(k): int(v) for k, v in _mapping(d.get("lost_base", {}), "lost_base").items()
                },
                clock={
                    str(a): tuple(ClockSample.from_dict(s) for s in v)
                    for a, v in _mapping(d.get("clock", {}), "clock").items()
                },
                restarts=int(d.get("restarts", 0)),
                quarantined_bytes=int(d.get("quarantined_bytes", 0)),
                active=bool(d.get("active", False)),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:  # WireError is a ValueError
            raise CollectorError(f"{where}: cannot resume the run: {e!r}") from None


def _mapping(v: object, what: str) -> Mapping[str, Any]:
    if not isinstance(v, dict):
        raise TypeError(f"{what} is not a mapping")
    return v
