"""The running collector: a Zenoh router session, the data subscriber, the writer thread that owns
all run state, the control queryables, the acknowledgement publisher and agent bookkeeping.

Threads: Zenoh callbacks only decode and enqueue; one writer thread dedupes, formats and writes;
one control thread answers queries and asks agents for their status (blocking calls live there).
"""

from __future__ import annotations

import logging
import queue
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from ble_groundtruth import wire
from ble_groundtruth.zenoh_config import AclFileError, build_config, load_acl
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.ingest import (
    RawBatch,
    RejectCounter,
    StreamTracker,
    decode,
    format_rows,
    reject_reason,
)
from collector.store import RunWriter, iso_utc, list_runs, make_run_id

log = logging.getLogger(__name__)

COMMANDS = ("start", "stop", "status", "runs")
TICK_S = 0.2  # flush + ack period while data arrives
RATE_WINDOW_S = 5.0
RSSI_HISTORY = 40  # readings kept per sensor for the live sparkline


def zenoh_reason(err: Exception) -> str:
    """Zenoh's error text without the Rust source locations it appends ('... at /path/x.rs:61.')."""
    text = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", " ".join(str(err).split()))
    return text.replace("[", "").replace("]", "").strip()


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
    """Open with ``open()``, close with ``close()`` (which also ends an active run cleanly)."""

    def __init__(self, cfg: CollectorConfig, *, clock: Callable[[], int] = time.time_ns,
                 monotonic: Callable[[], float] = time.monotonic, drain_grace_s: float = 0.3,
                 drain_timeout_s: float = 3.0, status_timeout_s: float = 1.0) -> None:
        self.cfg = cfg
        self._clock = clock
        self._mono = monotonic
        self._drain_grace = drain_grace_s
        self._drain_timeout = drain_timeout_s
        self._status_timeout = status_timeout_s
        self.rejects = RejectCounter(monotonic)
        self._data: queue.SimpleQueue[RawBatch] = queue.SimpleQueue()
        self._cmds: queue.SimpleQueue[tuple[Callable[[], Any], Future]] = queue.SimpleQueue()
        self._ctl: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._closing = threading.Event()
        self._lock = threading.Lock()  # guards _alive and _agent_info (shared with callbacks)
        self._alive: dict[str, bool] = {}
        self._agent_info: dict[str, dict[str, Any]] = {}
        self._info_pending: set[str] = set()
        # Writer-thread state: nobody else touches these.
        self._tracker = StreamTracker()
        self._run: RunWriter | None = None
        self._stopping: _Stopping | None = None
        self._live: dict[tuple[str, str], SensorLive] = {}
        self._discarded = 0
        self._write_errors = 0
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
        try:
            self._session = zenoh.open(conf)
        except zenoh.ZError as e:
            raise CollectorError(f"cannot open the Zenoh router on {', '.join(self.cfg.listen)}: "
                                 f"{zenoh_reason(e)}") from None
        site, s = self.cfg.site, self._session
        self._threads = [threading.Thread(target=self._writer_loop, name="collector-writer", daemon=True),
                         threading.Thread(target=self._control_loop, name="collector-control", daemon=True)]
        for t in self._threads:
            t.start()
        self._decls.append(zext.declare_advanced_subscriber(
            s, wire.data_selector(site), self._on_sample,
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True)))
        self._decls.append(s.liveliness().declare_subscriber(
            wire.agent_token_selector(site), self._on_token, history=True))
        for cmd in COMMANDS:
            self._decls.append(s.declare_queryable(
                wire.collector_control_key(site, cmd), lambda q, c=cmd: self._ctl.put((c, q))))
        log.info("collector serving site %r on %s, data in %s", site, ", ".join(self.cfg.listen),
                 self.cfg.data_dir)
        for r in list_runs(self.cfg.data_dir):
            if r["stop"] is None:
                log.warning("run %s was never stopped (collector killed?); its files hold what "
                            "was fsynced before that", r["run_id"])
        return self

    def close(self) -> None:
        """End an active run (drained and finalised), then stop the threads and the session."""
        if self._session is None:
            return
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

    def __enter__(self) -> Collector:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- public API (also what the control queryables call) ---------------------------------------

    def start_run(self, name: str | None = None, timeout: float = 10.0) -> dict[str, Any]:
        self._refresh_agents()
        return self._call(lambda: self._do_start(name), timeout)

    def stop_run(self, *, reason: str = "requested", missing_ok: bool = False,
                 timeout: float = 60.0) -> dict[str, Any] | None:
        self._refresh_agents()
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

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            _site, agent, sensor = wire.parse_data_key(key)
            batch = decode(sample.payload.to_bytes())
            if batch.agent_id != agent or batch.sensor != sensor:
                self.rejects.reject("key_mismatch", key,
                                    f"batch of agent {batch.agent_id}, sensor {batch.sensor} on this key")
                return
        except wire.WireError as e:
            self.rejects.reject(reject_reason(e), key, str(e))
            return
        except Exception as e:  # noqa: BLE001 - a callback must not die on one bad sample
            self.rejects.reject("malformed", key, f"{type(e).__name__}: {e}")
            return
        self._data.put(batch)

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
        while not self._closing.is_set():
            try:
                cmd, arg = self._ctl.get(timeout=0.2)
            except queue.Empty:
                continue
            if cmd == "agent_info":
                self._fetch_agent_info(wire.agent_status_key(self.cfg.site, arg))
                with self._lock:
                    self._info_pending.discard(arg)
                continue
            self._answer(cmd, arg)

    def _answer(self, cmd: str, query: Any) -> None:
        try:
            req: dict[str, Any] = {}
            if query.payload is not None and query.payload.to_bytes().strip():
                req = wire.from_json(query.payload.to_bytes(), f"{cmd} request")
            if cmd == "start":
                reply = self.start_run(_request_name(req))
            elif cmd == "stop":
                reply = self.stop_run()
            elif cmd == "status":
                reply = self.status()
            else:
                reply = {"runs": self.runs()}
            reply = {"ok": True, **reply}
        except (CollectorError, wire.WireError) as e:
            reply = {"ok": False, "error": str(e)}
        except Exception as e:
            log.exception("control command %s failed", cmd)
            reply = {"ok": False, "error": f"internal error: {type(e).__name__}: {e}"}
        try:
            query.reply(wire.collector_control_key(self.cfg.site, cmd), wire.to_json(reply))
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
                try:
                    info = wire.from_json(reply.ok.payload.to_bytes(), "agent status")
                    agent = wire.check_id(info.get("agent_id"), "agent id")
                except wire.WireError as e:
                    log.warning("ignoring an agent status reply on %s: %s", reply.ok.key_expr, e)
                    continue
                with self._lock:
                    self._agent_info[agent] = info
        except Exception as e:  # noqa: BLE001 - agent status is best effort; the data path is not
            log.warning("could not query agent status on %s: %s", selector, e)

    # -- writer thread ------------------------------------------------------------------------------

    def _writer_loop(self) -> None:
        clocks = {"tick": self._mono(), "fsync": self._mono(), "reack": self._mono()}
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
        now = self._mono()
        if now - clocks["tick"] >= TICK_S or self._stopping is not None:
            clocks["tick"] = now
            moved: set[str] = set()
            if self._run is None:
                moved = self._tracker.mark_durable()
            else:
                try:
                    self._run.flush()
                    if now - clocks["fsync"] >= self.cfg.fsync_interval_s:
                        self._run.fsync()
                        clocks["fsync"] = now
                        moved = self._tracker.mark_durable()
                except OSError as e:  # e.g. disk full: keep the rows buffered, ack nothing
                    self._write_errors += 1
                    if now - clocks.get("write_error_log", -1e9) > 10:
                        clocks["write_error_log"] = now
                        log.error("cannot write run %s: %s (retrying; nothing is acknowledged "  # noqa: TRY400 - known condition, no traceback
                                  "until it works)", self._run.run_id, e)
            if now - clocks["reack"] >= 2.0:  # repeat acks now and then: an agent may have missed one
                clocks["reack"] = now
                with self._lock:
                    moved |= {a for a, alive in self._alive.items() if alive}
            self._publish_acks(moved)
            if self._stopping is not None:
                self._maybe_finish_stop(now)

    def _ingest_some(self) -> None:
        try:
            first = self._data.get(timeout=0.05)
        except queue.Empty:
            return
        batches = [first]
        try:
            for _ in range(5000):
                batches.append(self._data.get_nowait())
        except queue.Empty:
            pass
        now = self._mono()
        run, tracker, live = self._run, self._tracker, self._live
        for b in batches:
            new_stream = b.stream not in tracker.streams
            if not tracker.accept(b.stream, b.seq):
                continue
            if new_stream:
                self._want_agent_info(b.agent_id)
            if b.rows:
                sl = live.get((b.agent_id, b.sensor))
                if sl is None:
                    sl = live[(b.agent_id, b.sensor)] = SensorLive(b.agent_id)
                sl.add(now, b.rows)
                if run is not None:
                    run.append(b.agent_id, b.sensor, format_rows(b.sensor, b.rows), len(b.rows))
                else:
                    self._discarded += len(b.rows)

    def _want_agent_info(self, agent: str) -> None:
        with self._lock:
            if agent in self._agent_info or agent in self._info_pending:
                return
            self._info_pending.add(agent)
        self._ctl.put(("agent_info", agent))

    def _publish_acks(self, agents: set[str]) -> None:
        for agent in agents:
            msg = self._tracker.ack_message(agent)
            if msg is None or not msg["streams"]:
                continue
            try:
                self._session.put(wire.ack_key(self.cfg.site, agent), wire.to_json(msg))
            except Exception as e:  # noqa: BLE001 - the next tick retries
                log.warning("could not publish ack for %s: %s", agent, e)

    def _do_start(self, name: str | None) -> dict[str, Any]:
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
        self._run = RunWriter(self.cfg.data_dir, run_id, name or "", t_ns, meta)
        log.info("run %s started in %s", run_id, self._run.dir)
        return {"run_id": run_id, "run_dir": str(self._run.dir.resolve())}

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
                   and self._tracker.open_gaps() == 0)
        if not settled and waited < self._drain_timeout:
            return
        run = self._run
        self._stopping = self._run = None
        try:
            run.close()
            self._tracker.mark_durable()
            summary = self._finish_yaml(run, st.reason)
        except Exception as e:  # noqa: BLE001 - reported to the caller of stop
            st.future.set_exception(CollectorError(f"could not finalise run {run.run_id}: {e}"))
            return
        self._publish_acks({a for a, _b, _s in self._tracker.streams})
        log.info("run %s stopped: %d readings", run.run_id, run.readings)
        st.future.set_result({"run_id": run.run_id, "run_dir": str(run.dir.resolve()),
                              "readings": run.readings, **summary})

    def _finish_yaml(self, run: RunWriter, reason: str) -> dict[str, Any]:
        with self._lock:
            infos = {a: dict(i) for a, i in self._agent_info.items()}
        agents: dict[str, Any] = {}
        gaps_total = missing_total = 0
        for sensor, stats in sorted(run.sensors.items()):
            info = infos.get(stats.agent_id, {})
            a = agents.setdefault(stats.agent_id, {
                "hostname": info.get("hostname"), "version": info.get("version"),
                "backend": info.get("backend"), "boot_ids": [], "sensors": {}})
            adapter = next((ad for ad in info.get("adapters", []) if isinstance(ad, dict)
                            and str(ad.get("mac", "")).replace(":", "").lower() == sensor), {})
            gaps = missing = 0
            for (ag, boot, sn), ss in self._tracker.streams.items():
                if ag == stats.agent_id and sn == sensor:
                    gaps += ss.gaps
                    missing += self._tracker.missing((ag, boot, sn))
                    if boot not in a["boot_ids"]:
                        a["boot_ids"].append(boot)
            gaps_total += gaps
            missing_total += missing
            a["sensors"][sensor] = {"adapter": adapter.get("name"), "mac": sensor,
                                    "backend": adapter.get("backend", info.get("backend")),
                                    "mode": adapter.get("mode"), "readings": stats.readings,
                                    "batches": stats.batches, "gaps": gaps,
                                    "missing_batches": missing}
        extra = {"stopped_by": reason, "gaps": gaps_total, "missing_batches": missing_total,
                 "duplicates_dropped": self._tracker.duplicates,
                 "rejected_payloads": self.rejects.snapshot()}
        run.write_yaml(stop_ns=self._clock(), agents=agents, extra=extra)
        return {"gaps": gaps_total, "missing_batches": missing_total}

    def _do_status(self) -> dict[str, Any]:
        now = self._mono()
        with self._lock:
            alive = dict(self._alive)
        agents: dict[str, Any] = {a: {"alive": v, "sensors": {}} for a, v in alive.items()}
        for (agent, sensor), sl in sorted(self._live.items()):
            ag = agents.setdefault(agent, {"alive": alive.get(agent, False), "sensors": {}})
            ag["sensors"][sensor] = {"rate_hz": round(sl.rate(now), 2),
                                     "last_seen_age_s": round(now - sl.last_seen, 3),
                                     "last_rssi": sl.last_rssi, "readings": sl.readings,
                                     "recent_rssi": list(sl.rssi)}
        run = None
        if self._run is not None:
            r = self._run
            run = {"run_id": r.run_id, "name": r.name, "run_dir": str(r.dir.resolve()),
                   "start": iso_utc(r.start_ns), "readings": r.readings,
                   "sensors": len(r.sensors), "stopping": self._stopping is not None}
        return {"run": run, "agents": agents, "discarded_no_run": self._discarded,
                "duplicates_dropped": self._tracker.duplicates,
                "rejected_payloads": self.rejects.snapshot(), "queue": self._data.qsize(), "write_errors": self._write_errors}


def _request_name(req: dict[str, Any]) -> str | None:
    name = req.get("name")
    if name is not None and not isinstance(name, str):
        raise CollectorError("start: name must be a string or null")
    return name
