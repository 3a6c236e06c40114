"""The collector's receive side: Zenoh data samples are decoded and checked here (on the receive
thread), bad ones counted and queued for quarantine (<run>/rejected.jsonl), good batches queued
for the writer thread in a queue bounded by memory, whose waiting is the back-pressure on agents.
"""

from __future__ import annotations

import base64
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from bgt_core import wire
from collector.ingest import SEQ_LIMIT, RawBatch, RejectCounter, decode, reject_reason

log = logging.getLogger(__name__)

ROW_COST = 192  # bytes counted per reading in the receive queue (generous: the array views the
# payload, 23 bytes a reading; the bound was set when each reading was a tuple)
BATCH_COST = 512
QUEUE_WAIT_S = 0.5  # a callback waits this long for room (back-pressure) before dropping unacked
FUTURE_LIMIT_NS = 24 * 3600 * 10**9  # readings further ahead than this are absurd
QUARANTINE_PAYLOAD = 4096  # bytes of each rejected payload kept (base64) in rejected.jsonl


class ByteQueue:
    """FIFO bounded by the summed cost (bytes of memory) of its items, not their number. An item
    costlier than the whole bound is still let in when the queue is empty, so none is too big."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._items: deque[tuple[Any, int]] = deque()
        self.bytes = 0
        self._cond = threading.Condition()

    def put(self, item: Any, cost: int, timeout: float) -> bool:
        """Wait up to ``timeout`` for room; False if there was none."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._items and self.bytes + cost > self.max_bytes:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            self._items.append((item, cost))
            self.bytes += cost
            self._cond.notify_all()
            return True

    def get(self, timeout: float) -> Any:
        """The oldest item, waiting up to ``timeout``; None if there is none."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item, cost = self._items.popleft()
            self.bytes -= cost
            self._cond.notify_all()
            return item

    def qsize(self) -> int:
        return len(self._items)

    def empty(self) -> bool:
        return not self._items


def batch_cost(batch: RawBatch) -> int:
    return BATCH_COST + ROW_COST * len(batch.rows)


class Inbox:
    """The receive side: Zenoh samples are decoded and checked here (on Zenoh's or the receive
    thread), bad ones counted and queued for quarantine, good batches queued for the writer with
    back-pressure. Never raises."""

    def __init__(
        self, *, queue_bytes: int, clock: Callable[[], int], monotonic: Callable[[], float]
    ) -> None:
        self._clock = clock
        self._mono = monotonic
        self.data = ByteQueue(queue_bytes)
        self.quarantine: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=1000)
        self.rejects = RejectCounter(monotonic)
        self._lock = threading.Lock()
        self.overflow = 0  # batches dropped (unacknowledged) because the queue stayed full
        self._overflow_log = -1e9
        self._quarantine_dropped = 0
        # Set at shutdown: samples still delivered are dropped unread (unacknowledged, so agents
        # re-send them) instead of waiting for room the stopped writer will never make.
        self.shutting = threading.Event()
        self.dropped_at_shutdown = 0

    @property
    def quarantine_dropped(self) -> int:
        with self._lock:
            return self._quarantine_dropped

    def count_quarantine_dropped(self, n: int) -> None:
        with self._lock:
            self._quarantine_dropped += n

    def reset_quarantine_dropped(self) -> None:
        with self._lock:
            self._quarantine_dropped = 0

    def receive_loop(self, handler: Any) -> None:
        """Take samples from the subscriber's channel until it is undeclared. Once ``shutting``
        is set the channel is still drained, but at once: a Zenoh thread blocked on the full
        channel must finish, since undeclare and session close wait for it."""
        while True:
            try:
                sample = handler.recv()
            except Exception:  # noqa: BLE001 - the channel is closed: the subscriber is gone
                break
            if self.shutting.is_set():
                self.dropped_at_shutdown += 1
                continue
            self.on_sample(sample)
        if self.dropped_at_shutdown:
            log.info(
                "%d batches arriving during shutdown dropped unacknowledged (agents re-send them)",
                self.dropped_at_shutdown,
            )

    def on_sample(self, sample: Any) -> None:
        """Handle one data sample (anything with ``key_expr`` and ``payload.to_bytes()``)."""
        key = str(sample.key_expr)
        payload = b""
        try:
            payload = sample.payload.to_bytes()
            _site, agent, sensor = wire.parse_data_key(key)  # ids never start with a dot
            batch = decode(payload)
            # The key (which the ACL checks) says who sent it; the payload must agree.
            if batch.agent_id != agent or batch.sensor != sensor:
                self.reject(
                    "key_mismatch",
                    key,
                    f"batch of agent {batch.agent_id}, sensor {batch.sensor} on this key",
                    payload,
                )
                return
            if batch.seq >= SEQ_LIMIT or batch.floor >= SEQ_LIMIT:
                self.reject(
                    "seq_out_of_range",
                    key,
                    f"seq {batch.seq} / floor {batch.floor} not below 2^40",
                    payload,
                )
                return
        except wire.WireError as e:
            self.reject(reject_reason(e), key, str(e), payload)
            return
        except Exception as e:  # noqa: BLE001 - a callback must not die on one bad sample
            self.reject("malformed", key, f"{type(e).__name__}: {e}", payload)
            return
        if batch.skipped:
            # The rest of the batch is kept and acknowledged, so one absurd value (a scanner's
            # +42 dBm) neither costs the other readings nor makes the agent re-send forever.
            self.reject(
                "bad_reading",
                key,
                f"{batch.skipped} of {batch.skipped + len(batch.rows)} readings of seq "
                f"{batch.seq} skipped ({batch.skip_reason})",
                payload,
                count=batch.skipped,
            )
        batch = self._drop_future_readings(batch, key, payload)
        # Waiting here is the back-pressure: Zenoh (BLOCK congestion control) slows the senders.
        wait = 0.0 if self.shutting.is_set() else QUEUE_WAIT_S
        if not self.data.put(batch, batch_cost(batch), timeout=wait):
            # Not handled, so never acknowledged: the agent's spool sends it again later.
            now = self._mono()
            with self._lock:
                self.overflow += 1
                if now - self._overflow_log < 10:
                    return
                self._overflow_log = now
                n = self.overflow
            log.warning(
                "receive queue full (%.0f MiB): dropped a batch of %s unacknowledged "
                "(%d so far); the writer cannot keep up",
                self.data.max_bytes / 2**20,
                key,
                n,
            )

    def _drop_future_readings(self, batch: RawBatch, key: str, payload: bytes) -> RawBatch:
        """Readings stamped more than FUTURE_LIMIT_NS ahead of our clock are quarantined, the
        rest of the batch is kept: the batch itself is still handled (and acknowledged), so a
        broken clock on one agent cannot stall its stream. Old timestamps are legitimate
        (``--replay-keep-time`` of a past recording), so only the future counts as absurd."""
        limit = self._clock() + FUTURE_LIMIT_NS
        t = batch.rows["t"]
        if not len(t) or t.max() <= limit:
            return batch
        ahead = t > limit
        good = batch.rows[~ahead]
        bad = int(ahead.sum())
        first = int(t[ahead].min())
        self.reject(
            "future_timestamp",
            key,
            f"{bad} of {len(batch.rows)} readings of seq {batch.seq} stamped "
            f"{wire.format_ts(first)}, more than a day ahead of the collector's clock",
            payload,
            count=bad,
        )
        return replace(batch, rows=good)

    def reject(self, reason: str, key: str, message: str, payload: bytes, count: int = 1) -> None:
        """Count, log (rate-limited) and queue for <run>/rejected.jsonl; never raises."""
        self.rejects.reject(reason, key, message, count)
        rec = {
            "at_ns": self._clock(),
            "key": key,
            "reason": reason,
            "error": message,
            "size": len(payload),
            "payload_b64": base64.b64encode(payload[:QUARANTINE_PAYLOAD]).decode("ascii"),
        }
        try:
            self.quarantine.put_nowait(rec)
        except queue.Full:
            self.count_quarantine_dropped(1)
