"""Runs one agent: picks the backend, opens the Zenoh session, pumps readings into batches,
answers status queries, and on the end of a replay waits for the collector's acknowledgements.

The only place that knows the order of start-up and shut-down.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import signal
import socket
from collections import deque
from dataclasses import dataclass
from typing import Any

from ble_groundtruth import __version__
from ble_groundtruth.wire import Reading
from ble_groundtruth.zenoh_config import SessionSpec, build_config
from sensor_agent.config import AgentConfig, AllowList
from sensor_agent.errors import AckTimeout, AgentError, BackendError
from sensor_agent.scanning.base import AdapterInfo, Clocks, ScannerBackend

log = logging.getLogger(__name__)

RATE_WINDOW_S = 5  # adverts/s in the status is averaged over this many whole seconds
ACK_POLL_S = 0.02


def new_boot_id() -> str:
    """16 random hex digits, fresh for every process start."""
    return secrets.token_hex(8)


def make_backend(cfg: AgentConfig, clocks: Clocks) -> ScannerBackend:
    """The scanner backend the config asks for (bleak is imported only when chosen)."""
    if cfg.backend == "replay":
        from sensor_agent.scanning.replay import ReplayBackend

        if not cfg.replay.paths:
            raise BackendError("the replay backend needs files: give --replay PATH or replay.paths")
        return ReplayBackend(cfg.replay.paths, cfg.replay.speed, cfg.replay.keep_time, clocks)
    if cfg.backend == "simulated":
        from sensor_agent.scanning.simulated import SimulatedBackend

        return SimulatedBackend.from_config(cfg.simulated, clocks)
    if cfg.backend == "bleak":
        from sensor_agent.scanning.bleak_backend import BleakBackend

        return BleakBackend(cfg.adapters, cfg.scan_mode, clocks)
    raise BackendError(f"unknown backend {cfg.backend!r}")


def allowed(allow: AllowList, reading: Reading) -> bool:
    if allow.everything or reading.beacon in allow.macs:
        return True
    return reading.ibeacon is not None and reading.ibeacon.uuid in allow.ibeacon_uuids


class AdapterStats:
    """Counters for one adapter, updated from the event loop, read by the status queryable."""

    __slots__ = ("readings_total", "last_mono_ns", "_buckets")

    def __init__(self) -> None:
        self.readings_total = 0
        self.last_mono_ns: int | None = None
        self._buckets: deque[list[int]] = deque(maxlen=RATE_WINDOW_S + 1)  # [second, count]

    def record(self, mono_ns: int) -> None:
        self.readings_total += 1
        self.last_mono_ns = mono_ns
        sec = mono_ns // 1_000_000_000
        if self._buckets and self._buckets[-1][0] == sec:
            self._buckets[-1][1] += 1
        else:
            self._buckets.append([sec, 1])

    def rate(self, now_mono_ns: int) -> float:
        """Adverts per second over the last RATE_WINDOW_S complete seconds."""
        now_sec = now_mono_ns // 1_000_000_000
        lo = now_sec - RATE_WINDOW_S
        n = sum(c for s, c in list(self._buckets) if lo <= s < now_sec)
        return n / RATE_WINDOW_S


@dataclass(frozen=True, slots=True)
class RunResult:
    readings: int
    acknowledged: bool  # the collector acknowledged every batch (False: not waited for)


class Agent:
    """One running agent; ``run()`` returns when the source finishes or ``stop()`` is called."""

    def __init__(self, cfg: AgentConfig, backend: ScannerBackend, clocks: Clocks | None = None,
                 boot_id: str | None = None) -> None:
        self.cfg = cfg
        self.backend = backend
        self.clocks = clocks or Clocks()
        self.boot_id = boot_id or new_boot_id()
        self.stats: dict[str, AdapterStats] = {}
        self.started_ns = 0
        self.readings = 0
        self._stop = asyncio.Event()
        self._publisher: Any = None

    def stop(self) -> None:
        """Ask ``run()`` to stop (safe to call from a signal handler on the loop)."""
        self._stop.set()

    # -- the sink every backend feeds -------------------------------------------------------

    def _sink(self, adapter_mac: str, reading: Reading) -> None:
        if not allowed(self.cfg.allow, reading):
            return
        st = self.stats.get(adapter_mac)
        if st is None:
            st = self.stats[adapter_mac] = AdapterStats()
        st.record(reading.mono_ns or self.clocks.mono_ns())
        self.readings += 1
        self._publisher.add(adapter_mac, reading)

    def status(self) -> dict[str, Any]:
        """The status queryable's reply (see the agent/collector contract)."""
        now_mono = self.clocks.mono_ns()
        adapters = []
        for info in self.backend.adapters:
            st = self.stats.get(info.mac)
            adapters.append(_adapter_status(info, st, now_mono, self.backend.restarts(info.mac)))
        return {"agent_id": self.cfg.agent_id, "boot_id": self.boot_id, "version": __version__,
                "backend": self.cfg.backend, "hostname": socket.gethostname(),
                "started_ns": self.started_ns, "now_ns": self.clocks.wall_ns(),
                "adapters": adapters}

    # -- lifecycle --------------------------------------------------------------------------

    async def run(self, *, wait_ack: bool = True) -> RunResult:
        import zenoh

        from sensor_agent.publisher import Publisher

        cfg = self.cfg
        await asyncio.to_thread(self.backend.check)  # bad input fails before connecting
        spec = SessionSpec(mode="client", connect=tuple(cfg.connect), tls=cfg.tls)
        try:
            session = await asyncio.to_thread(zenoh.open, build_config(spec))
        except zenoh.ZError as e:
            # Zenoh appends the Rust source location after two spaces; the reason comes first.
            reason = str(e).splitlines()[0].split("  at ")[0].strip() if str(e) else ""
            raise AgentError(f"cannot open a Zenoh session to {', '.join(cfg.connect)}: "
                             f"{reason or 'connection failed'} (is the collector running?)"
                             ) from None
        acknowledged = False
        try:
            self.started_ns = self.clocks.wall_ns()
            self._publisher = Publisher(session, site=cfg.site, agent_id=cfg.agent_id,
                                        boot_id=self.boot_id, wall_ns=self.clocks.wall_ns,
                                        status=self.status)
            log.info("agent %s (boot %s) on %s, backend %s", cfg.agent_id, self.boot_id,
                     ", ".join(cfg.connect), cfg.backend)
            try:
                await self.backend.start(self._sink)
                for a in self.backend.adapters:
                    self.stats.setdefault(a.mac, AdapterStats())
                    log.info("adapter %s (%s) %s", a.name, a.mac, a.mode)
                finished = await self._pump()
            finally:
                await self.backend.stop()
                self._publisher.flush()  # whatever arrived before the stop still goes out
            if finished and wait_ack:
                await self._wait_acked(cfg.ack_timeout_s)
                acknowledged = True
        finally:
            if self._publisher is not None:
                self._publisher.close()
            await asyncio.to_thread(session.close)
        return RunResult(self.readings, acknowledged)

    async def _pump(self) -> bool:
        """Flush every batch_ms until the source finishes (True) or stop() (False)."""
        period = self.cfg.batch_ms / 1000
        done = asyncio.create_task(self.backend.wait_finished(), name="backend-finished")
        stop = asyncio.create_task(self._stop.wait(), name="stop")
        status_every = max(1, round(self.cfg.status_interval_s / period))
        ticks = 0
        try:
            while True:
                finished, _ = await asyncio.wait({done, stop}, timeout=period,
                                                 return_when=asyncio.FIRST_COMPLETED)
                self._publisher.flush()
                if done in finished:
                    done.result()  # re-raise what ended the source early
                    log.info("source finished after %d readings", self.readings)
                    return True
                if stop in finished:
                    return False
                ticks += 1
                if ticks % status_every == 0:
                    self._log_status()
        finally:
            for t in (done, stop):
                if not t.done():
                    t.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await t

    def _log_status(self) -> None:
        now = self.clocks.mono_ns()
        for mac, st in self.stats.items():
            log.info("adapter %s: %.1f adverts/s, %d readings", mac, st.rate(now), st.readings_total)

    async def _wait_acked(self, timeout_s: float) -> None:
        """Wait (bounded) until the collector acknowledged every published batch, else AckTimeout."""
        deadline = self.clocks.mono_ns() + int(timeout_s * 1e9)
        while True:
            pending = self._publisher.unacked()
            if not pending:
                log.info("every batch acknowledged by the collector")
                return
            if self.clocks.mono_ns() >= deadline or self._stop.is_set():
                missing = sum(p - a for p, a in pending.values())
                acked_any = bool(self._publisher.acked())
                hint = "" if acked_any else " (no acknowledgement at all: is a collector running?)"
                log.warning("%d batch(es) of %d stream(s) not acknowledged", missing, len(pending))
                raise AckTimeout(f"the collector did not acknowledge {missing} batch(es) of "
                                 f"{len(pending)} stream(s) within {timeout_s:g} s{hint}")
            await self.clocks.sleep(ACK_POLL_S)


def _adapter_status(info: AdapterInfo, st: AdapterStats | None, now_mono: int,
                    restarts: int) -> dict[str, Any]:
    last_age = None
    if st is not None and st.last_mono_ns is not None:
        last_age = round(max(0, now_mono - st.last_mono_ns) / 1e9, 3)
    return {"name": info.name, "mac": info.mac, "backend": info.backend, "mode": info.mode,
            "adverts_per_s": 0.0 if st is None else round(st.rate(now_mono), 2),
            "last_advert_age_s": last_age, "restarts": restarts,
            "readings_total": 0 if st is None else st.readings_total}


async def run_agent(cfg: AgentConfig, *, wait_ack: bool = True, clocks: Clocks | None = None,
                    handle_signals: bool = False) -> RunResult:
    """Build the backend and run an agent until its source ends or SIGINT/SIGTERM."""
    clocks = clocks or Clocks()
    agent = Agent(cfg, make_backend(cfg, clocks), clocks)
    if handle_signals:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, agent.stop)
    return await agent.run(wait_ack=wait_ack)
