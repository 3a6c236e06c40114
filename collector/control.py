"""The collector's control side: the queryables operators call (start, stop, status, runs),
fetching agents' status replies (kept in collector.agents.AgentBook) and agent clock checks.

One control thread answers queries and asks agents for their status and clock (blocking calls),
so neither Zenoh's callbacks nor the writer ever wait on the network.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from bgt_core import wire
from bgt_core.control_messages import (
    AgentClock,
    CollectorStatus,
    Reply,
    StartReply,
    StartRequest,
    StopReply,
)
from bgt_core.messages import AgentStatus, ClockReply, ClockRequest, ClockSample
from bgt_core.run_record import iso_utc
from collector.agents import AgentBook
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.store import list_runs
from collector.summary import build_status

if TYPE_CHECKING:
    import zenoh

    from collector.inbox import Inbox
    from collector.writer import Writer

log = logging.getLogger(__name__)

COMMANDS = ("start", "stop", "status", "runs")


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
        self.session: zenoh.Session | None = None  # the collector's session once open

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
            body: dict[str, Any] = {}
            if cmd == "start":
                try:
                    start = StartRequest.from_dict(req)
                except wire.InvalidField as e:  # a well-formed request with a bad value
                    raise CollectorError(str(e)) from None
                body = self.start_run(start).to_dict()
            elif cmd == "stop":
                stopped = self.stop_run()
                body = {} if stopped is None else stopped.to_dict()
            elif cmd == "status":
                body = self.status().to_dict()
            else:
                body = {"runs": list_runs(self.cfg.data_dir)}
            reply = Reply(True, body=body)
        except wire.WireError as e:
            self.inbox.reject("bad_request", key, str(e), raw)
            reply = Reply(False, str(e))
        except CollectorError as e:
            reply = Reply(False, str(e))
        except Exception as e:
            log.exception("control command %s failed", cmd)
            reply = Reply(False, f"internal error: {type(e).__name__}: {e}")
        try:
            query.reply(key, wire.to_json(reply.to_dict()))
        except Exception as e:  # noqa: BLE001 - the asker may be gone; the collector goes on
            log.warning("could not answer %s: %s", cmd, e)
        finally:
            query.drop()

    # -- runs ---------------------------------------------------------------------------------------

    def start_run(self, req: StartRequest, timeout: float = 10.0) -> StartReply:
        """Start a run; agents' clocks are measured first. With ``req.strict``, an agent whose
        clock is off by more than ``req.max_offset_ms`` refuses the start (CollectorError).

        The run starts only within ``timeout`` of the request's arrival: a start that would land
        later (a busy writer, slow agents) is refused, so an operator whose command timed out
        never finds a run started behind its back."""
        deadline = self._mono() + timeout
        try:
            return self._start_by(req, deadline)
        except TimeoutError:
            raise CollectorError(
                f"the collector did not start the run within {timeout:g} s (its writer is busy); "
                "nothing was started"
            ) from None

    def _start_by(self, req: StartRequest, deadline: float) -> StartReply:
        w = self.writer
        if w.run_active:  # answer at once, without asking the agents anything first
            return w.call(
                lambda: w.start(req.name, {}, deadline, notes=req.notes), deadline - self._mono()
            )
        self.refresh_agents()
        samples = self.measure_clocks()
        warnings = []
        limit = req.max_offset_ms
        if limit is not None:
            for agent, smp in sorted(samples.items()):
                if abs(smp.offset_ms) > limit:
                    warnings.append(
                        f"agent {agent}: clock offset {smp.offset_ms:+.1f} ms "
                        f"exceeds {limit:g} ms (round trip {smp.rtt_ms:.1f} ms)"
                    )
        if req.strict and warnings:
            more = f" ({len(warnings) - 1} more agents off)" if len(warnings) > 1 else ""
            raise CollectorError(
                f"{warnings[0]}; fix its time sync (chrony) or start without --strict{more}"
            )
        remaining = deadline - self._mono()
        if remaining <= 0:
            raise CollectorError(
                "measuring the agents' clocks took longer than the start may wait; nothing was "
                "started (try again)"
            )
        started = w.call(lambda: w.start(req.name, samples, deadline, notes=req.notes), remaining)
        clock = {a: AgentClock(v.offset_ms, v.rtt_ms) for a, v in samples.items()}
        return dataclasses.replace(started, clock=clock, clock_warnings=tuple(warnings))

    def stop_run(
        self, *, reason: str = "requested", missing_ok: bool = False, timeout: float = 60.0
    ) -> StopReply | None:
        w = self.writer
        self.refresh_agents()
        if w.run_active:
            samples = self.measure_clocks()
            if samples:
                w.call(lambda: w.add_clock(samples), timeout)
        fut: Future[StopReply | None] = Future()
        w.post(lambda: w.stop(fut, reason, missing_ok))
        return fut.result(timeout)

    def status(self, timeout: float = 10.0) -> CollectorStatus:
        return self.writer.call(
            lambda: build_status(self.writer.status_view(self._mono())), timeout
        )

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
                    info = AgentStatus.from_dict(
                        wire.from_json(reply.ok.payload.to_bytes(), "agent status")
                    )
                except wire.WireError as e:
                    log.warning("ignoring an agent status reply on %s: %s", key, e)
                    continue
                claimed = info.agent_id
                if claimed != agent:
                    log.warning(
                        "agent %s's status reply names itself %r; credited to %s (the key)",
                        agent,
                        claimed,
                        agent,
                    )
                    info = dataclasses.replace(info, agent_id=agent)
                self.agents.set_info(agent, info)
        except Exception as e:  # noqa: BLE001 - agent status is best effort; the data path is not
            log.warning("could not query agent status on %s: %s", selector, e)

    def measure_clocks(self) -> dict[str, ClockSample]:
        """Four-timestamp exchange with every live agent (contract 4), one query per agent so
        each reply's arrival time t4 is its own.

        See ``messages.clock_offset`` for the arithmetic.
        """
        if self.session is None or self.writer.on_writer_thread():
            return {}
        out: dict[str, ClockSample] = {}
        for agent in sorted(self.agents.alive_agents()):
            key = wire.agent_clock_key(self.cfg.site, agent)
            try:
                t1 = self._clock()
                replies = self.session.get(
                    key,
                    payload=wire.to_json(ClockRequest(t1).to_dict()),
                    timeout=self._status_timeout,
                )
                for reply in replies:
                    t4 = self._clock()
                    if reply.ok is None:
                        log.warning(
                            "agent %s refused the clock check: %s",
                            agent,
                            "" if reply.err is None else reply.err.payload.to_string()[:200],
                        )
                        break
                    msg = ClockReply.from_dict(
                        wire.from_json(reply.ok.payload.to_bytes(), "clock reply")
                    )
                    out[agent] = ClockSample.measure(msg, t1, t4, iso_utc(t4))
                    break
            except wire.WireError as e:
                log.warning("ignoring the clock reply of agent %s: %s", agent, e)
            except Exception as e:  # noqa: BLE001 - clock health is advisory; never blocks a run
                log.warning("could not check the clock of agent %s: %s", agent, e)
        return out
