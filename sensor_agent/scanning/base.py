"""The seam between the agent and whatever produces advertisements: ``ScannerBackend`` and ``AdvertSink``.

Backends call the sink from the event loop's thread with ``(adapter_mac, Reading)``; the agent
never needs to know whether a reading came from BlueZ, a file or a simulation.
"""

from __future__ import annotations

import abc
import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from bgt_core.wire import Reading

AdvertSink = Callable[[str, Reading], None]
"""Receives ``(adapter_mac, reading)``; adapter_mac is 12 lowercase hex digits. Must not block."""

WallClock = Callable[[], int]  # Unix ns
MonoClock = Callable[[], int]  # monotonic ns
Sleeper = Callable[[float], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class Clocks:
    """The time sources a backend may read; tests pass fakes."""

    wall_ns: WallClock = time.time_ns
    mono_ns: MonoClock = time.monotonic_ns
    sleep: Sleeper = asyncio.sleep


@dataclass(frozen=True, slots=True)
class AdapterInfo:
    """One scanning adapter (physical or virtual) as the status queryable reports it."""

    name: str  # "hci0", or a descriptive name for virtual adapters
    mac: str  # 12 lowercase hex digits: the sensor id in every batch
    backend: str  # "bleak" | "replay" | "simulated"
    mode: str  # "active" | "passive" | "replay" | "simulated"


class ScannerBackend(abc.ABC):
    """Produces readings for one or more adapters until stopped (or, for finite sources, finished)."""

    name: str = "?"

    @property
    @abc.abstractmethod
    def adapters(self) -> tuple[AdapterInfo, ...]:
        """Known after ``start`` returns (the replay backend knows them once its files are checked)."""

    def check(self) -> None:  # noqa: B027 - an optional hook; most backends need none
        """Validate inputs (files, names) before anything is connected; may block briefly."""

    @abc.abstractmethod
    async def start(self, sink: AdvertSink) -> None:
        """Begin delivering readings to ``sink``; returns once scanning is under way."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Stop delivering; idempotent. No sink call happens after it returns."""

    async def wait_finished(self) -> None:
        """Returns when a finite source has delivered everything; never for live scanners."""
        await asyncio.Event().wait()

    def restarts(self, adapter_mac: str) -> int:
        """How many times the backend restarted this adapter's scanner (watchdog)."""
        return 0

    def power_cycles(self, adapter_mac: str) -> int:
        """How many times the watchdog power-cycled this adapter."""
        return 0
