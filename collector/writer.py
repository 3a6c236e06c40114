"""The collector's writer thread, which owns all run state: ingest of what the receive side
(``inbox.Inbox``) queued, dedupe, the stream caps, files, state.json, fsync, disk-full handling,
quarantine files, acks, start/stop of runs. The stream caps are ``admission.StreamGate``, the
live per-sensor figures ``live_stats.SensorLive``.

Everything else reaches run state through ``Writer.call``, which runs a function on the writer
thread and waits for its result.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections import Counter
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

from bgt_core import __version__, wire
from bgt_core.control_messages import RefusedStreams, StartReply, StopReply
from bgt_core.messages import Ack, ClockSample
from bgt_core.sdnotify import Notifier
from collector import views
from collector.admission import MAX_AGENT_ENTRIES, StreamGate
from collector.agents import AgentBook
from collector.beacon_rates import report_drop
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.inbox import Inbox
from collector.ingest import StreamTracker
from collector.live_stats import SensorLive
from collector.readings import beacons, count_beacons, format_rows
from collector.run_state import RunState
from collector.store import STATE_FILE, FileWrite, RunWriter, is_disk_full, make_run_id
from collector.summary import Counters, StatusView, run_summary

log = logging.getLogger(__name__)

T = TypeVar("T")

TICK_S = 0.2  # flush + ack period while data arrives
REACK_S = 2.0  # acks are repeated this often, in case an agent missed one
LIVE_IDLE_S = 3600.0  # live state of a stream silent this long is dropped
MAX_BUFFER_BYTES = 64 * 1024 * 1024  # rows held in memory while the disk refuses them
DISK_RETRY_S = 1.0
QUARANTINE_MAX_BYTES = 16 * 1024 * 1024  # per run; beyond it rejects are only counted


@dataclass(slots=True)
class Stopping:
    """A stop request waiting for the run to drain."""

    future: Future[StopReply | None]
    requested: float  # monotonic
    reason: str


@dataclass(slots=True)
class Resumed:
    """What crash resume recovered from a run's state.json, for the writer to adopt."""

    run: RunWriter
    tracker: StreamTracker
    clock_log: dict[str, list[ClockSample]]
    restarts: int
    quarantined_bytes: int


