"""What the collector knows about its agents: liveliness (alive or left) and their last status
reply. Shared by the control thread (which fetches statuses) and the writer (which reads them);
it depends on nothing else of the collector, so neither of the two depends on the other for it."""

from __future__ import annotations

import threading
import time

from bgt_core.messages import AgentStatus


class AgentBook:
    """Agents as the collector sees them: liveliness (alive or left) and their last status reply.
    Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, bool] = {}
        self._info: dict[str, AgentStatus] = {}
        self._pending: set[str] = set()
        self._acked: dict[str, float] = {}  # monotonic time of the last ack sent to each agent

    def set_alive(self, agent: str, alive: bool) -> None:
        with self._lock:
            self._alive[agent] = alive

    def alive_map(self) -> dict[str, bool]:
        with self._lock:
            return dict(self._alive)

    def alive_agents(self) -> set[str]:
        with self._lock:
            return {a for a, alive in self._alive.items() if alive}

    def set_info(self, agent: str, info: AgentStatus) -> None:
        with self._lock:
            self._info[agent] = info

    def infos(self) -> dict[str, AgentStatus]:
        with self._lock:
            return dict(self._info)

    def acked(self, agent: str, now: float | None = None) -> None:
        with self._lock:
            self._acked[agent] = time.monotonic() if now is None else now

    def last_acks(self) -> dict[str, float]:
        with self._lock:
            return dict(self._acked)

    def claim_fetch(self, agent: str) -> bool:
        """True if nobody has asked for this agent's status yet (and it is now pending)."""
        with self._lock:
            if agent in self._info or agent in self._pending:
                return False
            self._pending.add(agent)
            return True

    def fetched(self, agent: str) -> None:
        with self._lock:
            self._pending.discard(agent)
