"""The receive side of the data path: decode and validate batches cheaply, count and log rejects,
and deduplicate on (agent, boot id, sensor, seq) while tracking gaps and what can be acknowledged."""

from __future__ import annotations

import json
import logging
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bgt_core import wire
from bgt_core.messages import Ack
from collector import readings
from collector.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RawBatch:
    """A validated batch whose readings stay as one record array (``readings.READING``).

    Building a Reading object per row would cost more than everything else on the ingest path;
    iBeacon/Eddystone extras are not written to .mbd files, so they are not kept here.
    """

    agent_id: str
    boot_id: str
    sensor: str
    seq: int
    rows: readings.Rows
    floor: int = -1  # the agent never (re)sends seqs below this; -1 = not said (older agent)
    skipped: int = 0  # implausible readings left out (RSSI, timestamp, monotonic time)
    skip_reason: str = ""  # why the first of them was left out

    @property
    def stream(self) -> tuple[str, str, str]:
        return (self.agent_id, self.boot_id, self.sensor)


def decode(payload: bytes) -> RawBatch:
    """Validate like ``wire.from_wire`` (same rules, same typed errors) without per-row objects.

    The fast path checks the common case; anything it does not accept outright is decoded again by
    ``wire.from_wire`` so that the error raised (type and message) is always the canonical one.
    """
    try:
        fast = _decode_fast(payload)
    except Exception:  # noqa: BLE001 - any surprise is settled by the canonical decoder below
        fast = None
    if fast is not None:
        return fast
    skipped: list[tuple[int, str]] = []
    b = wire.from_wire(payload, skipped=skipped)
    return RawBatch(
        b.agent_id,
        b.boot_id,
        b.sensor,
        b.seq,
        readings.from_tuples(
            (r.t_ns, r.mono_ns, bytes.fromhex(r.beacon), r.rssi) for r in b.readings
        ),
        getattr(b, "floor", -1),
        len(skipped),
        f"reading {skipped[0][0]}: {skipped[0][1]}" if skipped else "",
    )


def _decode_fast(data: bytes) -> RawBatch | None:
    if len(data) > wire.MAX_PAYLOAD_BYTES or len(data) < wire.BATCH_HEAD.size:
        return None
    magic, version, meta_len, n = wire.BATCH_HEAD.unpack_from(data, 0)
    if (
        magic != wire.MAGIC
        or version != wire.SCHEMA_VERSION
        or meta_len > wire.MAX_META_BYTES
        or n > wire.MAX_READINGS
    ):
        return None
    start = wire.BATCH_HEAD.size + meta_len
    end = start + n * wire.BATCH_READING.size
    if len(data) != end:  # trailing extras (or a bad length): let the full decoder judge
        return None
    meta = json.loads(data[wire.BATCH_HEAD.size : start].decode("utf-8"))
    if not isinstance(meta, dict):
        return None
    agent = wire.check_id(meta.get("agent"), "agent id")
    boot = wire.check_id(meta.get("boot"), "boot id")
    sensor = meta.get("sensor")
    if not isinstance(sensor, str) or len(sensor) != 12 or sensor != wire.normalize_mac(sensor):
        return None
    seq = meta.get("seq")
    if type(seq) is not int or not 0 <= seq < 2**63:
        return None
    sent = meta.get("sent_ns", 0)
    if type(sent) is not int or sent < 0:
        return None
    floor = meta.get("floor", -1)
    if type(floor) is not int or not -1 <= floor < 2**63:
        return None
    rows = readings.from_payload(data, start, n)
    if not readings.plausible(rows):
        return None  # the canonical decoder skips the implausible readings one by one
    return RawBatch(agent, boot, sensor, seq, rows, floor)


# ---------------------------------------------------------------------------------------------
# Rejects


class RejectCounter:
    """Counts malformed payloads per reason and logs at most one line per reason per interval."""

    def __init__(self, monotonic: Callable[[], float], interval_s: float = 10.0) -> None:
        self._mono = monotonic
        self._interval = interval_s
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._last_log: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def reject(self, reason: str, key: str, message: str, count: int = 1) -> None:
        now = self._mono()
        with self._lock:
            self.counts[reason] += count
            last = self._last_log.get(reason)
            if last is not None and now - last < self._interval:
                self._suppressed[reason] += 1
                return
            self._last_log[reason] = now
            skipped, self._suppressed[reason] = self._suppressed[reason], 0
        log.warning(
            "rejected payload on %s (%s): %s%s",
            key,
            reason,
            message,
            f" [{skipped} more like it not logged]" if skipped else "",
        )

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)


