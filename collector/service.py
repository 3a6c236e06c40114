"""The running collector: a Zenoh router session with its declarations and threads, crash resume
of a run a killed collector left active, and the public API (start/stop/status/runs).

The work is done by parts with one job each: ``writer.Inbox`` and ``writer.Writer`` (the data
path and run state), ``control.Control`` (queries, agents, clocks) and ``summary`` (run.yaml and
status). Threads: Zenoh callbacks only decode and enqueue; one writer thread owns the run; one
control thread answers queries; one receive thread drains the data subscriber.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bgt_core import wire
from bgt_core.control_messages import StartRequest
from bgt_core.messages import ClockSample
from bgt_core.run_record import RunRecordError
from bgt_core.sdnotify import Notifier
from bgt_core.zenoh_config import AclFileError, build_config, load_acl, zenoh_reason
from collector.agents import AgentBook
from collector.config import CollectorConfig, descriptor_budget
from collector.control import COMMANDS, Control
from collector.errors import CollectorError
from collector.inbox import Inbox
from collector.ingest import StreamTracker
from collector.run_state import RunState
from collector.store import (
    STATE_FILE,
    FileWrite,
    RunWriter,
    find_active_state,
    list_runs,
    read_run_record,
)
from collector.summary import build_status
from collector.writer import (
    MAX_BUFFER_BYTES,
    QUARANTINE_MAX_BYTES,
    Resumed,
    Writer,
)

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

SUB_CHANNEL = 16  # samples Zenoh may hold for the receive thread (a FIFO: Zenoh waits when full)


def _stopped(run_dir: Path) -> bool:
    """Whether run.yaml says the run stopped (an unreadable one says not)."""
    try:
        return read_run_record(run_dir).stopped
    except RunRecordError:
        return False


def resume_state(
    run_dir: Path, state: dict[str, Any], *, write: FileWrite, open_files: int
) -> Resumed:
    """Reopen the run of ``run_dir`` from its state.json (files cut back to what it covers)."""
    where = run_dir / STATE_FILE
    rs = RunState.from_dict(state, str(where))
    if rs.run_id != run_dir.name:
        raise CollectorError(
            f"{where}: run_id {rs.run_id!r} is not its directory's "
            "name; move the file aside to start fresh"
        )
    try:
        tracker = StreamTracker.from_state(dict(rs.tracker), dict(rs.lost_base))
        run = RunWriter(
            run_dir.parent,
            run_dir.name,
            rs.name,
            rs.start_ns,
            dict(rs.meta),
            resume=rs,
            write=write,
            open_files=open_files,
        )
    except (KeyError, TypeError, ValueError, AttributeError) as e:  # WireError is a ValueError
        raise CollectorError(f"{where}: cannot resume the run: {e!r}") from None
    except OSError as e:
        raise CollectorError(f"cannot resume run {run_dir}: {e}") from None
    clock_log = {a: list(v) for a, v in rs.clock.items()}
    return Resumed(run, tracker, clock_log, rs.restarts + 1, rs.quarantined_bytes)


def find_unfinished_run(data_dir: Path, *, write: FileWrite, open_files: int) -> Resumed | None:
    """The newest run a killed collector left active (state.json active, run.yaml not stopped),
    reopened; older ones are only reported."""
    resumed: Resumed | None = None
    for run_dir, state in find_active_state(data_dir):
        if _stopped(run_dir):  # stopped, killed before state.json said so
            continue
        if resumed is not None:
            log.warning(
                "run %s was also left active; only the newest run (%s) is resumed",
                state.get("run_id"),
                resumed.run.run_id,
            )
            continue
        resumed = resume_state(run_dir, state, write=write, open_files=open_files)
    for r in list_runs(data_dir):
        if (
            r["stop"] is None
            and (resumed is None or r["run_id"] != resumed.run.run_id)
            and not (data_dir / str(r["run_id"]) / STATE_FILE).exists()
        ):
            log.warning(
                "run %s was never stopped and has no %s; its files hold what was "
                "fsynced before the collector died",
                r["run_id"],
                STATE_FILE,
            )
    return resumed


class Collector:
    """Open with ``open()``, close with ``close()`` (which also ends an active run cleanly).

    A run left active by a killed collector is resumed by ``open()`` on the same data directory:
    same run id and files (cut back to what state.json covers), same dedupe state.
    ``abandon()`` stops it the way a kill does (for crash tests and benches).
    """

    def __init__(
        self,
        cfg: CollectorConfig,
        *,
        clock: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
        drain_grace_s: float = 0.3,
        drain_timeout_s: float = 3.0,
        status_timeout_s: float = 1.0,
        max_buffer_bytes: int = MAX_BUFFER_BYTES,
        queue_bytes: int | None = None,
        quarantine_max_bytes: int = QUARANTINE_MAX_BYTES,
        notifier: Notifier | None = None,
        file_write: FileWrite = os.write,
    ) -> None:
        self.cfg = cfg
        self._mono = monotonic
        self._file_write = file_write
        self._notifier = notifier if notifier is not None else Notifier()
        lim = cfg.limits
        self._open_files = descriptor_budget(lim.open_files)
        self.agents = AgentBook()
        self.inbox = Inbox(
            queue_bytes=int(lim.queue_mb * 2**20) if queue_bytes is None else queue_bytes,
            clock=clock,
            monotonic=monotonic,
        )
        self.writer = Writer(
            cfg,
            self.inbox,
            self.agents,
            clock=clock,
            monotonic=monotonic,
            notifier=self._notifier,
            file_write=file_write,
            drain_grace_s=drain_grace_s,
            drain_timeout_s=drain_timeout_s,
            max_buffer_bytes=max_buffer_bytes,
            quarantine_max_bytes=quarantine_max_bytes,
            open_files=self._open_files,
        )
        self.control = Control(
            cfg,
            self.writer,
            self.inbox,
            self.agents,
            clock=clock,
            monotonic=monotonic,
            status_timeout_s=status_timeout_s,
        )
        self.writer.want_agent_info = self.control.want_agent_info
        self._resumed: str | None = None
        self._closing = threading.Event()
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self._threads: list[threading.Thread] = []

    # -- lifecycle ------------------------------------------------------------------------------

    def open(self) -> Collector:
        import zenoh

        acl_text = None
        if self.cfg.acl is not None:
            try:
                acl_text = load_acl(self.cfg.acl)
            except AclFileError as e:
                raise CollectorError(zenoh_reason(e)) from None
        conf = build_config(self.cfg.session_spec(acl_text))
        self._resume()
        try:
            s = zenoh.open(conf)
        except zenoh.ZError as e:
            self.writer.drop_run()
            raise CollectorError(
                f"cannot open the Zenoh router on {', '.join(self.cfg.listen)}: {zenoh_reason(e)}"
            ) from None
        self._session = self.control.session = s
        self.writer.publish = s.put
        self._closing.clear()
        self._threads = []
        self.writer.thread = self._start_thread(self.writer.loop, "writer", self._closing)
        self._start_thread(self.control.loop, "control", self._closing)
        self._declare(s)
        listen = ", ".join(self.cfg.listen)
        log.info(
            "collector serving site %r on %s, data in %s", self.cfg.site, listen, self.cfg.data_dir
        )
        self._notifier.ready(f"serving site {self.cfg.site} on {listen}")
        return self

    def _resume(self) -> None:
        """Adopt the run a killed collector left active, if any (before any data flows)."""
        resumed = find_unfinished_run(
            self.cfg.data_dir, write=self._file_write, open_files=self._open_files
        )
        if resumed is None:
            return
        self.writer.adopt(resumed)
        self._resumed = resumed.run.run_id
        log.warning(
            "resumed run %s after an unclean stop (restart %d): %d readings on disk",
            resumed.run.run_id,
            resumed.restarts,
            resumed.run.readings,
        )

    def _start_thread(self, target: Callable[..., None], name: str, *args: Any) -> threading.Thread:
        t = threading.Thread(target=target, args=args, name=f"collector-{name}", daemon=True)
        t.start()
        self._threads.append(t)
        return t

    def _declare(self, s: zenoh.Session) -> None:
        """The data subscriber (with its receive thread), the agents' liveliness subscriber and
        the control queryables."""
        import zenoh
        import zenoh.ext as zext

        site = self.cfg.site
        # A bounded FIFO instead of a callback: Zenoh's callback mode queues samples for the
        # Python thread without a bound; this way Zenoh waits (back-pressure) once 16 are pending.
        sub = zext.declare_advanced_subscriber(
            s,
            wire.data_selector(site),
            zenoh.handlers.FifoChannel(SUB_CHANNEL),
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(periodic_queries=None, heartbeat=True),
        )
        self._decls.append(sub)
        self._start_thread(self.inbox.receive_loop, "receive", sub.handler)
        self._decls.append(
            s.liveliness().declare_subscriber(
                wire.agent_token_selector(site), self.control.on_token, history=True
            )
        )
        for cmd in COMMANDS:
            self._decls.append(
                s.declare_queryable(
                    wire.collector_control_key(site, cmd),
                    functools.partial(self.control.on_query, cmd),
                )
            )

    @property
    def resumed_run(self) -> str | None:
        """The run id ``open()`` resumed after an unclean stop, if any."""
        return self._resumed

    def close(self) -> None:
        """End an active run (drained and finalised), then stop the threads and the session."""
        if self._session is None:
            return
        self._notifier.stopping("stopping: draining the active run")
        try:
            self.stop_run(reason="shutdown", missing_ok=True)
        except CollectorError as e:
            log.warning("while stopping the run at shutdown: %s", e)
        except TimeoutError:  # the writer never answered: still end the threads and the session
            log.error(  # noqa: TRY400 - one line, no traceback
                "the active run did not stop in time at shutdown; left unfinished, it is "
                "resumed at the next start"
            )
        finally:
            self._shut_down()
            self._notifier.close()

    def abandon(self) -> None:
        """Stop serving the way a killed process does: the session and threads end, the active
        run is left as it is on disk (not finalised, state.json still active, run.yaml without a
        stop). What a new collector on the same data directory resumes; for crash tests."""
        if self._session is None:
            return
        self._shut_down()

    def _shut_down(self) -> None:
        # Nothing is recorded past this point. Without this the writer may end (closing and
        # idle) while Zenoh still delivers samples: each then waited QUEUE_WAIT_S for room in a
        # queue nobody drains, a Zenoh thread stayed blocked on the full FIFO, and undeclare /
        # session close (which wait for it) or the process exit could hang.
        self.inbox.shutting.set()
        for d in self._decls:
            d.undeclare()
        self._decls.clear()
        self._closing.set()
        for t in self._threads:
            t.join(timeout=10)
        self._threads = []
        self.writer.publish = None
        self.control.session = None
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def __enter__(self) -> Collector:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- public API (also what the control queryables call) ---------------------------------------

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
        req = StartRequest(name, max_offset_ms, strict)
        return self.control.start_run(req, timeout).to_dict()

    def stop_run(
        self, *, reason: str = "requested", missing_ok: bool = False, timeout: float = 60.0
    ) -> dict[str, Any] | None:
        stopped = self.control.stop_run(reason=reason, missing_ok=missing_ok, timeout=timeout)
        return None if stopped is None else stopped.to_dict()

    def status(self, timeout: float = 10.0) -> dict[str, Any]:
        """The status reply as it goes on the wire (``control_messages.CollectorStatus.to_dict``)."""
        return self.control.status(timeout).to_dict()

    def status_now(self) -> dict[str, Any]:
        """The status reply built on the calling thread: for a collector that is not open."""
        if self._session is not None:
            raise CollectorError("status_now is for a collector that is not open; use status()")
        return build_status(self.writer.status_view(self._mono())).to_dict()

    def runs(self) -> list[dict[str, Any]]:
        return list_runs(self.cfg.data_dir)

    def measure_clocks(self) -> dict[str, ClockSample]:
        """One clock sample per live agent (see ``control.Control.measure_clocks``)."""
        return self.control.measure_clocks()

    def shared_sensors(self) -> dict[str, list[str]]:
        """Sensor MACs published by more than one agent since the collector started."""
        return self.writer.gate.shared_sensors()
