"""Which batches the collector accepts: the stream caps and per-agent quotas of ``limits:``, the
counts of what they refused, the refusals owed to agents as negative acknowledgements, and
sensors published by more than one agent. The writer makes a new gate at every start and stop of
a run, so no cap or quota outlives its run."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

from bgt_core.messages import MAX_REASON, Refusal
from collector.config import Limits

log = logging.getLogger(__name__)

MAX_AGENT_ENTRIES = 1024  # agents remembered per counter (unknown agents, refused streams)
# Refusals told per agent per acknowledgement round (each is sent once; a batch re-sent after a
# lost one is refused and told again), keeping every ack message far under the JSON size limit.
MAX_NACKS = 256
RATE_BURST_S = 10.0  # the readings/s quota is an average over this long (a token bucket)


@dataclass(slots=True)
class _Bucket:
    tokens: float
    at: float


class StreamGate:
    """Which (agent, sensor) streams the collector accepts: the stream caps
    (``limits.streams_per_agent``, ``limits.streams_total``), counters of what they refused,
    and sensors published by more than one agent. Writer thread only."""

    def __init__(self, limits: Limits) -> None:
        self._limits = limits
        # Streams (agent, sensor) accepted in this run (or since the last run ended); the
        # Writer makes a new gate at every start and stop, so a cap never outlives its run.
        self.admitted: set[tuple[str, str]] = set()
        self._agent_streams: Counter[str] = Counter()
        self._sensor_agents: dict[str, set[str]] = {}  # sensor MAC -> agents publishing it
        self.refused: Counter[str] = Counter()  # agent -> batches refused (stream caps)
        self.refused_streams: set[tuple[str, str]] = set()  # at most MAX_AGENT_ENTRIES kept
        self._refused_log: dict[str, float] = {}
        self.over_quota: Counter[str] = Counter()  # "agent: rate" / "agent: disk" -> batches
        self._buckets: dict[str, _Bucket] = {}
        self._bytes: Counter[str] = Counter()  # per agent, this run
        # Negative acknowledgements owed since the last round: agent -> (boot, sensor) -> the
        # refusal (its highest seq); the writer sends them once, after the round's fsync.
        self.refusals: dict[str, dict[tuple[str, str], Refusal]] = {}
        self.nacks_due: set[str] = set()

    def admit(self, agent: str, sensor: str, now: float) -> bool:
        """Accept a new (agent, sensor) stream under the stream caps, or refuse its batch (not
        written, not acknowledged, counted)."""
        lim = self._limits
        key = (agent, sensor)
        if (
            self._agent_streams[agent] >= lim.streams_per_agent
            or len(self.admitted) >= lim.streams_total
        ):
            if agent in self.refused or len(self.refused) < MAX_AGENT_ENTRIES:
                self.refused[agent] += 1
            else:
                self.refused["(other agents)"] += 1
            if len(self.refused_streams) < MAX_AGENT_ENTRIES:
                self.refused_streams.add(key)
            if (
                now - self._refused_log.get(agent, -1e9) >= 60
                and len(self._refused_log) < MAX_AGENT_ENTRIES
            ):
                self._refused_log[agent] = now
                which = (
                    f"agent {agent} already has {lim.streams_per_agent} streams"
                    if self._agent_streams[agent] >= lim.streams_per_agent
                    else f"the collector already has {lim.streams_total} streams"
                )
                log.warning(
                    "refused sensor %s of agent %s: %s (limits.streams_per_agent / "
                    "streams_total); its batches are not written (%d refused so far)",
                    sensor,
                    agent,
                    which,
                    self.refused[agent],
                )
            return False
        self.admit_known(key)
        return True

    def quota(self, agent: str, nrows: int, nbytes: int, now: float) -> str | None:
        """Charge a batch to its agent's quotas; the reason it is refused, or None."""
        lim = self._limits
        rate = lim.agent_readings_per_s
        b = self._buckets.get(agent)
        if b is None:
            if len(self._buckets) >= MAX_AGENT_ENTRIES:
                return None  # agents past the bookkeeping bound are held by the stream caps
            b = self._buckets[agent] = _Bucket(rate * RATE_BURST_S, now)
        b.tokens = min(rate * RATE_BURST_S, b.tokens + (now - b.at) * rate)
        b.at = now
        if self._bytes[agent] + nbytes > lim.agent_mb_per_run * 1024 * 1024:
            why = f"over limits.agent_mb_per_run ({lim.agent_mb_per_run:g} MB in this run)"
            kind = "disk"
        elif b.tokens < nrows:
            why = f"over limits.agent_readings_per_s ({rate:g} readings/s over {RATE_BURST_S:g} s)"
            kind = "rate"
        else:
            b.tokens -= nrows
            self._bytes[agent] += nbytes
            return None
        key = f"{agent}: {kind}"
        if key in self.over_quota or len(self.over_quota) < MAX_AGENT_ENTRIES:
            self.over_quota[key] += 1
        return why

    def refuse(self, agent: str, boot: str, sensor: str, seq: int, reason: str) -> None:
        """Owe ``agent`` a negative acknowledgement for this batch (its stream's highest)."""
        mine = self.refusals.get(agent)
        if mine is None:
            if len(self.refusals) >= MAX_AGENT_ENTRIES:
                return
            mine = self.refusals[agent] = {}
        key = (boot, sensor)
        old = mine.get(key)
        if old is None and len(mine) >= MAX_NACKS:
            return  # the rest are refused again when re-sent, and told then
        if old is None or seq > old.upto:
            mine[key] = Refusal(seq, reason[:MAX_REASON])
        self.nacks_due.add(agent)

    def reason_for_cap(self, agent: str) -> str:
        lim = self._limits
        if self._agent_streams[agent] >= lim.streams_per_agent:
            return f"stream cap: agent {agent} already has {lim.streams_per_agent} streams"
        return f"stream cap: the collector already has {lim.streams_total} streams"

    def admit_known(self, key: tuple[str, str]) -> None:
        """Count a stream as admitted without checking the caps (a resumed run's streams)."""
        if key in self.admitted:
            return
        agent, sensor = key
        self.admitted.add(key)
        self._agent_streams[agent] += 1
        agents = self._sensor_agents.setdefault(sensor, set())
        agents.add(agent)
        if len(agents) > 1:
            log.warning(
                "sensor %s is published by agents %s: kept as separate streams "
                "(rssi/<agent>/%s.mbd); a copied adapter address or a misconfigured agent?",
                sensor,
                ", ".join(sorted(agents)),
                sensor,
            )

    def shared_sensors(self) -> dict[str, list[str]]:
        """Sensor MACs published by more than one agent since the collector started."""
        return {m: sorted(a) for m, a in sorted(self._sensor_agents.items()) if len(a) > 1}
