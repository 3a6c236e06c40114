"""What `collector status` and `live` show for one sensor: readings, last RSSI, the rate over
the last seconds and a short RSSI history. Kept by the writer thread."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from bgt_core.control_messages import SensorRate
from collector.beacon_rates import MAX_BEACONS, BeaconTrend, Drop
from collector.readings import Rows

RATE_WINDOW_S = 5.0
RSSI_HISTORY = 40  # readings kept per sensor for the live sparkline


@dataclass(slots=True)
class SensorLive:
    """What status/live show for one sensor (since the collector started)."""

    agent_id: str
    readings: int = 0
    last_rssi: int | None = None
    last_seen: float = 0.0  # monotonic seconds
    # (monotonic s, readings) over RATE_WINDOW_S
    window: deque[tuple[float, int]] = field(default_factory=deque)
    rssi: deque[int] = field(default_factory=lambda: deque(maxlen=RSSI_HISTORY))
    beacons: dict[bytes, BeaconTrend] = field(default_factory=dict)  # per-beacon rates and trend

    def add(
        self,
        now: float,
        rows: Rows,
        counts: dict[bytes, list[int]] | None = None,
    ) -> list[tuple[bytes, Drop]]:
        """Count a batch's rows (``counts``: its per-beacon readings and RSSI sums,
        readings.count_beacons); returns the beacons whose rate just dropped."""
        recent = rows["rssi"][-RSSI_HISTORY:].tolist()
        self.readings += len(rows)
        self.last_rssi = recent[-1]
        self.last_seen = now
        self.window.append((now, len(rows)))
        self.rssi.extend(recent)
        self._prune(now)
        drops = []
        for mac, (n, rssi_sum) in (counts or {}).items():
            trend = self.beacons.get(mac)
            if trend is None:
                if len(self.beacons) >= MAX_BEACONS:
                    continue
                trend = self.beacons[mac] = BeaconTrend(now)
            drop = trend.add(now, n, rssi_sum)
            if drop is not None:
                drops.append((mac, drop))
        return drops

    def check(self, now: float) -> list[tuple[bytes, Drop]]:
        """Close finished bins of beacons not heard lately (a beacon gone silent drops too)."""
        return [(mac, d) for mac, t in self.beacons.items() if (d := t.roll(now)) is not None]

    def beacon_rssi(self, now: float, max_age_s: float = 2.0, top: int = 64) -> dict[str, int]:
        """The last RSSI of each beacon heard in the last ``max_age_s`` (a live localizer's
        input: one reading per sensor and beacon)."""
        fresh = [(mac, t) for mac, t in self.beacons.items() if now - t.last_at <= max_age_s]
        fresh.sort(key=lambda kv: -kv[1].last_at)
        return {mac.hex(): round(t.last_rssi) for mac, t in fresh[:top]}

    def beacon_rates(self, now: float, top: int = 8) -> dict[str, float]:
        """Readings/s of the ``top`` most heard beacons over the last seconds."""
        rates = {mac.hex(): round(t.rate(now), 2) for mac, t in self.beacons.items()}
        return dict(sorted(rates.items(), key=lambda kv: -kv[1])[:top])

    def _prune(self, now: float) -> None:
        while self.window and now - self.window[0][0] > RATE_WINDOW_S:
            self.window.popleft()

    def rate(self, now: float) -> float:
        self._prune(now)
        return sum(n for _, n in self.window) / RATE_WINDOW_S

    def sensor_rate(self, now: float) -> SensorRate:
        """What a status reply lists for this sensor at ``now``."""
        return SensorRate(
            rate_hz=round(self.rate(now), 2),
            last_seen_age_s=round(now - self.last_seen, 3),
            last_rssi=self.last_rssi,
            readings=self.readings,
            recent_rssi=tuple(self.rssi),
            beacons=self.beacon_rates(now),
            beacon_rssi=self.beacon_rssi(now),
        )