class Writer:
    """Owns the run: every attribute below is read and written on the writer thread only
    (``call`` runs a function there), except ``inbox`` and ``agents``, which are thread-safe."""

    def __init__(
        self,
        cfg: CollectorConfig,
        inbox: Inbox,
        agents: AgentBook,
        *,
        clock: Callable[[], int],
        monotonic: Callable[[], float],
        notifier: Notifier,
        file_write: FileWrite,
        drain_grace_s: float,
        drain_timeout_s: float,
        max_buffer_bytes: int,
        quarantine_max_bytes: int,
        open_files: int,
    ) -> None:
        self.cfg = cfg
        self.inbox = inbox
        self.agents = agents
        self._clock = clock
        self._mono = monotonic
        self._notifier = notifier
        self._file_write = file_write  # tests inject a writer that fails like a full disk
        self._drain_grace = drain_grace_s
        self._drain_timeout = drain_timeout_s
        self._max_buffer = max_buffer_bytes
        self._quarantine_max = quarantine_max_bytes
        self._open_files = open_files
        self._cmds: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]]] = queue.SimpleQueue()
        # Publishes one ack (key, payload); set once the Zenoh session is open.
        self.publish: Callable[[str, bytes], None] | None = None
        # Asks the control thread for an agent's status; set by the service.
        self.want_agent_info: Callable[[str], None] = lambda _agent: None
        self.thread: threading.Thread | None = None
        self.run_active = False  # mirror of `run is not None` for the other threads
        self.gate = StreamGate(cfg.limits)
        self.tracker = StreamTracker()
        self.run: RunWriter | None = None
        self.stopping: Stopping | None = None
        self.live: dict[tuple[str, str], SensorLive] = {}
        self.discarded = 0
        self.write_errors = 0
        self._write_failing = False  # the last write attempt failed (not for lack of space)
        self.deferred = 0  # batches refused unacked while rows piled up in memory (disk full)
        self.unknown_agents: dict[str, int] = {}
        self._recent: dict[str, float] = {}  # agent -> monotonic time of its last batch
        self.clock_log: dict[str, list[ClockSample]] = {}
        self.restarts = 0
        self._dirty = False  # something to persist since the last state.json
        self._quarantined_bytes = 0

    # -- commands from other threads -------------------------------------------------------------

    def call(self, fn: Callable[[], T], timeout: float) -> T:
        """Run ``fn`` on the writer thread; its result (or exception) once it ran."""
        fut: Future[T] = Future()
        self._cmds.put((fn, fut))
        return fut.result(timeout)

    def post(self, fn: Callable[[], object]) -> None:
        """Run ``fn`` on the writer thread without waiting."""
        self._cmds.put((fn, Future()))

    def on_writer_thread(self) -> bool:
        return threading.current_thread() is self.thread

    def idle(self) -> bool:
        """Nothing queued: no data and no commands."""
        return self.inbox.data.empty() and self._cmds.empty()

    def adopt(self, resumed: Resumed) -> None:
        """Continue a run recovered after a crash (before the writer thread starts)."""
        run, tracker = resumed.run, resumed.tracker
        self.run, self.tracker = run, tracker
        for a, _b, sn in tracker.streams:
            self.gate.admit_known((a, sn))
        for key in run.sensors:
            self.gate.admit_known(key)
        self.run_active = True
        self.clock_log = resumed.clock_log
        self.restarts = resumed.restarts
        self._quarantined_bytes = resumed.quarantined_bytes
        try:
            run.write_state(self.state())
        except OSError as e:  # the old state still matches the repaired files; go on
            log.warning("could not update %s: %s", run.dir / STATE_FILE, e)

    def drop_run(self) -> None:
        """Close the run's files without finishing it (the service could not start)."""
        if self.run is not None:
            self.run.close()
            self.run = None
            self.run_active = False

    # -- the thread -------------------------------------------------------------------------------

    def loop(self, closing: threading.Event) -> None:
        now = self._mono()
        clocks = {
            "tick": now,
            "fsync": now,
            "reack": now,
            "watchdog": -1e9,
            "disk_retry": -1e9,
            "write_error_log": -1e9,
        }
        while True:
            try:
                self._step(clocks)
            except Exception:
                # A bug must not silently stop ingest (futures would hang); log it and go on.
                log.exception("collector writer step failed")
            if closing.is_set() and self.idle():
                break

    def _step(self, clocks: dict[str, float]) -> None:
        while True:
            try:
                fn, fut = self._cmds.get_nowait()
            except queue.Empty:
                break
            try:
                fut.set_result(fn())
            except Exception as e:  # noqa: BLE001 - handed to whoever waits on the future
                fut.set_exception(e)
        self._ingest_some()
        self._write_quarantine()
        now = self._mono()
        wd = self._notifier.watchdog_interval_s
        if wd is not None and now - clocks["watchdog"] >= wd:
            # From the writer thread on purpose: if ingest hangs, systemd restarts the service.
            clocks["watchdog"] = now
            self._notifier.watchdog()
        if now - clocks["tick"] >= TICK_S or self.stopping is not None:
            clocks["tick"] = now
            moved: set[str] = set()
            if self.run is None:
                moved = self.tracker.mark_durable()
            else:
                moved = self._persist(self.run, now, clocks)
            if now - clocks["reack"] >= REACK_S:  # repeat acks: an agent may have missed one
                clocks["reack"] = now
                moved |= self.agents.alive_agents()
                # Also agents heard from lately whose token is missing or late.
                moved |= {a for a, t in self._recent.items() if now - t < 60}
                self._prune_live(now)
            self.publish_acks(moved)
            if self.stopping is not None:
                self._maybe_finish_stop(self.stopping, now)

    def _persist(self, run: RunWriter, now: float, clocks: dict[str, float]) -> set[str]:
        """Write buffered rows; at fsync time: fsync files, then state.json, then (and only then)
        move the ack watermarks. Disk full: roll back, keep rows in memory, retry, ack nothing."""
        if (
            (run.disk_full or self._write_failing)
            and now - clocks["disk_retry"] < DISK_RETRY_S
            and self.stopping is None
        ):
            return set()
        try:
            run.flush()
            self._write_failing = False
            due = now - clocks["fsync"] >= self.cfg.fsync_interval_s
            if (due and self._dirty) or run.disk_full or self.stopping is not None:
                run.fsync()
                run.write_state(self.state())
                self._dirty = False
                clocks["fsync"] = now
                if run.disk_full:
                    run.disk_full = False
                    log.warning(
                        "run %s: writing again, disk space is back (%d batches were "
                        "refused meanwhile; agents re-send them)",
                        run.run_id,
                        self.deferred,
                    )
                    self._notifier.status(f"recording run {run.run_id}")
                return self.tracker.mark_durable()
        except OSError as e:
            clocks["disk_retry"] = now
            if is_disk_full(e):
                if not run.disk_full:
                    run.disk_full = True
                    log.error(  # noqa: TRY400 - a known condition, no traceback wanted
                        "run %s: disk full (%s); stopped writing, holding up to %.1f MiB in "
                        "memory unacknowledged and retrying every %.0f s",
                        run.run_id,
                        e.strerror,
                        self._max_buffer / 2**20,
                        DISK_RETRY_S,
                    )
                    self._notifier.status(f"DISK FULL: run {run.run_id} is not being written")
            else:
                self.write_errors += 1
                self._write_failing = True
                if now - clocks["write_error_log"] > 10:
                    clocks["write_error_log"] = now
                    log.error(  # noqa: TRY400 - a known condition, no traceback wanted
                        "cannot write run %s: %s (retrying; nothing is acknowledged "
                        "until it works)",
                        run.run_id,
                        e,
                    )
        return set()

    def state(self) -> RunState:
        """state.json of the active run (which must exist)."""
        if self.run is None:
            raise CollectorError("no run is active")
        return self.run.state(
            tracker=self.tracker.to_state(),
            lost_base=dict(self.tracker.lost_base),
            clock={a: tuple(v) for a, v in self.clock_log.items()},
            restarts=self.restarts,
            quarantined_bytes=self._quarantined_bytes,
        )

    def _ingest_some(self) -> None:
        data = self.inbox.data
        first = data.get(timeout=0.05)
        if first is None:
            return
        batches = [first]
        for _ in range(5000):
            b = data.get(timeout=0)
            if b is None:
                break
            batches.append(b)
        now = self._mono()
        run, tracker, live = self.run, self.tracker, self.live
        # While the disk refuses rows, memory holds them up to a bound; past it, batches are
        # refused before dedupe, so they stay unacknowledged and the agents send them again.
        # The memory bound applies only while writes fail; otherwise the next tick writes it all.
        capped = run is not None and (run.disk_full or self._write_failing)
        buffered = run.buffered if run is not None and capped else 0
        alive = self.agents.alive_map()
        self._dirty = True  # even a duplicate may carry a higher floor
        gate = self.gate
        admitted = gate.admitted
        for b in batches:
            if (b.agent_id, b.sensor) not in admitted and not gate.admit(b.agent_id, b.sensor, now):
                gate.refuse(b.agent_id, b.boot_id, b.sensor, b.seq, gate.reason_for_cap(b.agent_id))
                continue
            self._recent[b.agent_id] = now
            if capped and buffered >= self._max_buffer:
                self.deferred += 1
                continue
            new_stream = b.stream not in tracker.streams
            if not tracker.accept(b.stream, b.seq, b.floor):
                continue
            if new_stream:
                self.want_agent_info(b.agent_id)
            if not alive.get(b.agent_id):
                self._count_unknown(b.agent_id)
            if len(b.rows):
                sl = live.get((b.agent_id, b.sensor))
                if sl is None:
                    sl = live[(b.agent_id, b.sensor)] = SensorLive(b.agent_id)
                found = beacons(b.rows)
                counts = count_beacons(b.rows, found)
                for mac, drop in sl.add(now, b.rows, counts):
                    report_drop(b.agent_id, b.sensor, mac, drop)
                if run is not None:
                    text = format_rows(b.sensor, b.rows, found)
                    why = gate.quota(b.agent_id, len(b.rows), len(text), now)
                    if why is not None:
                        # Refused after the tracker took it: the seq counts as handled (nothing
                        # waits for it) and the agent drops it on the negative acknowledgement.
                        gate.refuse(b.agent_id, b.boot_id, b.sensor, b.seq, why)
                        continue
                    run.append(b.agent_id, b.sensor, text, len(b.rows), counts)
                    buffered += len(text) if capped else 0
                else:
                    self.discarded += len(b.rows)

    def _count_unknown(self, agent: str) -> None:
        n = self.unknown_agents.get(agent, 0)
        if n == 0:
            log.warning(
                "data from agent %s, which has no liveliness token (not a running "
                "agent of this site?); recorded and counted as unknown_agent",
                agent,
            )
        if n or len(self.unknown_agents) < MAX_AGENT_ENTRIES:
            self.unknown_agents[agent] = n + 1

    def _prune_live(self, now: float) -> None:
        for (agent, sensor), sl in self.live.items():
            for mac, drop in sl.check(now):
                report_drop(agent, sensor, mac, drop)
        for k in [k for k, sl in self.live.items() if now - sl.last_seen > LIVE_IDLE_S]:
            del self.live[k]
        for a in [a for a, t in self._recent.items() if now - t >= 60]:
            del self._recent[a]

    def _write_quarantine(self) -> None:
        recs: list[dict[str, Any]] = []
        try:
            while len(recs) < 1000:
                recs.append(self.inbox.quarantine.get_nowait())
        except queue.Empty:
            pass
        if not recs or self.run is None:
            return  # without a run, rejects are only counted
        lines = []
        dropped = 0
        for rec in recs:
            line = wire.to_json(rec) + b"\n"
            if self._quarantined_bytes + len(line) > self._quarantine_max:
                dropped += 1
                continue
            self._quarantined_bytes += len(line)
            lines.append(line)
        if lines:
            try:
                with (self.run.dir / "rejected.jsonl").open("ab") as f:
                    f.write(b"".join(lines))
            except OSError as e:
                dropped += len(lines)
                log.warning("could not write %s/rejected.jsonl: %s", self.run.dir, e)
        if dropped:
            self.inbox.count_quarantine_dropped(dropped)

    def publish_acks(self, agents: set[str]) -> None:
        """The acks of these agents (and the negative acknowledgements owed to any): called
        after the tick's fsync, so everything below a refused seq that was written is durable."""
        if self.publish is None:
            return
        gate = self.gate
        for agent in agents | gate.nacks_due:
            msgs = {m.boot: m for m in self.tracker.ack_messages(agent)}
            for (boot, sensor), refusal in gate.refusals.pop(agent, {}).items():
                m = msgs.get(boot) or Ack(boot)
                msgs[boot] = Ack(boot, m.streams, {**m.refused, sensor: refusal})
            for msg in msgs.values():
                if not msg.streams and not msg.refused:
                    continue
                try:
                    self.publish(wire.ack_key(self.cfg.site, agent), wire.to_json(msg.to_dict()))
                    self.agents.acked(agent, self._mono())
                except Exception as e:  # noqa: BLE001 - the next tick retries
                    log.warning("could not publish ack for %s: %s", agent, e)
        gate.nacks_due.clear()

    # -- run start and stop (on the writer thread, through `call`) ---------------------------------

    def add_clock(self, samples: dict[str, ClockSample]) -> None:
        if self.run is None:
            return
        for agent, smp in samples.items():
            self.clock_log.setdefault(agent, []).append(smp)
        self._dirty = True

    def start(
        self,
        name: str | None,
        clock_samples: dict[str, ClockSample],
        deadline: float | None = None,
        *,
        notes: str | None = None,
    ) -> StartReply:
        """Start a run, unless ``deadline`` (monotonic s) has passed: the operator's command has
        given up by then and must not find a run started after it reported a failure."""
        if deadline is not None and self._mono() > deadline:
            raise CollectorError(
                "the start request waited too long (the command that sent it has given up); "
                "nothing was started"
            )
        if self.run is not None:
            raise CollectorError(f"run {self.run.run_id} is already active; stop it first")
        t_ns = self._clock()
        run_id = make_run_id(t_ns, name)
        base = run_id
        for i in range(2, 100):
            if not (self.cfg.data_dir / run_id).exists():
                break
            run_id = f"{base}-{i}"
        meta: dict[str, Any] = {"site": self.cfg.site, "software_version": __version__}
        if notes:
            meta["notes"] = notes
        run = RunWriter(
            self.cfg.data_dir,
            run_id,
            name or "",
            t_ns,
            meta,
            write=self._file_write,
            open_files=self._open_files,
        )
        self.tracker.reset_run_totals()
        # A run's stream caps count that run's streams: whatever earlier runs admitted is free.
        self.gate = StreamGate(self.cfg.limits)
        self.clock_log = {a: [smp] for a, smp in clock_samples.items()}
        self.restarts = self._quarantined_bytes = 0
        self.inbox.reset_quarantine_dropped()
        self.deferred = 0
        self._write_failing = False
        self.run = run
        try:
            run.write_state(self.state())
        except OSError as e:
            self.run = None
            raise CollectorError(
                f"cannot write {run.dir / STATE_FILE}: {e.strerror or e}"
            ) from None
        self.run_active = True
        log.info("run %s started in %s", run_id, run.dir)
        self._notifier.status(f"recording run {run_id}")
        return StartReply(run_id, str(run.dir.resolve()))

    def stop(self, fut: Future[StopReply | None], reason: str, missing_ok: bool) -> None:
        """Ask the run to stop once drained; ``fut`` gets the summary (None: no run, missing_ok)."""
        if self.run is None:
            if missing_ok:
                fut.set_result(None)
            else:
                fut.set_exception(CollectorError("no run is active"))
            return
        if self.stopping is not None:
            fut.set_exception(CollectorError(f"run {self.run.run_id} is already stopping"))
            return
        self.stopping = Stopping(fut, self._mono(), reason)

    def counters(self) -> Counters:
        inbox = self.inbox
        return Counters(
            discarded_no_run=self.discarded,
            duplicates_dropped=self.tracker.duplicates,
            rejected_payloads=inbox.rejects.snapshot(),
            queue=inbox.data.qsize(),
            queue_bytes=inbox.data.bytes,
            write_errors=self.write_errors,
            deferred_batches=self.deferred,
            queue_overflow=inbox.overflow,
            quarantine_dropped=inbox.quarantine_dropped,
            unknown_agents=dict(Counter(self.unknown_agents).most_common(20)),
            restarts=self.restarts,
        )

    def refused(self) -> RefusedStreams:
        return views.refused_of(self.gate)

    def status_view(self, now: float) -> StatusView:
        """A copy of what the status reply says (``now``: monotonic s), for summary.build_status."""
        return views.status_view(
            now,
            self.live,
            self.agents,
            self.clock_log,
            self.run,
            self.stopping is not None,
            self.gate,
            self.counters(),
        )

    def _maybe_finish_stop(self, st: Stopping, now: float) -> None:
        run = self.run
        if run is None:
            return
        waited = now - st.requested
        settled = (
            waited >= self._drain_grace
            and self.inbox.data.empty()
            and self.tracker.open_gaps() == 0
            and not run.disk_full
        )
        if not settled and waited < self._drain_timeout:
            return
        if run.disk_full:
            st.future.set_exception(
                CollectorError(
                    f"run {run.run_id}: the disk is full; free space and stop again (nothing was lost "
                    f"so far: {run.buffered} bytes are held in memory)"
                )
            )
            self.stopping = None
            return
        try:
            run.fsync()
            run.write_state(self.state())
            self.tracker.mark_durable()
            stop_ns = self._clock()
            view = views.run_view(
                run,
                stop_ns,
                self.tracker,
                self.agents,
                self.clock_log,
                self.refused(),
                self.counters(),
            )
            agents, summary, totals = run_summary(view, st.reason)
            run.write_yaml(stop_ns=stop_ns, agents=agents, summary=summary)
            run.write_state(dataclasses.replace(self.state(), active=False))
            run.close()
        except Exception as e:  # noqa: BLE001 - reported to the caller of stop; the run stays active
            self.stopping = None
            st.future.set_exception(CollectorError(f"could not finalise run {run.run_id}: {e}"))
            return
        self.stopping = self.run = None
        self.run_active = False
        self.gate = StreamGate(self.cfg.limits)  # stopping a run frees its streams
        self.publish_acks({a for a, _b, _s in self.tracker.streams})
        log.info("run %s stopped: %d readings", run.run_id, run.readings)
        self._notifier.status("idle: no run active")
        st.future.set_result(
            StopReply(
                run.run_id,
                str(run.dir.resolve()),
                run.readings,
                totals.gaps,
                totals.missing_batches,
                totals.lost_batches,
            )
        )
