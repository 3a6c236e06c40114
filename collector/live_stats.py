"""What `collector status` and `live` show for one sensor: readings, last RSSI, the rate over
the last seconds and a short RSSI history. Kept by the writer thread."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

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

    def add(self, now: float, rows: list[tuple[int, int, bytes, int]]) -> None:
        self.readings += len(rows)
        self.last_rssi = rows[-1][3]
        self.last_seen = now
        self.window.append((now, len(rows)))
        self.rssi.extend([r[3] for r in rows[-RSSI_HISTORY:]])
        self._prune(now)

    def _prune(self, now: float) -> None:
        while self.window and now - self.window[0][0] > RATE_WINDOW_S:
            self.window.popleft()

    def rate(self, now: float) -> float:
        self._prune(now)
        return sum(n for _, n in self.window) / RATE_WINDOW_S
