"""`sensor-agent doctor`: does this machine hand in every advertisement, and with which backend?

Each scanning mode it can use (the kernel's management socket, bleak active, bleak passive) scans
for a while; per adapter and beacon the doctor measures reports per second, the share of reports
that repeat the previous RSSI value exactly, and the largest gap between reports. Two kinds of
throttling show in those figures: a controller's duplicate filter (about one report per scan
period: long gaps, a low rate) and BlueZ's RSSI threshold without a discovery filter (a report
only when the RSSI moved by 8 dB: no repeated values at all, a low rate). A mode is called
throttled when its median rate over the beacons is under half the best mode's, or when its
median beacon goes more than ``MAX_GAP_S`` (or half a short scan) without a report.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from bgt_core.wire import Reading
from sensor_agent.errors import AgentError
from sensor_agent.scanning.base import ScannerBackend

MAX_GAP_S = 5.0  # a beacon unheard this long while it advertises: a duplicate filter at work
RATE_SHARE = 0.5  # a mode under half the best mode's median rate is throttled


@dataclass(frozen=True, slots=True)
class BeaconFigures:
    reports: int
    per_s: float
    repeated_share: float  # consecutive reports with exactly the same RSSI
    largest_gap_s: float


@dataclass
class ModeResult:
    mode: str
    error: str | None = None  # the mode could not run here: why
    beacons: dict[tuple[str, str], BeaconFigures] = field(default_factory=dict)  # (adapter, beacon)
    throttled: bool = False

    @property
    def median_rate(self) -> float:
        return statistics.median(b.per_s for b in self.beacons.values()) if self.beacons else 0.0

    @property
    def median_gap_s(self) -> float:
        return (
            statistics.median(b.largest_gap_s for b in self.beacons.values())
            if self.beacons
            else float("inf")
        )


@dataclass
class Diagnosis:
    modes: list[ModeResult]
    recommended: str | None  # the mode to use; None when every mode is throttled or failed

    @property
    def usable(self) -> bool:
        return any(m.error is None for m in self.modes)


def figures(
    readings: Sequence[tuple[str, Reading]],
    seconds: float,
    span: tuple[float, float] | None = None,
) -> dict[tuple[str, str], BeaconFigures]:
    """Per (adapter, beacon): reports/s over ``seconds``, repeated-RSSI share, largest gap
    (with ``span``, the scan's start and end in monotonic seconds, the silences before the first
    and after the last report count as gaps too)."""
    series: dict[tuple[str, str], list[Reading]] = defaultdict(list)
    for adapter, r in readings:
        series[(adapter, r.beacon)].append(r)
    out = {}
    for key, rs in series.items():
        rs.sort(key=lambda r: r.mono_ns or r.t_ns)
        times = [(r.mono_ns or r.t_ns) / 1e9 for r in rs]
        if span is not None:
            times = [span[0], *times, span[1]]
        gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
        same = sum(1 for a, b in zip(rs, rs[1:], strict=False) if a.rssi == b.rssi)
        out[key] = BeaconFigures(
            len(rs),
            len(rs) / seconds,
            same / (len(rs) - 1) if len(rs) > 1 else 0.0,
            max(gaps) if gaps else seconds,
        )
    return out


async def scan_for(
    backend: ScannerBackend, seconds: float
) -> tuple[list[tuple[str, Reading]], tuple[float, float]]:
    """Every report of ``seconds`` of scanning, and the scan's span in monotonic seconds."""
    got: list[tuple[str, Reading]] = []
    await backend.start(lambda adapter, r: got.append((adapter, r)))
    start = time.monotonic_ns() / 1e9
    try:
        await asyncio.sleep(seconds)
    finally:
        await backend.stop()
    return got, (start, time.monotonic_ns() / 1e9)


async def diagnose(
    modes: Sequence[tuple[str, Callable[[], ScannerBackend]]],
    seconds: float,
    progress: Callable[[str], None] = lambda _: None,
) -> Diagnosis:
    """Scan ``seconds`` with each mode in turn and judge them against each other."""
    results = []
    for name, make in modes:
        progress(name)
        try:
            got, span = await scan_for(make(), seconds)
        except AgentError as e:
            results.append(ModeResult(name, error=str(e)))
            continue
        results.append(ModeResult(name, beacons=figures(got, seconds, span)))
    ran = [m for m in results if m.error is None and m.beacons]
    best = max((m.median_rate for m in ran), default=0.0)
    # A short scan cannot show a 5 s gap: there, a silence over half the scan is one.
    max_gap = min(MAX_GAP_S, seconds / 2)
    for m in results:
        if m.error is None:
            m.throttled = (
                not m.beacons or m.median_rate < RATE_SHARE * best or m.median_gap_s > max_gap
            )
    fine = [m for m in ran if not m.throttled]
    recommended = max(fine, key=lambda m: m.median_rate).mode if fine else None
    return Diagnosis(results, recommended)
