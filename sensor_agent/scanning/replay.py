"""Replay backend: plays recorded ``.mbd`` files as if their sensors were local adapters.

Every distinct sensor MAC in the files becomes a virtual adapter with that MAC. Rows of all
files are merged in time order and paced like the recording (scaled by ``speed``; 0 = as fast
as possible). Timestamps are shifted by one constant so the first row is "now", or kept exactly.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

from bgt_core.formats._textio import iter_lines
from bgt_core.formats.mbd import parse_line
from bgt_core.wire import RSSI_MAX, RSSI_MIN, T_NS_MAX, T_NS_MIN, Reading
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, Clocks, ScannerBackend

log = logging.getLogger(__name__)

# The replay sleeps at least this long at a time and then delivers every row that has come due:
# at most 50 wake-ups a second whatever the advert rate, each row at most this late.
GRANULE_S = 0.02


class _Row(NamedTuple):
    t_ns: int
    sensor: str
    beacon: str
    rssi: int


class _Skipped:
    """Readings of one file left out for an implausible value: how many, and the first one."""

    def __init__(self) -> None:
        self.count = 0
        self.first = ""


def _rows(path: Path, skipped: _Skipped | None = None) -> Iterator[_Row]:
    """Rows of one file (extra columns dropped); a malformed line raises BackendError naming file
    and line. A reading with an implausible RSSI (the dataset holds a +42 dBm) is skipped and
    counted in ``skipped``: one absurd value must not stop the replay of all the others."""
    for lineno, line in iter_lines(path, BackendError):
        if not line.strip():
            continue
        try:
            r = parse_line(line)
        except ValueError as e:
            raise BackendError(f"{path}:{lineno}: {e}") from None
        if not RSSI_MIN <= r.rssi <= RSSI_MAX:
            if skipped is not None:
                skipped.count += 1
                skipped.first = skipped.first or f"{path}:{lineno}: RSSI {r.rssi} dBm out of range"
            continue
        yield _Row(r.t_ns, r.sensor, r.beacon, r.rssi)


class ReplayBackend(ScannerBackend):
    name = "replay"

    def __init__(
        self,
        paths: Sequence[str | Path],
        speed: float = 1.0,
        keep_time: bool = False,
        clocks: Clocks | None = None,
        yield_every: int = 200,
        granule_s: float = GRANULE_S,
    ) -> None:
        if not paths:
            raise BackendError("the replay backend needs at least one .mbd file")
        if speed < 0:
            raise BackendError(f"replay speed must be >= 0, got {speed}")
        self.paths = tuple(Path(p) for p in paths)
        self.speed = float(speed)
        self.keep_time = keep_time
        self.clocks = clocks or Clocks()
        self.yield_every = max(1, yield_every)
        self.granule_s = granule_s
        self.rows_total = 0
        self.rows_delivered = 0
        self.rows_skipped = 0  # implausible readings left out (see check)
        self._adapters: tuple[AdapterInfo, ...] = ()
        self._checked = False
        self._task: asyncio.Task[None] | None = None
        self._finished = asyncio.Event()

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return self._adapters

    def check(self) -> None:
        """Read every file once: validate all rows and learn the sensors (before anything is sent)."""
        sensors: dict[str, None] = {}
        total = 0
        skipped_total = 0
        for p in self.paths:
            if not p.exists():  # not a regular file: _rows says what it is
                raise BackendError(f"{p}: no such replay file")
            skipped = _Skipped()
            for r in _rows(p, skipped):
                sensors.setdefault(r.sensor, None)
                total += 1
                if self.keep_time and not T_NS_MIN <= r.t_ns <= T_NS_MAX:
                    raise BackendError(
                        f"{p}: timestamp {r.t_ns} ns is not a plausible Unix time "
                        "(use shifted time, not --replay-keep-time)"
                    )
            if skipped.count:
                log.warning(
                    "replay: skipped %d implausible reading(s) of %s (first: %s); "
                    "the rest are replayed",
                    skipped.count,
                    p.name,
                    skipped.first,
                )
            skipped_total += skipped.count
        self.rows_total = total
        self.rows_skipped = skipped_total
        self._checked = True
        self._adapters = tuple(
            AdapterInfo(f"replay-{mac}", mac, "replay", "replay") for mac in sensors
        )
        log.info(
            "replay: %d rows from %d file(s), %d sensor(s)%s",
            total,
            len(self.paths),
            len(sensors),
            f", {skipped_total} implausible skipped" if skipped_total else "",
        )

    async def start(self, sink: AdvertSink) -> None:
        if not self._checked:
            await asyncio.to_thread(self.check)
        self._task = asyncio.create_task(self._run(sink), name="replay")

    async def _run(self, sink: AdvertSink) -> None:
        clocks = self.clocks
        try:
            merged = heapq.merge(*(_rows(p) for p in self.paths), key=lambda r: r.t_ns)
            first: int | None = None
            start_wall = start_mono = 0
            for i, row in enumerate(merged):
                if first is None:
                    first = row.t_ns
                    start_wall, start_mono = clocks.wall_ns(), clocks.mono_ns()
                if self.speed > 0:
                    due = start_mono + int((row.t_ns - first) / self.speed)
                    wait = due - clocks.mono_ns()
                    if wait > 0:
                        await clocks.sleep(max(wait / 1e9, self.granule_s))
                else:
                    due = clocks.mono_ns()
                    if i % self.yield_every == 0:
                        await clocks.sleep(0)  # let the publisher run between chunks
                if self.keep_time:
                    t_ns, mono = row.t_ns, 0  # reception happened long ago: monotonic unknown
                else:
                    # monotonic time of the scheduled reception, consistent with t_ns
                    t_ns, mono = start_wall + (row.t_ns - first), due
                sink(row.sensor, Reading(t_ns, row.beacon, row.rssi, mono))
                self.rows_delivered += 1
        finally:
            self._finished.set()

    async def wait_finished(self) -> None:
        """Returns once every row was delivered; re-raises what stopped the replay early."""
        if self._task is not None:
            await asyncio.shield(self._task)
        await self._finished.wait()

    async def stop(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self._finished.set()
