"""The running collector: a Zenoh router session, the data subscriber, the writer thread that owns
all run state (files, state.json, dedupe, acks, quarantine), the control queryables, agent clock
checks and agent bookkeeping.

Threads: Zenoh callbacks only decode and enqueue; one writer thread dedupes, formats and writes;
one control thread answers queries and asks agents for their status and clock (blocking calls).
"""

from __future__ import annotations

import base64
import logging
import os
import queue
import re
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from importlib import metadata
from typing import Any

from ble_groundtruth import wire
from ble_groundtruth.sdnotify import Notifier
from ble_groundtruth.zenoh_config import AclFileError, build_config, load_acl
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.ingest import (
    SEQ_LIMIT,
    RawBatch,
    RejectCounter,
    StreamTracker,
    decode,
    format_rows,
    reject_reason,
)
from collector.store import (
    STATE_FILE,
    STATE_VERSION,
    FileWrite,
    RunWriter,
    find_active_state,
    is_disk_full,
    iso_utc,
    list_runs,
    make_run_id,
)

log = logging.getLogger(__name__)

COMMANDS = ("start", "stop", "status", "runs")
TICK_S = 0.2  # flush + ack period while data arrives
REACK_S = 2.0  # acks are repeated this often, in case an agent missed one
RATE_WINDOW_S = 5.0
RSSI_HISTORY = 40  # readings kept per sensor for the live sparkline
SUB_CHANNEL = 16  # samples Zenoh may hold for the receive thread (a FIFO: Zenoh waits when full)
ROW_COST = 192  # bytes of memory one decoded reading takes in the receive queue
BATCH_COST = 512
STATUS_MAX_STREAMS = 200  # streams listed in a status reply; the rest only counted
LIVE_IDLE_S = 3600.0  # live state of a stream silent this long is dropped
MAX_AGENT_ENTRIES = 1024  # agents remembered per counter (unknown agents, refused streams)
QUEUE_WAIT_S = 0.5  # a callback waits this long for room (back-pressure) before dropping unacked
FUTURE_LIMIT_NS = 24 * 3600 * 10**9  # readings further ahead than this are absurd
MAX_BUFFER_BYTES = 64 * 1024 * 1024  # rows held in memory while the disk refuses them
DISK_RETRY_S = 1.0
QUARANTINE_MAX_BYTES = 16 * 1024 * 1024  # per run; beyond it rejects are only counted
QUARANTINE_PAYLOAD = 4096  # bytes of each rejected payload kept (base64) in rejected.jsonl


def zenoh_reason(err: Exception) -> str:
    """Zenoh's error text without the Rust source locations it appends ('... at /path/x.rs:61.')."""
    text = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", " ".join(str(err).split()))
    return text.replace("[", "").replace("]", "").strip()


