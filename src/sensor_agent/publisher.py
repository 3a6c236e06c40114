"""Everything the agent says on Zenoh: batched readings (one AdvancedPublisher per sensor stream),
the liveliness token, the status queryable, and the collector's acknowledgements.

Zenoh calls the ack and status callbacks on its own threads; the small shared state they touch
is guarded by one lock. Batches are only built and sent from the caller's (event loop) thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from ble_groundtruth import wire
from ble_groundtruth.wire import Batch, Reading

log = logging.getLogger(__name__)

# History kept per stream for AdvancedSubscribers that detect a gap (about a minute at 10 Hz).
CACHE_SAMPLES = 600
# How often the publisher re-announces its last sequence number so a lost last sample is noticed.
HEARTBEAT_S = 1.0
# A stream's buffer is sent early when it reaches this many readings (fast replays).
MAX_BATCH_READINGS = 5000


class StreamPublisher:
    """One (agent, boot, sensor) stream: sequence numbers from 0 and its AdvancedPublisher."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.key = key
        self.next_seq = 0
        self.pending: list[Reading] = []
        self.readings_sent = 0
        self._pub = zenoh.ext.declare_advanced_publisher(
            session, key,
            encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            cache=zenoh.ext.CacheConfig(CACHE_SAMPLES),
            sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=HEARTBEAT_S,
                                                                sporadic_heartbeat=None),
            publisher_detection=True,
        )

    def put(self, payload: bytes) -> None:
        self._pub.put(payload)

    def close(self) -> None:
        self._pub.undeclare()


class Publisher:
    """Batches readings per sensor and publishes them; tracks what the collector acknowledged."""

    def __init__(self, session: zenoh.Session, *, site: str, agent_id: str, boot_id: str,
                 wall_ns: Callable[[], int],
                 status: Callable[[], dict[str, Any]] | None = None,
                 max_batch: int = MAX_BATCH_READINGS) -> None:
        self.session = session
        self.site = site
        self.agent_id = agent_id
        self.boot_id = boot_id
        self.wall_ns = wall_ns
        self.max_batch = max_batch
        self._streams: dict[str, StreamPublisher] = {}
        self._lock = threading.Lock()
        self._acked: dict[str, int] = {}  # sensor -> highest seq with all earlier ones handled
        self._published: dict[str, int] = {}  # sensor -> last seq put on the wire
        self._status = status
        self._token = session.liveliness().declare_token(wire.agent_token_key(site, agent_id))
        self._ack_sub = session.declare_subscriber(wire.ack_key(site, agent_id), self._on_ack)
        self._queryable = None
        if status is not None:
            self._queryable = session.declare_queryable(wire.agent_status_key(site, agent_id),
                                                        self._on_status_query)

    # -- readings ---------------------------------------------------------------------------

    def add(self, sensor: str, reading: Reading) -> None:
        """Queue one reading of ``sensor`` (12 hex digits); sent at the next flush."""
        s = self._streams.get(sensor)
        if s is None:
            s = StreamPublisher(self.session, wire.data_key(self.site, self.agent_id, sensor))
            self._streams[sensor] = s
        s.pending.append(reading)
        if len(s.pending) >= self.max_batch:
            self._flush_stream(sensor, s)

    def flush(self) -> int:
        """Send every non-empty buffer as one batch; returns how many batches were sent."""
        n = 0
        for sensor, s in self._streams.items():
            if s.pending:
                self._flush_stream(sensor, s)
                n += 1
        return n

    def _flush_stream(self, sensor: str, s: StreamPublisher) -> None:
        batch = Batch(self.agent_id, self.boot_id, sensor, s.next_seq, tuple(s.pending),
                      sent_ns=self.wall_ns())
        s.put(wire.to_wire(batch))
        s.readings_sent += len(s.pending)
        s.pending = []
        with self._lock:
            self._published[sensor] = s.next_seq
        s.next_seq += 1

    def readings_sent(self, sensor: str) -> int:
        s = self._streams.get(sensor)
        return 0 if s is None else s.readings_sent

    # -- acknowledgements -------------------------------------------------------------------

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            msg = wire.from_json(sample.payload.to_bytes(), "ack")
        except wire.WireError as e:
            log.warning("ignoring a malformed ack: %s", e)
            return
        if msg.get("boot") != self.boot_id:
            return  # meant for an earlier (or later) run of this agent
        streams = msg.get("streams")
        if not isinstance(streams, dict):
            log.warning("ignoring an ack without a 'streams' object")
            return
        with self._lock:
            for mac, seq in streams.items():
                if isinstance(seq, int) and not isinstance(seq, bool) and isinstance(mac, str):
                    if seq > self._acked.get(mac, -1):
                        self._acked[mac] = seq

    def unacked(self) -> dict[str, tuple[int, int]]:
        """Streams with batches not yet acknowledged: sensor -> (last published, last acked)."""
        with self._lock:
            return {m: (p, self._acked.get(m, -1)) for m, p in self._published.items()
                    if self._acked.get(m, -1) < p}

    def acked(self) -> dict[str, int]:
        with self._lock:
            return dict(self._acked)

    # -- status -----------------------------------------------------------------------------

    def _on_status_query(self, query: zenoh.Query) -> None:
        try:
            assert self._status is not None
            query.reply(query.key_expr, wire.to_json(self._status()),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception:  # a bug here must not kill Zenoh's callback thread silently
            log.exception("status query failed")

    def close(self) -> None:
        """Undeclare everything (pending readings are NOT flushed: call flush() first)."""
        for s in self._streams.values():
            s.close()
        if self._queryable is not None:
            self._queryable.undeclare()
        self._ack_sub.undeclare()
        self._token.undeclare()
