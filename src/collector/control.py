"""The collector's control side: the queryables operators call (start, stop, status, runs), what
the collector knows about agents (liveliness, their status replies) and agent clock checks.

One control thread answers queries and asks agents for their status and clock (blocking calls),
so neither Zenoh's callbacks nor the writer ever wait on the network.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from ble_groundtruth import wire
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.store import iso_utc, list_runs

if TYPE_CHECKING:
    from collector.writer import Inbox, Writer

log = logging.getLogger(__name__)

COMMANDS = ("start", "stop", "status", "runs")


class AgentBook:
    """Agents as the collector sees them: liveliness (alive or left) and their last status reply.
    Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, bool] = {}
        self._info: dict[str, dict[str, Any]] = {}
        self._pending: set[str] = set()

    def set_alive(self, agent: str, alive: bool) -> None:
        with self._lock:
            self._alive[agent] = alive

    def alive_map(self) -> dict[str, bool]:
        with self._lock:
            return dict(self._alive)

    def alive_agents(self) -> set[str]:
        with self._lock:
            return {a for a, alive in self._alive.items() if alive}

    def set_info(self, agent: str, info: dict[str, Any]) -> None:
        with self._lock:
            self._info[agent] = info

    def infos(self) -> dict[str, dict[str, Any]]:
        with self._lock:
            return {a: dict(i) for a, i in self._info.items()}

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


def clock_sample(msg: dict[str, Any], t1: int, t4: int, at: str) -> dict[str, Any]:
    """One clock measurement from an agent's reply (t1 echoed, t2, t3) and our t4, all Unix ns."""
    t2, t3 = msg.get("t2"), msg.get("t3")
    if msg.get("t1") != t1:
        raise wire.InvalidField("clock reply does not echo our t1")
    if not (
        isinstance(t2, int)
        and not isinstance(t2, bool)
        and isinstance(t3, int)
        and not isinstance(t3, bool)
    ):
        raise wire.InvalidField("clock reply needs integer t2 and t3 (ns)")
    chrony = msg.get("chrony")
    if chrony is not None and not isinstance(chrony, dict):
        raise wire.InvalidField("clock reply chrony must be an object or null")
    offset = ((t2 - t1) + (t3 - t4)) / 2
    rtt = (t4 - t1) - (t3 - t2)
    return {
        "at": at,
        "offset_ms": round(offset / 1e6, 3),
        "rtt_ms": round(rtt / 1e6, 3),
        "chrony": chrony,
    }


def _request_name(req: dict[str, Any]) -> str | None:
    name = req.get("name")
    if name is not None and not isinstance(name, str):
        raise CollectorError("start: name must be a string or null")
    return name


def _request_clock_limits(req: dict[str, Any]) -> tuple[float | None, bool]:
    max_off, strict = req.get("max_offset_ms"), req.get("strict", False)
    if max_off is not None and (
        isinstance(max_off, bool) or not isinstance(max_off, int | float) or max_off < 0
    ):
        raise CollectorError("start: max_offset_ms must be a non-negative number or null")
    if not isinstance(strict, bool):
        raise CollectorError("start: strict must be true or false")
    return (None if max_off is None else float(max_off)), strict