class ByteQueue:
    """FIFO bounded by the summed cost (bytes of memory) of its items, not their number. An item
    costlier than the whole bound is still let in when the queue is empty, so none is too big."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._items: deque[tuple[Any, int]] = deque()
        self.bytes = 0
        self._cond = threading.Condition()

    def put(self, item: Any, cost: int, timeout: float) -> bool:
        """Wait up to ``timeout`` for room; False if there was none."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._items and self.bytes + cost > self.max_bytes:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            self._items.append((item, cost))
            self.bytes += cost
            self._cond.notify_all()
            return True

    def get(self, timeout: float) -> Any:
        """The oldest item, waiting up to ``timeout``; None if there is none."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item, cost = self._items.popleft()
            self.bytes -= cost
            self._cond.notify_all()
            return item

    def qsize(self) -> int:
        return len(self._items)

    def empty(self) -> bool:
        return not self._items


def _check_folder_name(agent: str) -> None:
    if agent.startswith("."):  # would name a hidden folder (or ..) under rssi/
        raise wire.InvalidField(f"agent id {agent!r} may not start with a dot")


def batch_cost(batch: RawBatch) -> int:
    return BATCH_COST + ROW_COST * len(batch.rows)


def descriptor_budget(open_files: int) -> int:
    """Files the writer may hold open: the configured number, at most half the soft RLIMIT_NOFILE
    (Zenoh's sockets and the rest of the process need the other half)."""
    try:
        import resource

        soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (ImportError, OSError, ValueError):
        return open_files
    if soft == resource.RLIM_INFINITY:
        return open_files
    return max(4, min(open_files, soft // 2))


def software_version() -> str:
    try:
        return metadata.version("ble-groundtruth")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(slots=True)
class SensorLive:
    """What status/live show for one sensor (since the collector started)."""

    agent_id: str
    readings: int = 0
    last_rssi: int | None = None
    last_seen: float = 0.0  # monotonic seconds
    window: deque = field(default_factory=deque)  # (monotonic s, readings) over RATE_WINDOW_S
    rssi: deque = field(default_factory=lambda: deque(maxlen=RSSI_HISTORY))

    def add(self, now: float, rows: list[tuple[int, int, bytes, int]]) -> None:
        self.readings += len(rows)
        self.last_rssi = rows[-1][3]
        self.last_seen = now
        self.window.append((now, len(rows)))
        self.rssi.extend([r[3] for r in rows[-RSSI_HISTORY:]])
        self._prune(now)

    def _prune(self, now: float) -> None:
        while self.window and now - self.window[0][0] > RATE_WINDOW_S:
            self.window.popleft()

    def rate(self, now: float) -> float:
        self._prune(now)
        return sum(n for _, n in self.window) / RATE_WINDOW_S


@dataclass(slots=True)
class _Stopping:
    future: Future
    requested: float  # monotonic
    reason: str


class Collector:
    """Open with ``open()``, close with ``close()`` (which also ends an active run cleanly).

    A run left active by a killed collector is resumed by ``open()`` on the same data directory:
    same run id and files (cut back to what state.json covers), same dedupe state.
    """

    def __init__(self, cfg: CollectorConfig, *, clock: Callable[[], int] = time.time_ns,
                 monotonic: Callable[[], float] = time.monotonic, drain_grace_s: float = 0.3,
                 drain_timeout_s: float = 3.0, status_timeout_s: float = 1.0,
                 max_buffer_bytes: int = MAX_BUFFER_BYTES, queue_bytes: int | None = None,
                 quarantine_max_bytes: int = QUARANTINE_MAX_BYTES,
                 notifier: Notifier | None = None, file_write: FileWrite = os.write) -> None:
        self.cfg = cfg
        self._file_write = file_write  # tests inject a writer that fails like a full disk
        self._clock = clock
        self._mono = monotonic
        self._drain_grace = drain_grace_s
        self._drain_timeout = drain_timeout_s
        self._status_timeout = status_timeout_s
        self._max_buffer = max_buffer_bytes
        self._quarantine_max = quarantine_max_bytes
        self._notifier = notifier if notifier is not None else Notifier()
        self.rejects = RejectCounter(monotonic)
        lim = cfg.limits
        self._data = ByteQueue(int(lim.queue_mb * 2**20) if queue_bytes is None else queue_bytes)
        self._open_files = descriptor_budget(lim.open_files)
        # Streams (agent, sensor) accepted since this collector started; others are refused.
        self._admitted: set[tuple[str, str]] = set()
        self._agent_streams: Counter[str] = Counter()
        self._sensor_agents: dict[str, set[str]] = {}  # sensor MAC -> agents publishing it
        self._refused: Counter[str] = Counter()  # agent -> batches refused (stream caps)
        self._refused_streams: set[tuple[str, str]] = set()  # at most MAX_AGENT_ENTRIES kept
        self._refused_log: dict[str, float] = {}
        self._sub: Any = None
        self._quarantine: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=1000)
        self._cmds: queue.SimpleQueue[tuple[Callable[[], Any], Future]] = queue.SimpleQueue()
        self._ctl: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._closing = threading.Event()
        self._lock = threading.Lock()  # guards _alive, _agent_info and the overflow counter
        self._alive: dict[str, bool] = {}
        self._agent_info: dict[str, dict[str, Any]] = {}
        self._info_pending: set[str] = set()
        self._overflow = 0  # batches dropped (unacknowledged) because the queue stayed full
        self._overflow_log = -1e9
        self._run_active = False  # mirror of `_run is not None` for the control thread
        # Writer-thread state: nobody else touches these.
        self._tracker = StreamTracker()
        self._run: RunWriter | None = None
        self._stopping: _Stopping | None = None
        self._live: dict[tuple[str, str], SensorLive] = {}
        self._discarded = 0
        self._write_errors = 0
        self._write_failing = False  # the last write attempt failed (not for lack of space)
        self._deferred = 0  # batches refused unacked while rows piled up in memory (disk full)
        self._unknown_agents: dict[str, int] = {}
        self._recent: dict[str, float] = {}  # agent -> monotonic time of its last batch
        self._clock_log: dict[str, list[dict[str, Any]]] = {}
        self._restarts = 0
        self._resumed: str | None = None
        self._dirty = False  # something to persist since the last state.json
        self._quarantined_bytes = 0
        self._quarantine_dropped = 0
        self._session = None
        self._decls: list[Any] = []
        self._threads: list[threading.Thread] = []

    # -- lifecycle ------------------------------------------------------------------------------

    def open(self) -> Collector:
        import zenoh
        import zenoh.ext as zext

        acl_text = None
        if self.cfg.acl is not None:
            try:
                acl_text = load_acl(self.cfg.acl)
            except AclFileError as e:
                raise CollectorError(zenoh_reason(e)) from None
        conf = build_config(self.cfg.session_spec(acl_text))
        self._resume_unfinished_run()
        try:
            self._session = zenoh.open(conf)
        except zenoh.ZError as e:
            if self._run is not None:
                self._run.close()
                self._run = None
            raise CollectorError(f"cannot open the Zenoh router on {', '.join(self.cfg.listen)}: "
                                 f"{zenoh_reason(e)}") from None
        site, s = self.cfg.site, self._session
        self._threads = [threading.Thread(target=self._writer_loop, name="collector-writer", daemon=True),
                         threading.Thread(target=self._control_loop, name="collector-control", daemon=True)]
        for t in self._threads:
            t.start()
        # A bounded FIFO instead of a callback: Zenoh's callback mode queues samples for the
        # Python thread without a bound; this way Zenoh waits (back-pressure) once 16 are pending.
        self._sub = zext.declare_advanced_subscriber(
            s, wire.data_selector(site), zenoh.handlers.FifoChannel(SUB_CHANNEL),
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True))
        self._decls.append(self._sub)
        rx = threading.Thread(target=self._receive_loop, args=(self._sub.handler,),
                              name="collector-receive", daemon=True)
        rx.start()
        self._threads.append(rx)
        self._decls.append(s.liveliness().declare_subscriber(
            wire.agent_token_selector(site), self._on_token, history=True))
        for cmd in COMMANDS:
            self._decls.append(s.declare_queryable(
                wire.collector_control_key(site, cmd), lambda q, c=cmd: self._ctl.put((c, q))))
        log.info("collector serving site %r on %s, data in %s", site, ", ".join(self.cfg.listen),
                 self.cfg.data_dir)
        self._notifier.ready(f"serving site {site} on {', '.join(self.cfg.listen)}")
        return self

    @property
    def resumed_run(self) -> str | None:
        """The run id ``open()`` resumed after an unclean stop, if any."""
        return self._resumed

    def _resume_unfinished_run(self) -> None:
        """Continue the run a killed collector left active (state.json), before any data flows."""
        from ble_groundtruth.safe_yaml import YamlError, load_file

        active = find_active_state(self.cfg.data_dir)
        for run_dir, state in active:
            try:
                doc = load_file(run_dir / "run.yaml") or {}
            except YamlError:
                doc = {}
            if not isinstance(doc, dict):
                doc = {}
            if doc.get("stop") is not None:  # stopped, but killed before state.json said so
                continue
            if self._run is not None:
                log.warning("run %s was also left active; only the newest run (%s) is resumed",
                            state.get("run_id"), self._run.run_id)
                continue
            if state.get("version") != STATE_VERSION:
                raise CollectorError(
                    f"{run_dir / STATE_FILE}: version {state.get('version')} state of an unfinished run, "
                    f"written by an older collector (this one resumes version {STATE_VERSION}); finish "
                    "the run with that collector, or move the file aside to start fresh")
            if state.get("run_id") != run_dir.name:
                raise CollectorError(f"{run_dir / STATE_FILE}: run_id {state.get('run_id')!r} is not "
                                     "its directory's name; move the file aside to start fresh")
            try:
                tracker = StreamTracker.from_state(
                    state["tracker"], {k: int(v) for k, v in state.get("lost_base", {}).items()})
                run = RunWriter(self.cfg.data_dir, run_dir.name, state["name"],
                                int(state["start_ns"]), dict(state["meta"]), resume=state,
                                write=self._file_write, open_files=self._open_files)
            except (KeyError, TypeError, ValueError) as e:
                raise CollectorError(f"{run_dir / STATE_FILE}: cannot resume the run: {e!r}") from None
            except OSError as e:
                raise CollectorError(f"cannot resume run {run_dir}: {e}") from None
            self._run, self._tracker = run, tracker
            for a, _b, sn in tracker.streams:
                self._admit_known((a, sn))
            for key in run.sensors:
                self._admit_known(key)
            self._run_active = True
            self._resumed = run.run_id
            self._clock_log = {k: list(v) for k, v in state.get("clock", {}).items()}
            self._restarts = int(state.get("restarts", 0)) + 1
            self._quarantined_bytes = int(state.get("quarantined_bytes", 0))
            try:
                run.write_state(self._state())
            except OSError as e:  # the old state still matches the repaired files; go on
                log.warning("could not update %s: %s", run_dir / STATE_FILE, e)
            log.warning("resumed run %s after an unclean stop (restart %d): %d readings on disk",
                        run.run_id, self._restarts, run.readings)
        for r in list_runs(self.cfg.data_dir):
            if r["stop"] is None and (self._run is None or r["run_id"] != self._run.run_id) \
                    and not (self.cfg.data_dir / str(r["run_id"]) / STATE_FILE).exists():
                log.warning("run %s was never stopped and has no %s; its files hold what was "
                            "fsynced before the collector died", r["run_id"], STATE_FILE)

    def close(self) -> None:
        """End an active run (drained and finalised), then stop the threads and the session."""
        if self._session is None:
            return
        self._notifier.stopping("stopping: draining the active run")
        try:
            self.stop_run(reason="shutdown", missing_ok=True)
        except CollectorError as e:
            log.warning("while stopping the run at shutdown: %s", e)
        for d in self._decls:
            d.undeclare()
        self._decls.clear()
        self._closing.set()
        for t in self._threads:
            t.join(timeout=10)
        self._session.close()
        self._session = None
        self._notifier.close()

    def __enter__(self) -> Collector:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- public API (also what the control queryables call) ---------------------------------------

    def start_run(self, name: str | None = None, timeout: float = 10.0, *,
                  max_offset_ms: float | None = None, strict: bool = False) -> dict[str, Any]:
        """Start a run; agents' clocks are measured first. With ``strict``, an agent whose clock
        is off by more than ``max_offset_ms`` refuses the start (CollectorError)."""
        if self._run_active:  # answer at once, without asking the agents anything first
            return self._call(lambda: self._do_start(name, {}), timeout)
        self._refresh_agents()
        samples = self.measure_clocks()
        warnings = []
        if max_offset_ms is not None:
            for agent, smp in sorted(samples.items()):
                if abs(smp["offset_ms"]) > max_offset_ms:
                    warnings.append(f"agent {agent}: clock offset {smp['offset_ms']:+.1f} ms exceeds "
                                    f"{max_offset_ms:g} ms (round trip {smp['rtt_ms']:.1f} ms)")
        if strict and warnings:
            raise CollectorError(f"{warnings[0]}; fix its time sync (chrony) or start without --strict"
                                 + (f" ({len(warnings) - 1} more agents off)" if len(warnings) > 1 else ""))
        reply = self._call(lambda: self._do_start(name, samples), timeout)
        reply["clock"] = {a: {"offset_ms": v["offset_ms"], "rtt_ms": v["rtt_ms"]} for a, v in samples.items()}
        reply["clock_warnings"] = warnings
        return reply

    def stop_run(self, *, reason: str = "requested", missing_ok: bool = False,
                 timeout: float = 60.0) -> dict[str, Any] | None:
        self._refresh_agents()
        if self._run_active:
            samples = self.measure_clocks()
            if samples:
                self._call(lambda: self._add_clock(samples), timeout)
        fut: Future = Future()
        self._cmds.put((lambda: self._do_stop(fut, reason, missing_ok), Future()))
        return fut.result(timeout)

    def status(self, timeout: float = 10.0) -> dict[str, Any]:
        return self._call(self._do_status, timeout)

    def runs(self) -> list[dict[str, Any]]:
        return list_runs(self.cfg.data_dir)

    def _call(self, fn: Callable[[], Any], timeout: float) -> Any:
        fut: Future = Future()
        self._cmds.put((fn, fut))
        return fut.result(timeout)

    # -- Zenoh callbacks: cheap, never raise -------------------------------------------------------

    def _receive_loop(self, handler: Any) -> None:
        """Take samples from the subscriber's channel until it is undeclared."""
        while True:
            try:
                sample = handler.recv()
            except Exception:  # noqa: BLE001 - the channel is closed: the subscriber is gone
                return
            self._on_sample(sample)

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        payload = b""
        try:
            payload = sample.payload.to_bytes()
            _site, agent, sensor = wire.parse_data_key(key)
            _check_folder_name(agent)
            batch = decode(payload)
            # The key (which the ACL checks) says who sent it; the payload must agree.
            if batch.agent_id != agent or batch.sensor != sensor:
                self._reject("key_mismatch", key,
                             f"batch of agent {batch.agent_id}, sensor {batch.sensor} on this key", payload)
                return
            if batch.seq >= SEQ_LIMIT or batch.floor >= SEQ_LIMIT:
                self._reject("seq_out_of_range", key,
                             f"seq {batch.seq} / floor {batch.floor} not below 2^40", payload)
                return
        except wire.WireError as e:
            self._reject(reject_reason(e), key, str(e), payload)
            return
        except Exception as e:  # noqa: BLE001 - a callback must not die on one bad sample
            self._reject("malformed", key, f"{type(e).__name__}: {e}", payload)
            return
        if batch.skipped:
            # The rest of the batch is kept and acknowledged, so one absurd value (a scanner's
            # +42 dBm) neither costs the other readings nor makes the agent re-send forever.
            self._reject("bad_reading", key,
                         f"{batch.skipped} of {batch.skipped + len(batch.rows)} readings of seq "
                         f"{batch.seq} skipped ({batch.skip_reason})", payload, count=batch.skipped)
        batch = self._drop_future_readings(batch, key, payload)
        # Waiting here is the back-pressure: Zenoh (BLOCK congestion control) slows the senders.
        if not self._data.put(batch, batch_cost(batch), timeout=QUEUE_WAIT_S):
            # Not handled, so never acknowledged: the agent's spool sends it again later.
            now = self._mono()
            with self._lock:
                self._overflow += 1
                if now - self._overflow_log < 10:
                    return
                self._overflow_log = now
                n = self._overflow
            log.warning("receive queue full (%.0f MiB): dropped a batch of %s unacknowledged "
                        "(%d so far); the writer cannot keep up", self._data.max_bytes / 2**20, key, n)

    def _drop_future_readings(self, batch: RawBatch, key: str, payload: bytes) -> RawBatch:
        """Readings stamped more than FUTURE_LIMIT_NS ahead of our clock are quarantined, the
        rest of the batch is kept: the batch itself is still handled (and acknowledged), so a
        broken clock on one agent cannot stall its stream. Old timestamps are legitimate
        (``--replay-keep-time`` of a past recording), so only the future counts as absurd."""
        limit = self._clock() + FUTURE_LIMIT_NS
        if not batch.rows or max(r[0] for r in batch.rows) <= limit:
            return batch
        good = [r for r in batch.rows if r[0] <= limit]
        bad = len(batch.rows) - len(good)
        first = min(r[0] for r in batch.rows if r[0] > limit)
        self._reject("future_timestamp", key,
                     f"{bad} of {len(batch.rows)} readings of seq {batch.seq} stamped "
                     f"{wire.format_ts(first)}, more than a day ahead of the collector's clock",
                     payload, count=bad)
        return replace(batch, rows=good)

    def _reject(self, reason: str, key: str, message: str, payload: bytes, count: int = 1) -> None:
        """Count, log (rate-limited) and queue for <run>/rejected.jsonl; never raises."""
        self.rejects.reject(reason, key, message, count)
        rec = {"at_ns": self._clock(), "key": key, "reason": reason, "error": message,
               "size": len(payload),
               "payload_b64": base64.b64encode(payload[:QUARANTINE_PAYLOAD]).decode("ascii")}
        try:
            self._quarantine.put_nowait(rec)
        except queue.Full:
            with self._lock:
                self._quarantine_dropped += 1

    def _on_token(self, sample: Any) -> None:
        import zenoh

        agent = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            self._alive[agent] = alive
        log.info("agent %s %s", agent, "joined" if alive else "left")
        if alive:
            self._ctl.put(("agent_info", agent))

    # -- control thread ---------------------------------------------------------------------------

    def _control_loop(self) -> None:
        last_clock = self._mono()
        while not self._closing.is_set():
            if self._run_active and self._mono() - last_clock >= self.cfg.clock_interval_s:
                last_clock = self._mono()
                self._periodic_clock()
            try:
                cmd, arg = self._ctl.get(timeout=0.2)
            except queue.Empty:
                continue
            if cmd == "agent_info":
                self._fetch_agent_info(wire.agent_status_key(self.cfg.site, arg))
                with self._lock:
                    self._info_pending.discard(arg)
                continue
            if cmd == "start":
                last_clock = self._mono()
            self._answer(cmd, arg)

    def _periodic_clock(self) -> None:
        try:
            samples = self.measure_clocks()
            if samples:
                self._call(lambda: self._add_clock(samples), 10.0)
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
            if cmd == "start":
                max_off, strict = _request_clock_limits(req)
                reply = self.start_run(_request_name(req), max_offset_ms=max_off, strict=strict)
            elif cmd == "stop":
                reply = self.stop_run()
            elif cmd == "status":
                reply = self.status()
            else:
                reply = {"runs": self.runs()}
            reply = {"ok": True, **reply}
        except wire.WireError as e:
            self._reject("bad_request", key, str(e), raw)
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

    def _refresh_agents(self) -> None:
        """Ask every agent for its status (adapter names, backend, mode) for run.yaml."""
        if threading.current_thread() is self._threads[0]:
            return  # never block the writer
        self._fetch_agent_info(wire.agent_status_selector(self.cfg.site))

    def _fetch_agent_info(self, selector: str) -> None:
        try:
            replies = self._session.get(selector, timeout=self._status_timeout)
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
                    log.warning("agent %s's status reply names itself %r; credited to %s (the key)",
                                agent, claimed, agent)
                    info = {**info, "agent_id": agent}
                with self._lock:
                    self._agent_info[agent] = info
        except Exception as e:  # noqa: BLE001 - agent status is best effort; the data path is not
            log.warning("could not query agent status on %s: %s", selector, e)

    def measure_clocks(self) -> dict[str, dict[str, Any]]:
        """Four-timestamp exchange with every live agent (contract 4), one query per agent so
        each reply's arrival time t4 is its own.

        offset = ((t2 - t1) + (t3 - t4)) / 2 is how far the agent's clock is ahead of ours;
        rtt = (t4 - t1) - (t3 - t2) is the network round trip without the agent's own delay.
        """
        if self._session is None or (self._threads and threading.current_thread() is self._threads[0]):
            return {}
        with self._lock:
            agents = sorted(a for a, alive in self._alive.items() if alive)
        out: dict[str, dict[str, Any]] = {}
        for agent in agents:
            key = wire.agent_clock_key(self.cfg.site, agent)
            try:
                t1 = self._clock()
                replies = self._session.get(key, payload=wire.to_json({"t1": t1}),
                                            timeout=self._status_timeout)
                for reply in replies:
                    t4 = self._clock()
                    if reply.ok is None:
                        log.warning("agent %s refused the clock check: %s", agent,
                                    reply.err.payload.to_string()[:200])
                        break
                    msg = wire.from_json(reply.ok.payload.to_bytes(), "clock reply")
                    out[agent] = clock_sample(msg, t1, t4, iso_utc(t4))
                    break
            except wire.WireError as e:
                log.warning("ignoring the clock reply of agent %s: %s", agent, e)
            except Exception as e:  # noqa: BLE001 - clock health is advisory; never blocks a run
                log.warning("could not check the clock of agent %s: %s", agent, e)
        return out

    # -- writer thread ------------------------------------------------------------------------------

    def _writer_loop(self) -> None:
        now = self._mono()
        clocks = {"tick": now, "fsync": now, "reack": now, "watchdog": -1e9, "disk_retry": -1e9,
                  "write_error_log": -1e9}
        while True:
            try:
                self._writer_step(clocks)
            except Exception:
                # A bug must not silently stop ingest (futures would hang); log it and go on.
                log.exception("collector writer step failed")
            if self._closing.is_set() and self._data.empty() and self._cmds.empty():
                break

    def _writer_step(self, clocks: dict[str, float]) -> None:
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
        if now - clocks["tick"] >= TICK_S or self._stopping is not None:
            clocks["tick"] = now
            moved: set[str] = set()
            if self._run is None:
                moved = self._tracker.mark_durable()
            else:
                moved = self._persist(now, clocks)
            if now - clocks["reack"] >= REACK_S:  # repeat acks: an agent may have missed one
                clocks["reack"] = now
                with self._lock:
                    moved |= {a for a, alive in self._alive.items() if alive}
                # Also agents heard from lately whose token is missing or late.
                moved |= {a for a, t in self._recent.items() if now - t < 60}
                self._prune_live(now)
            self._publish_acks(moved)
            if self._stopping is not None:
                self._maybe_finish_stop(now)

    def _persist(self, now: float, clocks: dict[str, float]) -> set[str]:
        """Write buffered rows; at fsync time: fsync files, then state.json, then (and only then)
        move the ack watermarks. Disk full: roll back, keep rows in memory, retry, ack nothing."""
        run = self._run
        if ((run.disk_full or self._write_failing) and now - clocks["disk_retry"] < DISK_RETRY_S
                and self._stopping is None):
            return set()
        try:
            run.flush()
            self._write_failing = False
            due = now - clocks["fsync"] >= self.cfg.fsync_interval_s
            if (due and self._dirty) or run.disk_full or self._stopping is not None:
                run.fsync()
                run.write_state(self._state())
                self._dirty = False
                clocks["fsync"] = now
                if run.disk_full:
                    run.disk_full = False
                    log.warning("run %s: writing again, disk space is back (%d batches were "
                                "refused meanwhile; agents re-send them)", run.run_id, self._deferred)
                    self._notifier.status(f"recording run {run.run_id}")
                return self._tracker.mark_durable()
        except OSError as e:
            clocks["disk_retry"] = now
            if is_disk_full(e):
                if not run.disk_full:
                    run.disk_full = True
                    log.error("run %s: disk full (%s); stopped writing, holding up to %.1f MiB in "  # noqa: TRY400 - known condition
                              "memory unacknowledged and retrying every %.0f s", run.run_id, e.strerror,
                              self._max_buffer / 2**20, DISK_RETRY_S)
                    self._notifier.status(f"DISK FULL: run {run.run_id} is not being written")
            else:
                self._write_errors += 1
                self._write_failing = True
                if now - clocks["write_error_log"] > 10:
                    clocks["write_error_log"] = now
                    log.error("cannot write run %s: %s (retrying; nothing is acknowledged "  # noqa: TRY400 - known condition
                              "until it works)", run.run_id, e)
        return set()

    def _state(self) -> dict[str, Any]:
        return self._run.state({"tracker": self._tracker.to_state(), "lost_base": self._tracker.lost_base,
                                "clock": self._clock_log, "restarts": self._restarts,
                                "quarantined_bytes": self._quarantined_bytes})

    def _ingest_some(self) -> None:
        first = self._data.get(timeout=0.05)
        if first is None:
            return
        batches = [first]
        for _ in range(5000):
            b = self._data.get(timeout=0)
            if b is None:
                break
            batches.append(b)
        now = self._mono()
        run, tracker, live = self._run, self._tracker, self._live
        # While the disk refuses rows, memory holds them up to a bound; past it, batches are
        # refused before dedupe, so they stay unacknowledged and the agents send them again.
        # The memory bound applies only while writes fail; otherwise the next tick writes it all.
        capped = run is not None and (run.disk_full or self._write_failing)
        buffered = run.buffered if capped else 0
        with self._lock:
            alive = dict(self._alive)
        self._dirty = True  # even a duplicate may carry a higher floor
        admitted = self._admitted
        for b in batches:
            if (b.agent_id, b.sensor) not in admitted and not self._admit(b.agent_id, b.sensor, now):
                continue
            self._recent[b.agent_id] = now
            if capped and buffered >= self._max_buffer:
                self._deferred += 1
                continue
            new_stream = b.stream not in tracker.streams
            if not tracker.accept(b.stream, b.seq, b.floor):
                continue
            if new_stream:
                self._want_agent_info(b.agent_id)
            if not alive.get(b.agent_id):
                n = self._unknown_agents.get(b.agent_id, 0)
                if n == 0:
                    log.warning("data from agent %s, which has no liveliness token (not a running "
                                "agent of this site?); recorded and counted as unknown_agent", b.agent_id)
                if n or len(self._unknown_agents) < MAX_AGENT_ENTRIES:
                    self._unknown_agents[b.agent_id] = n + 1
            if b.rows:
                sl = live.get((b.agent_id, b.sensor))
                if sl is None:
                    sl = live[(b.agent_id, b.sensor)] = SensorLive(b.agent_id)
                sl.add(now, b.rows)
                if run is not None:
                    text = format_rows(b.sensor, b.rows)
                    run.append(b.agent_id, b.sensor, text, len(b.rows))
                    buffered += len(text) if capped else 0
                else:
                    self._discarded += len(b.rows)

    def _admit(self, agent: str, sensor: str, now: float) -> bool:
        """Accept a new (agent, sensor) stream under the stream caps, or refuse its batch (not
        written, not acknowledged, counted). Writer thread only."""
        lim = self.cfg.limits
        key = (agent, sensor)
        if self._agent_streams[agent] >= lim.streams_per_agent or len(self._admitted) >= lim.streams_total:
            if agent in self._refused or len(self._refused) < MAX_AGENT_ENTRIES:
                self._refused[agent] += 1
            else:
                self._refused["(other agents)"] += 1
            if len(self._refused_streams) < MAX_AGENT_ENTRIES:
                self._refused_streams.add(key)
            if now - self._refused_log.get(agent, -1e9) >= 60 and len(self._refused_log) < MAX_AGENT_ENTRIES:
                self._refused_log[agent] = now
                which = (f"agent {agent} already has {lim.streams_per_agent} streams"
                         if self._agent_streams[agent] >= lim.streams_per_agent
                         else f"the collector already has {lim.streams_total} streams")
                log.warning("refused sensor %s of agent %s: %s (limits.streams_per_agent / "
                            "streams_total); its batches are not written (%d refused so far)",
                            sensor, agent, which, self._refused[agent])
            return False
        self._admit_known(key)
        return True

    def _admit_known(self, key: tuple[str, str]) -> None:
        if key in self._admitted:
            return
        agent, sensor = key
        self._admitted.add(key)
        self._agent_streams[agent] += 1
        agents = self._sensor_agents.setdefault(sensor, set())
        agents.add(agent)
        if len(agents) > 1:
            log.warning("sensor %s is published by agents %s: kept as separate streams "
                        "(rssi/<agent>/%s.mbd); a copied adapter address or a misconfigured agent?",
                        sensor, ", ".join(sorted(agents)), sensor)

    def shared_sensors(self) -> dict[str, list[str]]:
        """Sensor MACs published by more than one agent since the collector started."""
        return {m: sorted(a) for m, a in sorted(self._sensor_agents.items()) if len(a) > 1}

    def _prune_live(self, now: float) -> None:
        for k in [k for k, sl in self._live.items() if now - sl.last_seen > LIVE_IDLE_S]:
            del self._live[k]
        for a in [a for a, t in self._recent.items() if now - t >= 60]:
            del self._recent[a]

    def _write_quarantine(self) -> None:
        recs = []
        try:
            while len(recs) < 1000:
                recs.append(self._quarantine.get_nowait())
        except queue.Empty:
            pass
        if not recs or self._run is None:
            return  # without a run, rejects are only counted
        lines = []
        for rec in recs:
            line = wire.to_json(rec) + b"\n"
            if self._quarantined_bytes + len(line) > self._quarantine_max:
                self._quarantine_dropped += 1
                continue
            self._quarantined_bytes += len(line)
            lines.append(line)
        if not lines:
            return
        try:
            with (self._run.dir / "rejected.jsonl").open("ab") as f:
                f.write(b"".join(lines))
        except OSError as e:
            self._quarantine_dropped += len(lines)
            log.warning("could not write %s/rejected.jsonl: %s", self._run.dir, e)

    def _want_agent_info(self, agent: str) -> None:
        with self._lock:
            if agent in self._agent_info or agent in self._info_pending:
                return
            self._info_pending.add(agent)
        self._ctl.put(("agent_info", agent))

    def _publish_acks(self, agents: set[str]) -> None:
        for agent in agents:
            for msg in self._tracker.ack_messages(agent):
                if not msg["streams"]:
                    continue
                try:
                    self._session.put(wire.ack_key(self.cfg.site, agent), wire.to_json(msg))
                except Exception as e:  # noqa: BLE001 - the next tick retries
                    log.warning("could not publish ack for %s: %s", agent, e)

    def _add_clock(self, samples: dict[str, dict[str, Any]]) -> None:
        if self._run is None:
            return
        for agent, smp in samples.items():
            self._clock_log.setdefault(agent, []).append(smp)
        self._dirty = True

    def _do_start(self, name: str | None, clock_samples: dict[str, dict[str, Any]]) -> dict[str, Any]:
        if self._run is not None:
            raise CollectorError(f"run {self._run.run_id} is already active; stop it first")
        t_ns = self._clock()
        run_id = make_run_id(t_ns, name)
        base = run_id
        for i in range(2, 100):
            if not (self.cfg.data_dir / run_id).exists():
                break
            run_id = f"{base}-{i}"
        meta = {"site": self.cfg.site, "software_version": software_version()}
        run = RunWriter(self.cfg.data_dir, run_id, name or "", t_ns, meta, write=self._file_write,
                        open_files=self._open_files)
        self._tracker.reset_run_totals()
        self._clock_log = {a: [smp] for a, smp in clock_samples.items()}
        self._restarts = self._quarantined_bytes = self._quarantine_dropped = 0
        self._deferred = 0
        self._write_failing = False
        self._run = run
        try:
            run.write_state(self._state())
        except OSError as e:
            self._run = None
            raise CollectorError(f"cannot write {run.dir / STATE_FILE}: {e.strerror or e}") from None
        self._run_active = True
        log.info("run %s started in %s", run_id, run.dir)
        self._notifier.status(f"recording run {run_id}")
        return {"run_id": run_id, "run_dir": str(run.dir.resolve())}

    def _do_stop(self, fut: Future, reason: str, missing_ok: bool) -> None:
        if self._run is None:
            if missing_ok:
                fut.set_result(None)
            else:
                fut.set_exception(CollectorError("no run is active"))
            return
        if self._stopping is not None:
            fut.set_exception(CollectorError(f"run {self._run.run_id} is already stopping"))
            return
        self._stopping = _Stopping(fut, self._mono(), reason)

    def _maybe_finish_stop(self, now: float) -> None:
        st = self._stopping
        waited = now - st.requested
        settled = (waited >= self._drain_grace and self._data.empty()
                   and self._tracker.open_gaps() == 0 and not self._run.disk_full)
        if not settled and waited < self._drain_timeout:
            return
        run = self._run
        if run.disk_full:
            st.future.set_exception(CollectorError(
                f"run {run.run_id}: the disk is full; free space and stop again (nothing was lost "
                f"so far: {run.buffered} bytes are held in memory)"))
            self._stopping = None
            return
        try:
            run.fsync()
            run.write_state(self._state())
            self._tracker.mark_durable()
            summary = self._finish_yaml(run, st.reason)
            state = self._state()
            state["active"] = False
            run.write_state(state)
            run.close()
        except Exception as e:  # noqa: BLE001 - reported to the caller of stop; the run stays active
            self._stopping = None
            st.future.set_exception(CollectorError(f"could not finalise run {run.run_id}: {e}"))
            return
        self._stopping = self._run = None
        self._run_active = False
        self._publish_acks({a for a, _b, _s in self._tracker.streams})
        log.info("run %s stopped: %d readings", run.run_id, run.readings)
        self._notifier.status("idle: no run active")
        st.future.set_result({"run_id": run.run_id, "run_dir": str(run.dir.resolve()),
                              "readings": run.readings, **summary})

    def _finish_yaml(self, run: RunWriter, reason: str) -> dict[str, Any]:
        with self._lock:
            infos = {a: dict(i) for a, i in self._agent_info.items()}
        agents: dict[str, Any] = {}
        gaps_total = missing_total = lost_total = 0
        per_stream = self._tracker.stream_totals()
        for (agent_id, sensor), stats in sorted(run.sensors.items()):
            info = infos.get(agent_id, {})
            a = agents.setdefault(agent_id, {
                "hostname": info.get("hostname"), "version": info.get("version"),
                "backend": info.get("backend"), "boot_ids": [], "sensors": {}})
            adapter = next((ad for ad in info.get("adapters", []) if isinstance(ad, dict)
                            and str(ad.get("mac", "")).replace(":", "").lower() == sensor), {})
            t = per_stream.get((agent_id, sensor))
            gaps, missing, lost = (t.gaps, t.missing, t.lost) if t else (0, 0, 0)
            for boot in (t.boots if t else ()):
                if boot not in a["boot_ids"]:
                    a["boot_ids"].append(boot)
            gaps_total += gaps
            missing_total += missing
            lost_total += lost
            a["sensors"][sensor] = {"adapter": adapter.get("name"), "mac": sensor,
                                    "file": f"rssi/{agent_id}/{sensor}.mbd",
                                    "backend": adapter.get("backend", info.get("backend")),
                                    "mode": adapter.get("mode"), "readings": stats.readings,
                                    "batches": stats.batches, "gaps": gaps,
                                    "missing_batches": missing, "lost_batches": lost}
        for agent, samples in self._clock_log.items():
            agents.setdefault(agent, {"hostname": infos.get(agent, {}).get("hostname"),
                                      "boot_ids": [], "sensors": {}})["clock"] = samples
        shared = run.shared_sensors()
        extra = {"layout": "rssi/<agent>/<sensor_mac>.mbd", "shared_sensors": shared,
                 "refused_streams": self._refused_summary(),
                 "stopped_by": reason, "gaps": gaps_total, "missing_batches": missing_total,
                 "lost_batches": lost_total, "duplicates_dropped": self._tracker.duplicates,
                 "rejected_payloads": self.rejects.snapshot(), "restarts": self._restarts}
        run.write_yaml(stop_ns=self._clock(), agents=agents, extra=extra)
        return {"gaps": gaps_total, "missing_batches": missing_total, "lost_batches": lost_total}

    def _do_status(self) -> dict[str, Any]:
        now = self._mono()
        with self._lock:
            alive = dict(self._alive)
            overflow = self._overflow
        agents: dict[str, Any] = {}
        for a, v in sorted(alive.items()):
            if len(agents) >= STATUS_MAX_STREAMS:
                break
            agents[a] = {"alive": v, "sensors": {}}
        # At most STATUS_MAX_STREAMS streams, the most recently heard first; the rest are counted.
        shown = sorted(self._live.items(), key=lambda kv: -kv[1].last_seen)[:STATUS_MAX_STREAMS]
        for (agent, sensor), sl in sorted(shown, key=lambda kv: kv[0]):
            ag = agents.setdefault(agent, {"alive": alive.get(agent, False), "sensors": {}})
            ag["sensors"][sensor] = {"rate_hz": round(sl.rate(now), 2),
                                     "last_seen_age_s": round(now - sl.last_seen, 3),
                                     "last_rssi": sl.last_rssi, "readings": sl.readings,
                                     "recent_rssi": list(sl.rssi)}
        run = None
        open_files = 0 if self._run is None else self._run.open_count
        if self._run is not None:
            r = self._run
            run = {"run_id": r.run_id, "name": r.name, "run_dir": str(r.dir.resolve()),
                   "start": iso_utc(r.start_ns), "readings": r.readings,
                   "sensors": len(r.sensors), "stopping": self._stopping is not None,
                   "restarts": self._restarts, "buffered_bytes": r.buffered,
                   "clock": {a: v[-1] for a, v in self._clock_log.items() if v}}
        return {"run": run, "agents": agents, "discarded_no_run": self._discarded,
                "duplicates_dropped": self._tracker.duplicates,
                "rejected_payloads": self.rejects.snapshot(), "queue": self._data.qsize(),
                "write_errors": self._write_errors,
                "disk_full": self._run is not None and self._run.disk_full,
                "deferred_batches": self._deferred, "queue_overflow": overflow,
                "unknown_agents": dict(Counter(self._unknown_agents).most_common(20)),
                "quarantine_dropped": self._quarantine_dropped,
                "streams": {"total": len(self._live), "shown": len(shown),
                            "admitted": len(self._admitted), "open_files": open_files},
                "refused_streams": self._refused_summary(),
                "shared_sensors": dict(list(self.shared_sensors().items())[:50]),
                "queue_bytes": self._data.bytes}

    def _refused_summary(self) -> dict[str, Any]:
        """Batches refused by the stream caps: total, streams, and the 20 worst agents."""
        return {"batches": sum(self._refused.values()), "streams": len(self._refused_streams),
                "by_agent": dict(self._refused.most_common(20))}


def clock_sample(msg: dict[str, Any], t1: int, t4: int, at: str) -> dict[str, Any]:
    """One clock measurement from an agent's reply (t1 echoed, t2, t3) and our t4, all Unix ns."""
    t2, t3 = msg.get("t2"), msg.get("t3")
    if msg.get("t1") != t1:
        raise wire.InvalidField("clock reply does not echo our t1")
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (t2, t3)):
        raise wire.InvalidField("clock reply needs integer t2 and t3 (ns)")
    chrony = msg.get("chrony")
    if chrony is not None and not isinstance(chrony, dict):
        raise wire.InvalidField("clock reply chrony must be an object or null")
    offset = ((t2 - t1) + (t3 - t4)) / 2
    rtt = (t4 - t1) - (t3 - t2)
    return {"at": at, "offset_ms": round(offset / 1e6, 3), "rtt_ms": round(rtt / 1e6, 3),
            "chrony": chrony}


def _request_name(req: dict[str, Any]) -> str | None:
    name = req.get("name")
    if name is not None and not isinstance(name, str):
        raise CollectorError("start: name must be a string or null")
    return name


def _request_clock_limits(req: dict[str, Any]) -> tuple[float | None, bool]:
    max_off, strict = req.get("max_offset_ms"), req.get("strict", False)
    if max_off is not None and (isinstance(max_off, bool) or not isinstance(max_off, int | float)
                                or max_off < 0):
        raise CollectorError("start: max_offset_ms must be a non-negative number or null")
    if not isinstance(strict, bool):
        raise CollectorError("start: strict must be true or false")
    return (None if max_off is None else float(max_off)), strict
