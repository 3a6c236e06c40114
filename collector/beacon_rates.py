"""Readings per second of each beacon at each sensor, and telling when one falls.

A sensor whose controller starts throttling (a duplicate filter, BlueZ's 8 dB rule) keeps
hearing its beacons, only less often; a beacon that walked out of range is heard less often
too, but weaker. So each (sensor, beacon) keeps its count per ``BIN_S`` bin over the run, and
when a finished bin falls under ``DROP_SHARE`` of the run's median bin, the mean RSSI of that
bin against the usual one says which it is. Kept by the collector's writer thread.
"""

from __future__ import annotations

import logging
import statistics
from collections import deque
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

BIN_S = 10.0
DROP_SHARE = 0.3  # a bin under this share of the median bin is a drop
RECOVER_SHARE = 0.6  # back above this share: the drop is over (one warning per drop)
MIN_BIN_READINGS = 5  # the median bin needs this many (0.5/s) before drops are looked for
MIN_HISTORY_BINS = 6  # and this many finished bins (a minute)
MAX_BINS = 360  # an hour of history per beacon
RANGE_DB = 10.0  # weaker than usual by this much: out of range, not throttled
RATE_WINDOW_S = 5.0
MAX_BEACONS = 64  # per sensor; further beacons are not tracked (a flood of random addresses)


@dataclass(frozen=True, slots=True)
class Drop:
    """A finished bin in which a beacon was heard far less often than usual."""

    rate_hz: float
    usual_hz: float
    rssi: float | None  # mean RSSI in that bin (None: not heard at all)
    usual_rssi: float | None

    @property
    def throttled(self) -> bool:
        """Heard as strongly as usual, only less often: the receiver, not the beacon."""
        return (
            self.rssi is not None
            and self.usual_rssi is not None
            and self.rssi > self.usual_rssi - RANGE_DB
        )

    def describe(self, agent: str, sensor: str, beacon: str) -> str:
        head = (
            f"sensor {sensor} of {agent} hears beacon {beacon} at {self.rate_hz:.2f}/s, under "
            f"{DROP_SHARE:.0%} of its usual {self.usual_hz:.2f}/s this run"
        )
        if self.throttled:
            return (
                f"{head}, at its usual RSSI ({self.rssi:.0f} against {self.usual_rssi:.0f} dBm): "
                "the receiver may have started throttling (`sensor-agent doctor` on that host)"
            )
        if self.rssi is None:
            return f"{head}: not heard at all (the beacon stopped, or left its range)"
        return (
            f"{head}, and weaker ({self.rssi:.0f} against {self.usual_rssi:.0f} dBm): the "
            "beacon moved out of its range"
        )


@dataclass(slots=True)
class BeaconTrend:
    bin_start: float
    count: int = 0
    rssi_sum: int = 0
    bins: deque[int] = field(default_factory=lambda: deque(maxlen=MAX_BINS))
    rssi_means: deque[float] = field(default_factory=lambda: deque(maxlen=MAX_BINS))
    window: deque[tuple[float, int]] = field(default_factory=deque)
    dropped: bool = False
    last_rssi: float = 0.0  # mean RSSI of its readings in the last batch, and when
    last_at: float = float("-inf")

    def add(self, now: float, n: int, rssi_sum: int) -> Drop | None:
        drop = self.roll(now)
        self.count += n
        self.rssi_sum += rssi_sum
        self.window.append((now, n))
        self.last_rssi, self.last_at = rssi_sum / n, now
        return drop

    def rate(self, now: float) -> float:
        while self.window and now - self.window[0][0] > RATE_WINDOW_S:
            self.window.popleft()
        return sum(n for _, n in self.window) / RATE_WINDOW_S

    def roll(self, now: float) -> Drop | None:
        """Close every bin that has ended by ``now``; the first Drop among them, if any."""
        drop = None
        while now - self.bin_start >= BIN_S:
            drop = self._close() or drop
            self.bin_start += BIN_S
            if now - self.bin_start >= BIN_S * MAX_BINS:  # silent for over an hour: jump ahead
                self.bin_start = now - (now - self.bin_start) % BIN_S
        return drop

    def _close(self) -> Drop | None:
        n, mean = self.count, (self.rssi_sum / self.count if self.count else None)
        history = list(self.bins)
        self.bins.append(n)
        if mean is not None:
            self.rssi_means.append(mean)
        self.count = self.rssi_sum = 0
        if len(history) < MIN_HISTORY_BINS:
            return None
        usual = statistics.median(history)
        if usual < MIN_BIN_READINGS:
            return None
        if n >= RECOVER_SHARE * usual:
            self.dropped = False
            return None
        if self.dropped or n >= DROP_SHARE * usual:
            return None
        self.dropped = True
        means = list(self.rssi_means)[:-1] if mean is not None else list(self.rssi_means)
        return Drop(
            n / BIN_S,
            usual / BIN_S,
            mean,
            statistics.median(means) if means else None,
        )


def report_drop(agent: str, sensor: str, mac: bytes, drop: Drop) -> None:
    """Log a drop: WARNING when the RSSI says the receiver throttles, INFO when the beacon
    simply moved away or stopped."""
    log.log(
        logging.WARNING if drop.throttled else logging.INFO,
        "%s",
        drop.describe(agent, sensor, mac.hex()),
    )
