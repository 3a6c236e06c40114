"""Warnings that an agent can trigger over and over, logged at a bounded rate.

One misbehaving agent must not flood the collector's log (and, under systemd, make journald drop
everyone else's messages). :class:`RateLimitedLog` logs the first warning of a key (an agent and
a kind of problem) as it is, then at most one line per ``interval_s`` summing up what happened
meanwhile: "agent pi-7: gave up on 12400 gap(s) in the last 10 s". Keys are bounded in number.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

MAX_KEYS = 4096  # past this many keys, new ones share one bucket


@dataclass
class _Bucket:
    last: float
    count: int = 0  # events since the last line
    amount: int = 0  # their summed amount (gaps, rows ...)


class RateLimitedLog:
    """``warn(key, amount, first, summary)``: the first event of ``key`` logs ``first``; later
    ones are counted and, once ``interval_s`` has passed since the last line, one line
    ``summary % (events, amount, seconds)`` is logged."""

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log, self._interval, self._clock = logger, interval_s, clock
        self._buckets: dict[str, _Bucket] = {}
        self.lines = 0  # lines logged (for tests and status)

    def warn(self, key: str, amount: int, first: str, summary: str) -> None:
        now = self._clock()
        if key not in self._buckets and len(self._buckets) >= MAX_KEYS:
            key = "(other keys)"
        b = self._buckets.get(key)
        if b is None:
            self._buckets[key] = _Bucket(now)
            self._log.warning("%s", first)
            self.lines += 1
            return
        b.count += 1
        b.amount += amount
        if now - b.last >= self._interval:
            self._log.warning(summary, b.count, b.amount, now - b.last)
            self.lines += 1
            b.last, b.count, b.amount = now, 0, 0
