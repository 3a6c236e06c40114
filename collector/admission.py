"""Which (agent, sensor) streams the collector accepts: the stream caps of ``limits:``, the
counts of what they refused, and sensors published by more than one agent. The writer makes a
new gate at every start and stop of a run."""

from __future__ import annotations

import logging
from collections import Counter

from collector.config import Limits

log = logging.getLogger(__name__)

MAX_AGENT_ENTRIES = 1024  # agents remembered per counter (unknown agents, refused streams)


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
