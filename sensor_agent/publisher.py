"""Everything the agent says on Zenoh: batched readings (one AdvancedPublisher per sensor key),
the spool they go through, re-sending what the collector has not acknowledged, the liveliness
token, the status and clock queryables, and the collector's acknowledgements.

Batches are built whether or not a Zenoh session is attached yet (the router may be unreachable
at start): each is appended to the spool (or, without one, to a bounded in-memory ring) before
it is put. Zenoh calls the ack and query callbacks on its own threads and re-sending runs in a
worker thread; the small shared state they touch is guarded by one lock.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bgt_core import wire
from bgt_core.messages import Ack, ClockReply, ClockRequest, Refusal
from bgt_core.wire import Batch, Reading
from sensor_agent.spool import SpoolError

log = logging.getLogger(__name__)

# History kept per stream for AdvancedSubscribers that detect a gap (about a minute at 10 Hz);
# also the size of the in-memory re-send ring per stream when a batch is not in the spool.
CACHE_SAMPLES = 600
# How often the publisher re-announces its last sequence number so a lost last sample is noticed.
HEARTBEAT_S = 1.0
# A stream's buffer is sent early when it reaches this many readings (fast replays).
MAX_BATCH_READINGS = 5000
# A stream whose acknowledgement has not moved for this long (while connected) is re-sent.
RESEND_S = 5.0
# Passes that bring no acknowledgement (collector rejecting us, ACL) back off up to this.
RESEND_MAX_S = 60.0


def stream_id(boot_id: str, sensor: str) -> str:
    """The spool's name for one (boot, sensor) stream of this agent."""
    return f"{boot_id}/{sensor}"


@dataclass(slots=True)
class _Stream:
    """One sensor of this boot: sequence numbers from 0, buffered readings, the re-send ring."""

    sensor: str
    next_seq: int = 0
    pending: list[Reading] = field(default_factory=list)
    readings_sent: int = 0
    # Batches not in the spool (no spool, disk full): (seq, payload), oldest first, bounded.
    ring: deque[tuple[int, bytes]] = field(default_factory=lambda: deque(maxlen=CACHE_SAMPLES))