class Control:
    """Answers control queries and talks to agents; runs start and stop through the writer."""

    def __init__(
        self,
        cfg: CollectorConfig,
        writer: Writer,
        inbox: Inbox,
        agents: AgentBook,
        *,
        clock: Callable[[], int],
        monotonic: Callable[[], float],
        status_timeout_s: float,
    ) -> None:
        self.cfg = cfg
        self.writer = writer
        self.inbox = inbox
        self.agents = agents
        self._clock = clock
        self._mono = monotonic
        self._status_timeout = status_timeout_s
        self._queue: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.session: Any = None  # the collector's zenoh.Session once open

    # -- entry points from Zenoh callbacks and the writer (never block) ---------------------------

    def on_query(self, cmd: str, query: Any) -> None:
        self._queue.put((cmd, query))

    def on_token(self, sample: Any) -> None:
        import zenoh

        agent = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT
        self.agents.set_alive(agent, alive)
        log.info("agent %s %s", agent, "joined" if alive else "left")
        if alive:
            self._queue.put(("agent_info", agent))

    def want_agent_info(self, agent: str) -> None:
        """Fetch an agent's status once (the writer calls this for a new stream)."""
        if self.agents.claim_fetch(agent):
            self._queue.put(("agent_info", agent))

    # -- the control thread ------------------------------------------------------------------------

    def loop(self, closing: threading.Event) -> None:
        last_clock = self._mono()
        while not closing.is_set():
            if self.writer.run_active and self._mono() - last_clock >= self.cfg.clock_interval_s:
                last_clock = self._mono()
                self._periodic_clock()
            try:
                cmd, arg = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            if cmd == "agent_info":
                self._fetch_agent_info(wire.agent_status_key(self.cfg.site, arg))
                self.agents.fetched(arg)
                continue
            if cmd == "start":
                last_clock = self._mono()
            self._answer(cmd, arg)

    def _periodic_clock(self) -> None:
        try:
            samples = self.measure_clocks()
            if samples:
                self.writer.call(lambda: self.writer.add_clock(samples), 10.0)
        except Exception:
            log.exception("periodic clock check failed")

    def _answer(self, cmd: str, query: Any) -> None:
        key = wire.collector_control_key(self.cfg.site, cmd)
        raw = b""
        try:
            req: dict[str, Any] = {}
            if query.payload is not None:
                raw = query.payload.to_bytes()
            if raw.strip():
                req = wire.from_json(raw, f"{cmd} request")
            reply: dict[str, Any] | None
            if cmd == "start":
                max_off, strict = _request_clock_limits(req)
                reply = self.start_run(_request_name(req), max_offset_ms=max_off, strict=strict)
            elif cmd == "stop":
                reply = self.stop_run()
            elif cmd == "status":
                reply = self.status()
            else:
                reply = {"runs": list_runs(self.cfg.data_dir)}
            reply = {"ok": True, **(reply or {})}
        except wire.WireError as e:
            self.inbox.reject("bad_request", key, str(e), raw)
            reply = {"ok": False, "error": str(e)}
        except CollectorError as e:
            reply = {"ok": False, "error": str(e)}
        except Exception as e:
            log.exception("control command %s failed", cmd)
            reply = {"ok": False, "error": f"internal error: {type(e).__name__}: {e}"}
        try:
            query.reply(key, wire.to_json(reply))
        except Exception as e:  # noqa: BLE001 - the asker may be gone; the collector goes on
            log.warning("could not answer %s: %s", cmd, e)
        finally:
            query.drop()

    # -- runs ---------------------------------------------------------------------------------------

    def start_run(
        self,
        name: str | None = None,
        timeout: float = 10.0,
        *,
        max_offset_ms: float | None = None,
        strict: bool = False,
    ) -> dict[str, Any]:
        """Start a run; agents' clocks are measured first. With ``strict``, an agent whose clock
        is off by more than ``max_offset_ms`` refuses the start (CollectorError)."""
        w = self.writer
        if w.run_active:  # answer at once, without asking the agents anything first
            return w.call(lambda: w.start(name, {}), timeout)
        self.refresh_agents()
        samples = self.measure_clocks()
        warnings = []
        if max_offset_ms is not None:
            for agent, smp in sorted(samples.items()):
                if abs(smp["offset_ms"]) > max_offset_ms:
                    warnings.append(
                        f"agent {agent}: clock offset {smp['offset_ms']:+.1f} ms "
                        f"exceeds {max_offset_ms:g} ms (round trip "
                        f"{smp['rtt_ms']:.1f} ms)"
                    )
        if strict and warnings:
            more = f" ({len(warnings) - 1} more agents off)" if len(warnings) > 1 else ""
            raise CollectorError(
                f"{warnings[0]}; fix its time sync (chrony) or start without --strict{more}"
            )
        reply = w.call(lambda: w.start(name, samples), timeout)
        reply["clock"] = {
            a: {"offset_ms": v["offset_ms"], "rtt_ms": v["rtt_ms"]} for a, v in samples.items()
        }
        reply["clock_warnings"] = warnings
        return reply

    def stop_run(
        self, *, reason: str = "requested", missing_ok: bool = False, timeout: float = 60.0
    ) -> dict[str, Any] | None:
        w = self.writer
        self.refresh_agents()
        if w.run_active:
            samples = self.measure_clocks()
            if samples:
                w.call(lambda: w.add_clock(samples), timeout)
        fut: Future[dict[str, Any] | None] = Future()
        w.post(lambda: w.stop(fut, reason, missing_ok))
        return fut.result(timeout)

    def status(self, timeout: float = 10.0) -> dict[str, Any]:
        from collector.summary import build_status

        return self.writer.call(lambda: build_status(self.writer, self._mono()), timeout)

    # -- agents -------------------------------------------------------------------------------------

    def refresh_agents(self) -> None:
        """Ask every agent for its status (adapter names, backend, mode) for run.yaml."""
        if self.writer.on_writer_thread():
            return  # never block the writer
        self._fetch_agent_info(wire.agent_status_selector(self.cfg.site))

    def _fetch_agent_info(self, selector: str) -> None:
        if self.session is None:
            return
        try:
            replies = self.session.get(selector, timeout=self._status_timeout)
            for reply in replies:
                if reply.ok is None:
                    continue
                key = str(reply.ok.key_expr)
                try:
                    # The agent is the one named by the reply's key (which the ACL lets only that
                    # agent answer on), never the id the payload claims.
                    agent = wire.check_id(key.rsplit("/", 1)[-1], "agent id")
                    if key != wire.agent_status_key(self.cfg.site, agent):
                        raise wire.InvalidField(f"not an agent status key: {key}")
                    info = wire.from_json(reply.ok.payload.to_bytes(), "agent status")
                except wire.WireError as e:
                    log.warning("ignoring an agent status reply on %s: %s", key, e)
                    continue
                claimed = info.get("agent_id")
                if claimed != agent:
                    log.warning(
                        "agent %s's status reply names itself %r; credited to %s (the key)",
                        agent,
                        claimed,
                        agent,
                    )
                    info = {**info, "agent_id": agent}
                self.agents.set_info(agent, info)
        except Exception as e:  # noqa: BLE001 - agent status is best effort; the data path is not
            log.warning("could not query agent status on %s: %s", selector, e)

    def measure_clocks(self) -> dict[str, dict[str, Any]]:
        """Four-timestamp exchange with every live agent (contract 4), one query per agent so
        each reply's arrival time t4 is its own.

        offset = ((t2 - t1) + (t3 - t4)) / 2 is how far the agent's clock is ahead of ours;
        rtt = (t4 - t1) - (t3 - t2) is the network round trip without the agent's own delay.
        """
        if self.session is None or self.writer.on_writer_thread():
            return {}
        out: dict[str, dict[str, Any]] = {}
        for agent in sorted(self.agents.alive_agents()):
            key = wire.agent_clock_key(self.cfg.site, agent)
            try:
                t1 = self._clock()
                replies = self.session.get(
                    key, payload=wire.to_json({"t1": t1}), timeout=self._status_timeout
                )
                for reply in replies:
                    t4 = self._clock()
                    if reply.ok is None:
                        log.warning(
                            "agent %s refused the clock check: %s",
                            agent,
                            reply.err.payload.to_string()[:200],
                        )
                        break
                    msg = wire.from_json(reply.ok.payload.to_bytes(), "clock reply")
                    out[agent] = clock_sample(msg, t1, t4, iso_utc(t4))
                    break
            except wire.WireError as e:
                log.warning("ignoring the clock reply of agent %s: %s", agent, e)
            except Exception as e:  # noqa: BLE001 - clock health is advisory; never blocks a run
                log.warning("could not check the clock of agent %s: %s", agent, e)
        return out