def reject_reason(err: Exception) -> str:
    """A short stable name for a decode error, used as the counter key."""
    names = {
        wire.BadMagic: "bad_magic",
        wire.UnsupportedVersion: "bad_version",
        wire.Oversized: "oversized",
        wire.Truncated: "truncated",
        wire.InvalidField: "invalid_field",
    }
    for cls, name in names.items():
        if isinstance(err, cls):
            return name
    return "malformed"


# ---------------------------------------------------------------------------------------------
# Deduplication, gaps and acknowledgement watermarks


@dataclass(slots=True)
class StreamState:
    """One (agent, boot, sensor) stream, as seen by the single writer thread."""

    done_upto: int  # every seq <= this has been handled (written to a file buffer or discarded)
    acked_upto: int  # every seq <= this is durable; what the ack message carries
    ahead: set[int] = field(default_factory=set)  # handled seqs above done_upto (after a gap)
    max_seq: int = -1
    gaps: int = 0  # times a seq jumped forward
    first_seq: int = 0  # where this collector joined the stream
    before_first: set[int] = field(default_factory=set)  # seqs < first_seq that arrived later
    floor: int = -1  # highest floor the agent announced (contract 1)
    lost: int = 0  # seqs skipped over because the agent's floor passed them unseen
    implicit_floor: int = 0  # first seq of a stream first seen without a floor (older agent)

    def lost_total(self) -> int:
        # An older agent's stream first seen at k counts seqs < k as lost, unless they came later.
        return self.lost + max(0, self.implicit_floor - len(self.before_first))

    def to_dict(self) -> dict[str, Any]:
        return {
            "done_upto": self.done_upto,
            "ahead": sorted(self.ahead),
            "max_seq": self.max_seq,
            "gaps": self.gaps,
            "first_seq": self.first_seq,
            "before_first": sorted(self.before_first),
            "floor": self.floor,
            "lost": self.lost,
            "implicit_floor": self.implicit_floor,
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> StreamState:
        done = int(d["done_upto"])
        # What was persisted is durable by construction: the state is written after the fsync.
        return StreamState(
            done_upto=done,
            acked_upto=done,
            ahead={int(x) for x in d["ahead"]},
            max_seq=int(d["max_seq"]),
            gaps=int(d["gaps"]),
            first_seq=int(d["first_seq"]),
            before_first={int(x) for x in d["before_first"]},
            floor=int(d["floor"]),
            lost=int(d["lost"]),
            implicit_floor=int(d["implicit_floor"]),
        )


SEQ_LIMIT = 2**40  # seqs at or above are refused: 348 years of 100 batches/s
MAX_AHEAD = 4096  # seqs held above a stream's gap; beyond it the oldest gap is given up (lost)
MAX_BOOTS = 16  # boots kept per (agent, sensor); older settled ones are retired into totals


@dataclass(slots=True)
class StreamTotals:
    """One (agent, sensor) stream over all its boots, for run.yaml."""

    gaps: int = 0
    missing: int = 0
    lost: int = 0
    boots: list[str] = field(default_factory=list)


class StreamTracker:
    """Decides whether a batch is new, and keeps the contiguous watermark the acks carry.

    Floors (contract 1): seqs below a stream's announced floor will never come again, so the
    watermark moves over the missing ones and counts them as lost; it never moves past a missing
    seq at or above the floor, so nothing the agent may still re-send is acknowledged unseen.

    Memory is bounded: at most ``max_boots`` boots per (agent, sensor) are tracked (the oldest
    settled one is retired into per-stream totals), and at most ``max_ahead`` seqs wait above a
    gap (past that the gap is given up and counted lost).
    """

    MAX_ACK_BOOTS = 16  # boots per agent that keep getting (re)acked; older ones were long settled

    def __init__(self, max_boots: int = MAX_BOOTS, max_ahead: int = MAX_AHEAD) -> None:
        self.streams: dict[tuple[str, str, str], StreamState] = {}
        self.duplicates = 0
        self.max_boots = max(1, max_boots)
        self.max_ahead = max(1, max_ahead)
        self.given_up = 0  # seqs counted lost because too many seqs waited above a gap
        self.lost_base: dict[str, int] = {}  # 'agent/boot/sensor' -> lost before the run started
        # (agent, sensor) -> [gaps, lost] of retired boots, counted since the run started
        self.retired: dict[tuple[str, str], list[int]] = {}
        self._boots: dict[tuple[str, str], list[str]] = {}
        self.warnings = RateLimitedLog(log)

    def _new_stream(self, stream: tuple[str, str, str]) -> None:
        agent, boot, sensor = stream
        boots = self._boots.setdefault((agent, sensor), [])
        while len(boots) >= self.max_boots:
            settled = [b for b in boots if self._settled((agent, b, sensor))]
            self._retire((agent, settled[0] if settled else boots[0], sensor))
        boots.append(boot)

    def _settled(self, stream: tuple[str, str, str]) -> bool:
        st = self.streams[stream]
        return not st.ahead and st.max_seq <= st.done_upto == st.acked_upto

    def _retire(self, stream: tuple[str, str, str]) -> None:
        agent, boot, sensor = stream
        st = self.streams.pop(stream)
        self._boots[(agent, sensor)].remove(boot)
        r = self.retired.setdefault((agent, sensor), [0, 0])
        r[0] += st.gaps
        r[1] += (
            st.lost_total()
            - self.lost_base.pop("/".join(stream), 0)
            + max(0, st.max_seq - st.done_upto - len(st.ahead))
        )

    def accept(self, stream: tuple[str, str, str], seq: int, floor: int = -1) -> bool:
        """True for a batch not seen before (call once per received batch, then handle it)."""
        floor = min(
            floor, seq
        )  # a floor above its own batch would be a broken agent; never skip it
        st = self.streams.get(stream)
        if st is None:
            self._new_stream(stream)
            if floor >= 0:
                st = StreamState(done_upto=-1, acked_upto=-1, first_seq=seq)
            else:
                # An older agent (no floor) first seen at seq k: treated as floor = k. Earlier seqs
                # that still turn up (e.g. from the publisher's history) are written once.
                st = StreamState(
                    done_upto=seq - 1, acked_upto=seq - 1, first_seq=seq, implicit_floor=seq
                )
                if seq > 0:
                    log.warning(
                        "stream %s/%s/%s first seen at seq %d without a floor; "
                        "treating seqs below it as lost",
                        *stream,
                        seq,
                    )
            self.streams[stream] = st
        if floor > st.floor:
            st.floor = floor
            self._apply_floor(st, floor)
        if seq < st.implicit_floor:
            if seq in st.before_first or len(st.before_first) >= self.max_ahead:
                self.duplicates += 1
                return False
            st.before_first.add(seq)
            return True
        if seq <= st.done_upto or seq in st.ahead:
            self.duplicates += 1
            return False
        if seq > max(st.max_seq, st.done_upto) + 1:
            st.gaps += 1
        st.max_seq = max(st.max_seq, seq)
        if seq == st.done_upto + 1:
            st.done_upto = seq
            self._advance(st)
        else:
            st.ahead.add(seq)
            if len(st.ahead) > self.max_ahead:
                self._give_up_gap(stream, st)
        return True

    def _give_up_gap(self, stream: tuple[str, str, str], st: StreamState) -> None:
        """Too many seqs wait above gaps: the gaps below the lower half of the waiting seqs are
        counted lost and the stream moves on. Halving the window (one sort per max_ahead / 2
        batches) keeps the cost per batch bounded, whatever seqs an agent sends; a gap that old
        had max_ahead / 2 newer batches arrive after it. The warning is rate-limited per agent."""
        waiting = sorted(st.ahead)
        cut = waiting[len(waiting) // 2]
        below = waiting[: len(waiting) // 2]
        skipped = (cut - 1 - st.done_upto) - len(below)
        st.lost += skipped
        self.given_up += skipped
        st.ahead.difference_update(below)
        st.done_upto = cut - 1
        self._advance(st)
        agent, _boot, sensor = stream
        self.warnings.warn(
            f"{agent}/gap",
            skipped,
            f"stream {'/'.join(stream)}: more than {self.max_ahead} batches waited above gaps; "
            f"gave up on {skipped} missing batch(es) below seq {cut} (counted lost)",
            f"agent {agent}: gave up on %d more gap window(s), %d missing batch(es) in the last "
            "%.0f s (counted lost)",
        )

    @staticmethod
    def _apply_floor(st: StreamState, floor: int) -> None:
        if floor - 1 <= st.done_upto:
            return
        below = {s for s in st.ahead if s < floor}
        st.lost += (floor - 1 - st.done_upto) - len(below)
        st.ahead -= below
        st.done_upto = floor - 1
        StreamTracker._advance(st)

    @staticmethod
    def _advance(st: StreamState) -> None:
        while st.done_upto + 1 in st.ahead:
            st.done_upto += 1
            st.ahead.discard(st.done_upto)

    def missing(self, stream: tuple[str, str, str]) -> int:
        """Batches below the highest seq seen that have not arrived (yet) and may still come."""
        st = self.streams[stream]
        return max(0, st.max_seq - st.done_upto - len(st.ahead))

    def open_gaps(self) -> int:
        return sum(self.missing(s) for s in self.streams)

    def stream_totals(
        self, lost_base: dict[str, int] | None = None
    ) -> dict[tuple[str, str], StreamTotals]:
        """Per (agent, sensor): gaps, missing and lost batches since the run started, and boots."""
        base = self.lost_base if lost_base is None else lost_base
        out: dict[tuple[str, str], StreamTotals] = {}
        for (a, s), (gaps, lost) in self.retired.items():
            out[(a, s)] = StreamTotals(gaps, 0, lost)
        for (a, b, s), st in self.streams.items():
            t = out.setdefault((a, s), StreamTotals())
            t.gaps += st.gaps
            t.missing += self.missing((a, b, s))
            t.lost += st.lost_total() - base.get(f"{a}/{b}/{s}", 0)
            t.boots.append(b)
        return out

    def reset_run_totals(self) -> dict[str, int]:
        """At the start of a run: what was lost so far becomes the base, retired totals restart."""
        self.lost_base = {"/".join(k): st.lost_total() for k, st in self.streams.items()}
        self.retired = {}
        return self.lost_base

    def mark_durable(self) -> set[str]:
        """Everything handled so far is now durable; returns the agents whose watermark moved."""
        moved = set()
        for (agent, _boot, _sensor), st in self.streams.items():
            if st.acked_upto != st.done_upto:
                st.acked_upto = st.done_upto
                moved.add(agent)
        return moved

    def ack_messages(self, agent_id: str) -> list[Ack]:
        """One ack JSON per boot of this agent (contract 2), most recent boots only, oldest first."""
        per_boot: dict[str, dict[str, int]] = {}
        for (a, b, s), st in self.streams.items():
            if a == agent_id:
                streams = per_boot.setdefault(b, {})
                if st.acked_upto >= 0:
                    streams[s] = st.acked_upto
        boots = list(per_boot.items())[-self.MAX_ACK_BOOTS :]
        return [Ack(b, s) for b, s in boots]

    def ack_message(self, agent_id: str) -> Ack | None:
        """The ack JSON for an agent's most recent boot (dicts keep insertion order)."""
        msgs = self.ack_messages(agent_id)
        return msgs[-1] if msgs else None

    def to_state(self) -> dict[str, Any]:
        """Only what is durable: acked_upto is what the persisted files cover."""
        return {
            "duplicates": self.duplicates,
            "given_up": self.given_up,
            "retired": [[a, s, g, lo] for (a, s), (g, lo) in self.retired.items()],
            "streams": [
                {"agent": a, "boot": b, "sensor": s, **st.to_dict()}
                for (a, b, s), st in self.streams.items()
            ],
        }

    @staticmethod
    def from_state(d: dict[str, Any], lost_base: dict[str, int] | None = None) -> StreamTracker:
        t = StreamTracker()
        t.duplicates = int(d.get("duplicates", 0))
        t.given_up = int(d.get("given_up", 0))
        t.lost_base = dict(lost_base or {})
        for a, s, g, lo in d.get("retired", []):
            t.retired[(str(a), str(s))] = [int(g), int(lo)]
        for e in d.get("streams", []):
            key = (e["agent"], e["boot"], e["sensor"])
            t.streams[key] = StreamState.from_dict(e)
            t._boots.setdefault((key[0], key[2]), []).append(key[1])
        return t