class Publisher:
    """Batches readings per sensor, spools and publishes them, re-sends what is unacknowledged."""

    def __init__(
        self,
        session: Any = None,
        *,
        site: str,
        agent_id: str,
        boot_id: str,
        wall_ns: Callable[[], int],
        mono_ns: Callable[[], int] | None = None,
        spool: Any = None,
        status: Callable[[], dict[str, Any]] | None = None,
        chrony: Callable[[], dict[str, Any] | None] | None = None,
        max_batch: int = MAX_BATCH_READINGS,
        resend_s: float = RESEND_S,
        on_refused: str = "drop",
    ) -> None:
        import time

        self.site = site
        self.agent_id = agent_id
        self.boot_id = boot_id
        self.wall_ns = wall_ns
        self.mono_ns = mono_ns or time.monotonic_ns
        self.spool = spool
        self.max_batch = max_batch
        self.resend_ns = int(resend_s * 1e9)
        self._status = status
        self._chrony = chrony
        self._streams: dict[str, _Stream] = {}
        self._lock = threading.RLock()
        self._acked: dict[
            str, int
        ] = {}  # sensor -> highest seq with all earlier ones handled (this boot)
        self._published: dict[str, int] = {}  # sensor -> last seq built (this boot)
        self._sid_acked: dict[str, int] = {}  # stream id (any boot) -> acked seq
        self._progress: dict[
            str, int
        ] = {}  # stream id -> mono ns of the last ack advance / re-send
        self._interval: dict[
            str, int
        ] = {}  # stream id -> current re-send interval (ns), backed off
        self._old_boots: set[str] = set()
        self.resent = 0
        # Batches the collector refused (negative acknowledgements): drop them, or keep
        # re-sending in case the collector's limits are raised (spool.on_refused).
        self.on_refused = on_refused
        self.refused: dict[str, int] = {}  # sensor -> highest refused seq (this boot)
        self._refusals_logged: set[tuple[str, str]] = set()
        self.last_ack_ns: int | None = None  # monotonic time of the last ack for this agent
        # Held for a whole re-send pass; close() takes it so no pass outlives the publishers.
        self._resend_lock = threading.Lock()
        self._closing = False
        if spool is not None:
            for sid in spool.pending_streams():
                boot = sid.split("/", 1)[0]
                if boot != boot_id:
                    self._old_boots.add(boot)
                self._progress[sid] = 0  # re-send at once when connected
            if self._old_boots:
                log.info(
                    "spool holds unacknowledged batches of %d earlier boot(s); they are "
                    "re-sent once the collector is reachable",
                    len(self._old_boots),
                )
        self.session: Any = None
        self._zpubs: dict[str, Any] = {}  # sensor -> AdvancedPublisher
        self._decls: list[Any] = []
        if session is not None:
            self.attach(session)

    # -- the Zenoh session ------------------------------------------------------------------

    def attach(self, session: Any) -> None:
        """Start talking on ``session``: token, ack subscriber, queryables, publishers."""
        import zenoh

        site, agent = self.site, self.agent_id
        self._decls.append(session.liveliness().declare_token(wire.agent_token_key(site, agent)))
        self._decls.append(session.declare_subscriber(wire.ack_key(site, agent), self._on_ack))
        if self._status is not None:
            self._decls.append(
                session.declare_queryable(wire.agent_status_key(site, agent), self._on_status_query)
            )
        self._decls.append(
            session.declare_queryable(wire.agent_clock_key(site, agent), self._on_clock_query)
        )
        with self._lock:
            self.session = session
            self._zenoh = zenoh
            for sensor in list(self._streams):
                self._zpub(sensor)

    @property
    def attached(self) -> bool:
        return self.session is not None

    def connected(self) -> bool:
        """True while the client session has a router (the collector) to talk to."""
        s = self.session
        if s is None:
            return False
        try:
            return bool(s.info.routers_zid())
        except self._zenoh.ZError:  # a closing session; treat as not connected
            return False

    def _zpub(self, sensor: str) -> Any:
        """The AdvancedPublisher for this sensor's key (same key for every boot); lock held."""
        p = self._zpubs.get(sensor)
        if p is None and self.session is not None:
            import zenoh.ext

            z = self._zenoh
            p = zenoh.ext.declare_advanced_publisher(
                self.session,
                wire.data_key(self.site, self.agent_id, sensor),
                encoding=z.Encoding.APPLICATION_OCTET_STREAM,
                congestion_control=z.CongestionControl.BLOCK,
                reliability=z.Reliability.RELIABLE,
                cache=zenoh.ext.CacheConfig(CACHE_SAMPLES),
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=HEARTBEAT_S, sporadic_heartbeat=None
                ),
                publisher_detection=True,
            )
            self._zpubs[sensor] = p
        return p

    def _put(self, sensor: str, payload: bytes) -> bool:
        with self._lock:
            p = self._zpub(sensor)
        if p is None:
            return False
        p.put(payload)
        return True

    # -- readings ---------------------------------------------------------------------------

    def add(self, sensor: str, reading: Reading) -> None:
        """Queue one reading of ``sensor`` (12 hex digits); sent at the next flush."""
        s = self._streams.get(sensor)
        if s is None:
            with self._lock:
                s = self._streams[sensor] = _Stream(sensor)
        s.pending.append(reading)
        if len(s.pending) >= self.max_batch:
            self._flush_stream(s)

    def flush(self) -> int:
        """Build every non-empty buffer into one batch, spool it and publish it; returns the count."""
        n = 0
        for s in list(self._streams.values()):
            if s.pending:
                self._flush_stream(s)
                n += 1
        return n

    def _floor(self, s: _Stream, sid: str) -> int:
        """The lowest seq of this stream the agent could still (re)send: in the spool or the ring
        and not acknowledged; the batch being built when there is none."""
        low = s.next_seq
        if self.spool is not None:
            lp = self.spool.lowest_pending(sid)
            if lp is not None:
                low = min(low, lp)
        with self._lock:
            a = self._acked.get(s.sensor, -1)
            while s.ring and s.ring[0][0] <= a:
                s.ring.popleft()
            if s.ring:
                low = min(low, s.ring[0][0])
        return low

    def _flush_stream(self, s: _Stream) -> None:
        sid = stream_id(self.boot_id, s.sensor)
        seq = s.next_seq
        batch = Batch(
            self.agent_id,
            self.boot_id,
            s.sensor,
            seq,
            tuple(s.pending),
            sent_ns=self.wall_ns(),
            floor=self._floor(s, sid),
        )
        payload = wire.to_wire(batch)
        spooled = self.spool is not None and self.spool.append(sid, seq, payload)
        with self._lock:
            if not spooled:
                s.ring.append((seq, payload))
            self._published[s.sensor] = seq
            self._progress.setdefault(sid, self.mono_ns())
        s.readings_sent += len(s.pending)
        s.pending = []
        s.next_seq += 1
        self._put(s.sensor, payload)

    def readings_sent(self, sensor: str) -> int:
        s = self._streams.get(sensor)
        return 0 if s is None else s.readings_sent

    # -- re-sending -------------------------------------------------------------------------

    def resend_due(self) -> int:
        """Re-publish every unacknowledged batch of each stream whose acknowledgement has not
        moved for ``resend_s`` (all of them right after start); returns how many were sent.

        Blocking (reads the spool, puts with congestion control BLOCK): run it in a worker
        thread. Does nothing while no router is connected."""
        with self._resend_lock:
            if self._closing or not self.connected():
                return 0
            return self._resend_pass()

    def _resend_pass(self) -> int:
        now = self.mono_ns()
        with self._lock:
            due = {
                sid
                for sid, t in self._progress.items()
                if now - t >= self._interval.get(sid, self.resend_ns)
            }
        if not due:
            return 0
        sent = 0
        if self.spool is not None:
            spooled = self.spool.pending_streams()
            due_spool = due & spooled.keys()
            if due_spool:
                for sid, _seq, payload in self.spool.pending():
                    if self._closing:
                        return sent
                    if sid in due_spool and self._put(sid.split("/", 1)[1], payload):
                        sent += 1
        for s in list(self._streams.values()):
            sid = stream_id(self.boot_id, s.sensor)
            if sid not in due:
                continue
            with self._lock:
                a = self._acked.get(s.sensor, -1)
                ring = [(q, p) for q, p in s.ring if q > a]
            for _q, p in ring:
                if self._closing:  # close() waits for this pass: end it, as the spool loop does
                    return sent
                if self._put(s.sensor, p):
                    sent += 1
        done = self.mono_ns()
        with self._lock:
            for sid in due:
                if self._still_pending(sid):
                    self._progress[sid] = done
                    # reset by the next ack that moves; doubled while passes bring nothing
                    self._interval[sid] = min(
                        int(RESEND_MAX_S * 1e9), 2 * self._interval.get(sid, self.resend_ns)
                    )
                else:
                    self._progress.pop(sid, None)
                    self._interval.pop(sid, None)
            self.resent += sent
        if sent:
            log.info("re-sent %d unacknowledged batch(es) of %d stream(s)", sent, len(due))
        return sent

    def _still_pending(self, sid: str) -> bool:
        boot, _, sensor = sid.partition("/")
        if boot == self.boot_id and self._acked.get(sensor, -1) < self._published.get(sensor, -1):
            return True
        return self.spool is not None and self.spool.lowest_pending(sid) is not None

    # -- acknowledgements -------------------------------------------------------------------

    def _on_ack(self, sample: Any) -> None:
        try:
            msg = Ack.from_dict(wire.from_json(sample.payload.to_bytes(), "ack"))
        except wire.WireError as e:
            log.warning("ignoring a malformed ack: %s", e)
            return
        boot = msg.boot
        if boot != self.boot_id and boot not in self._old_boots:
            return  # another agent's boot, or one this spool no longer holds anything of
        now = self.mono_ns()
        self.last_ack_ns = now
        advanced: list[tuple[str, int]] = []
        with self._lock:
            for mac, seq in msg.streams.items():
                sid = stream_id(boot, mac)
                if seq > self._sid_acked.get(sid, -1):
                    self._sid_acked[sid] = seq
                    advanced.append((sid, seq))
                    if sid in self._progress:
                        self._progress[sid] = now
                    self._interval.pop(sid, None)
                    if boot == self.boot_id:
                        self._acked[mac] = seq
            for mac, r in msg.refused.items():
                self._on_refusal(boot, mac, r, now, advanced)
        if self.spool is not None:
            for sid, seq in advanced:
                try:
                    self.spool.ack(sid, seq)
                except (SpoolError, OSError) as e:  # closing: a late ack costs a re-send next start
                    log.debug("spool ack of %s failed: %s", sid, e)
                    return

    def _on_refusal(
        self, boot: str, mac: str, r: Refusal, now: int, advanced: list[tuple[str, int]]
    ) -> None:
        """A negative acknowledgement: log it once per sensor and reason; with on_refused drop,
        everything of that stream up to ``r.upto`` counts as handled (written or refused)."""
        if boot == self.boot_id:
            self.refused[mac] = max(r.upto, self.refused.get(mac, -1))
        if (mac, r.reason) not in self._refusals_logged and len(self._refusals_logged) < 1024:
            self._refusals_logged.add((mac, r.reason))
            log.warning(
                "the collector refused sensor %s's batches (up to seq %d): %s; %s",
                mac,
                r.upto,
                r.reason,
                "dropped from the spool (spool.on_refused: drop)"
                if self.on_refused == "drop"
                else "kept and re-sent (spool.on_refused: keep)",
            )
        if self.on_refused != "drop":
            return
        sid = stream_id(boot, mac)
        if r.upto > self._sid_acked.get(sid, -1):
            self._sid_acked[sid] = r.upto
            advanced.append((sid, r.upto))
            self._interval.pop(sid, None)
            if sid in self._progress:
                self._progress[sid] = now
            if boot == self.boot_id:
                self._acked[mac] = max(self._acked.get(mac, -1), r.upto)

    def unacked(self) -> dict[str, tuple[int, int]]:
        """This boot's streams with batches not yet acknowledged: sensor -> (last built, last acked)."""
        with self._lock:
            return {
                m: (p, self._acked.get(m, -1))
                for m, p in self._published.items()
                if self._acked.get(m, -1) < p
            }

    def outstanding(self) -> dict[str, int]:
        """Every stream (any boot) with something unacknowledged: stream id -> how many batches."""
        out = {stream_id(self.boot_id, m): p - a for m, (p, a) in self.unacked().items()}
        if self.spool is not None:
            for sid, (lo, hi) in self.spool.pending_streams().items():
                out.setdefault(sid, hi - lo + 1)
        return out

    def acked(self) -> dict[str, int]:
        with self._lock:
            return dict(self._acked)

    def any_ack(self) -> bool:
        with self._lock:
            return bool(self._sid_acked)

    # -- queryables -------------------------------------------------------------------------

    def _on_status_query(self, query: Any) -> None:
        try:
            assert self._status is not None
            query.reply(
                query.key_expr,
                wire.to_json(self._status()),
                encoding=self._zenoh.Encoding.APPLICATION_JSON,
            )
        except Exception:  # a bug here must not kill Zenoh's callback thread silently
            log.exception("status query failed")

    def _on_clock_query(self, query: Any) -> None:
        t2 = self.wall_ns()  # stamp before anything else: the exchange measures this moment
        try:
            payload = query.payload
            raw = payload.to_bytes() if payload is not None else b""
            try:
                req = ClockRequest.from_dict(wire.from_json(raw or b"{}", "clock request"))
            except wire.WireError as e:
                query.reply_err(wire.to_json({"error": str(e)}))
                return
            chrony = self._chrony() if self._chrony is not None else None
            reply = ClockReply(req.t1, t2, self.wall_ns(), chrony)
            query.reply(
                query.key_expr,
                wire.to_json(reply.to_dict()),
                encoding=self._zenoh.Encoding.APPLICATION_JSON,
            )
        except Exception:
            log.exception("clock query failed")

    def close(self) -> None:
        """Undeclare everything (pending readings are NOT flushed: call flush() first)."""
        self._closing = True
        with self._resend_lock, self._lock:
            pubs, self._zpubs = list(self._zpubs.values()), {}
            decls, self._decls = self._decls, []
            self.session = None
        for p in pubs:
            p.undeclare()
        for d in reversed(decls):
            d.undeclare()
