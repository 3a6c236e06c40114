"""Runs one agent: picks the backend, opens the spool and the Zenoh session (retrying in the
background while the router is unreachable), pumps readings into batches, keeps re-sending what
is unacknowledged, tells systemd how it is doing, and on the end of a replay waits for the
collector's acknowledgements.

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
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bgt_core import __version__
from bgt_core.messages import AdapterStatus, AgentStatus
from bgt_core.sdnotify import Notifier
from bgt_core.wire import Reading, check_reading
from bgt_core.zenoh_config import SessionSpec, build_config, zenoh_reason
from sensor_agent.clockhealth import read_chrony
from sensor_agent.config import AgentConfig, AllowList
from sensor_agent.errors import AckTimeout, AgentError, BackendError
from sensor_agent.scanning.base import AdapterInfo, Clocks, ScannerBackend
from sensor_agent.spool import Spool

log = logging.getLogger(__name__)

RATE_WINDOW_S = 5  # adverts/s in the status is averaged over this many whole seconds
ACK_POLL_S = 0.02
HOUSEKEEPING_S = 0.5  # spool fsync and re-send checks run this often
CHRONY_REFRESH_S = 60.0
CONNECT_RETRY_MAX_S = 5.0
NO_ACK_WARN_S = 30.0  # connected, batches waiting, no acknowledgement for this long: say why
NO_ACK_REPEAT_S = 300.0
BAD_READING_LOG_S = 60.0  # at most one warning line about skipped readings per adapter per minute


def new_boot_id() -> str:
    """16 random hex digits, fresh for every process start."""
    return secrets.token_hex(8)


def make_backend(cfg: AgentConfig, clocks: Clocks) -> ScannerBackend:
    """The scanner backend the config asks for (bleak is imported only when chosen): ``auto``
    is the kernel's management socket, or bleak when the socket cannot be used."""
    if cfg.backend == "replay":
        from sensor_agent.scanning.replay import ReplayBackend

        if not cfg.replay.paths:
            raise BackendError("the replay backend needs files: give --replay PATH or replay.paths")
        return ReplayBackend(cfg.replay.paths, cfg.replay.speed, cfg.replay.keep_time, clocks)
    if cfg.backend == "simulated":
        from sensor_agent.scanning.simulated import SimulatedBackend

        return SimulatedBackend.from_config(cfg.simulated, clocks)
    if cfg.backend in ("bleak", "mgmt", "auto"):

        def bleak() -> ScannerBackend:
            from sensor_agent.scanning.bleak_backend import BleakBackend

            return BleakBackend(
                cfg.adapters,
                cfg.scan_mode,
                clocks,
                watchdog_silence_s=cfg.watchdog.silent_s,
                power_cycle_after=cfg.watchdog.power_cycle_after,
            )

        def mgmt() -> ScannerBackend:
            from sensor_agent.scanning.mgmt_backend import MgmtBackend

            return MgmtBackend(cfg.adapters, clocks)

        if cfg.backend == "auto":
            from sensor_agent.scanning.auto import AutoBackend

            return AutoBackend(mgmt, bleak)
        return bleak() if cfg.backend == "bleak" else mgmt()
    raise BackendError(f"unknown backend {cfg.backend!r}")


def allowed(allow: AllowList, reading: Reading) -> bool:
    if allow.everything or reading.beacon in allow.macs:
        return True
    return reading.ibeacon is not None and reading.ibeacon.uuid in allow.ibeacon_uuids


class AdapterStats:
    """Counters for one adapter, updated from the event loop, read by the status queryable."""

    __slots__ = ("readings_total", "last_mono_ns", "_buckets", "bad_readings", "bad_logged_ns")

    def __init__(self) -> None:
        self.readings_total = 0
        self.bad_readings = 0  # implausible readings skipped (RSSI, timestamp)
        self.bad_logged_ns: int | None = None
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

    def __init__(
        self,
        cfg: AgentConfig,
        backend: ScannerBackend,
        clocks: Clocks | None = None,
        boot_id: str | None = None,
        notifier: Notifier | None = None,
        resend_s: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.backend = backend
        self.clocks = clocks or Clocks()
        self.boot_id = boot_id or new_boot_id()
        self.stats: dict[str, AdapterStats] = {}
        self.started_ns = 0
        self.readings = 0
        self.bad_readings = 0
        self._stop = asyncio.Event()
        self._publisher: Any = None
        self._spool: Spool | None = None
        self._session: Any = None
        self._chrony: dict[str, Any] | None = None
        self.notifier = notifier or Notifier()
        self.resend_s = resend_s
        self.no_ack_warn_s = NO_ACK_WARN_S
        self._ack_wait_since: int | None = None
        self._ack_warned: int | None = None
        self.cert_cn = _cert_cn(cfg)

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
        why = check_reading(reading.t_ns, reading.rssi, reading.mono_ns)
        if why is not None:  # skipped one by one, counted and reported; the rest go on
            self._bad_reading(adapter_mac, st, reading, why)
            return
        st.record(reading.mono_ns or self.clocks.mono_ns())
        self.readings += 1
        self._publisher.add(adapter_mac, reading)

    def _bad_reading(self, adapter_mac: str, st: AdapterStats, reading: Reading, why: str) -> None:
        st.bad_readings += 1
        self.bad_readings += 1
        now = self.clocks.mono_ns()
        if st.bad_logged_ns is None or now - st.bad_logged_ns >= BAD_READING_LOG_S * 1e9:
            st.bad_logged_ns = now
            log.warning(
                "adapter %s: skipped an implausible reading of beacon %s (%s); %d skipped so far",
                adapter_mac,
                reading.beacon,
                why,
                st.bad_readings,
            )

    def status(self) -> dict[str, Any]:
        """The status queryable's reply (see the agent/collector contract)."""
        now_mono = self.clocks.mono_ns()
        adapters = tuple(
            _adapter_status(
                info,
                self.stats.get(info.mac),
                now_mono,
                self.backend.restarts(info.mac),
                self.backend.power_cycles(info.mac),
            )
            for info in self.backend.adapters
        )
        pub = self._publisher
        return AgentStatus(
            agent_id=self.cfg.agent_id,
            boot_id=self.boot_id,
            version=__version__,
            backend=self.cfg.backend,
            hostname=socket.gethostname(),
            started_ns=self.started_ns,
            now_ns=self.clocks.wall_ns(),
            adapters=adapters,
            spool=self.spool_status(),
            resent=0 if pub is None else pub.resent,
            chrony=self._chrony,
            bad_readings=self.bad_readings,
        ).to_dict()

    def spool_status(self) -> dict[str, Any] | None:
        """The spool's counters for the status reply; None when running without a spool."""
        if self._spool is None:
            return None
        st = self._spool.stats()
        return {
            "dir": st.directory,
            "bytes": st.bytes,
            "max_bytes": st.max_bytes,
            "records": st.records,
            "streams": st.streams,
            "dropped_oldest": st.dropped_oldest,
            "unspooled": st.unspooled,
            "disk_full": st.disk_full,
            "writing": st.writing,
            "last_error": st.last_error,
        }

    # -- lifecycle --------------------------------------------------------------------------

    async def run(self, *, wait_ack: bool = True) -> RunResult:
        from sensor_agent.publisher import RESEND_S, Publisher

        cfg = self.cfg
        await asyncio.to_thread(self.backend.check)  # bad input fails before connecting
        if cfg.tls is not None and self.cert_cn is not None and self.cert_cn != cfg.agent_id:
            log.warning(
                "agent id %r is not the CN %r of this agent's certificate (%s): the "
                "collector's ACL goes by the certificate's CN, so it will drop everything "
                "published as %r and nothing will be acknowledged; set agent_id: %s or "
                "install the certificate issued for %s",
                cfg.agent_id,
                self.cert_cn,
                cfg.tls.cert,
                cfg.agent_id,
                self.cert_cn,
                cfg.agent_id,
            )
        if cfg.spool.dir is not None:
            # fsync from the housekeeping timer (a worker thread), not inside append() on the loop
            self._spool = await asyncio.to_thread(
                Spool, cfg.spool.dir, cfg.spool.max_mb * 1024 * 1024, fsync_interval_s=None
            )
        acknowledged = False
        tasks: list[asyncio.Task[Any]] = []
        try:
            self.started_ns = self.clocks.wall_ns()
            self._publisher = Publisher(
                site=cfg.site,
                agent_id=cfg.agent_id,
                boot_id=self.boot_id,
                wall_ns=self.clocks.wall_ns,
                mono_ns=self.clocks.mono_ns,
                spool=self._spool,
                status=self.status,
                chrony=lambda: self._chrony,
                resend_s=RESEND_S if self.resend_s is None else self.resend_s,
                on_refused=cfg.spool.on_refused,
            )
            log.info(
                "agent %s (boot %s) on %s, backend %s, spool %s",
                cfg.agent_id,
                self.boot_id,
                ", ".join(cfg.connect),
                cfg.backend,
                "off" if cfg.spool.dir is None else cfg.spool.dir,
            )
            if not await self._try_open(first=True):
                tasks.append(asyncio.create_task(self._connect_loop(), name="zenoh-connect"))
            tasks += self._housekeeping_tasks()
            try:
                await self.backend.start(self._sink)
                for a in self.backend.adapters:
                    self.stats.setdefault(a.mac, AdapterStats())
                    log.info("adapter %s (%s) %s", a.name, a.mac, a.mode)
                self.notifier.ready(self._summary())
                finished = await self._pump()
            finally:
                await self.backend.stop()
                self._publisher.flush()  # whatever arrived before the stop still goes out
            if finished and wait_ack:
                await self._wait_acked(cfg.ack_timeout_s)
                acknowledged = True
        finally:
            self.notifier.stopping(f"stopping: {self.readings} readings")
            for t in tasks:
                t.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await t
            if self._publisher is not None:
                self._publisher.close()
            if self._spool is not None:
                await asyncio.to_thread(self._spool.close)
            if self._session is not None:
                await asyncio.to_thread(self._session.close)
            self.notifier.close()
        return RunResult(self.readings, acknowledged)

    async def _try_open(self, *, first: bool = False) -> bool:
        """Open the client session and attach the publisher; False while the router is
        unreachable (the caller retries). Other Zenoh errors (bad TLS files ...) are fatal."""
        import zenoh

        cfg = self.cfg
        spec = SessionSpec(mode="client", connect=tuple(cfg.connect), tls=cfg.tls)
        try:
            session = await asyncio.to_thread(zenoh.open, build_config(spec))
        except zenoh.ZError as e:
            reason = zenoh_reason(e)
            if "Unable to connect" in reason or "Timeout" in reason:
                if first:
                    log.warning(
                        "cannot reach the Zenoh router at %s yet (%s); recording "
                        "and retrying in the background",
                        ", ".join(cfg.connect),
                        reason,
                    )
                return False
            raise AgentError(
                f"cannot open a Zenoh session to {', '.join(cfg.connect)}: "
                f"{reason or 'connection failed'}"
            ) from None
        self._session = session
        self._publisher.attach(session)
        if not first:
            log.info("connected to the Zenoh router at %s", ", ".join(cfg.connect))
        return True

    async def _connect_loop(self) -> None:
        """Keep trying to open the session (backoff up to CONNECT_RETRY_MAX_S) until it opens.
        Once open, Zenoh's client reconnects by itself after an outage."""
        delay = 0.25
        while True:
            await self.clocks.sleep(delay)
            if await self._try_open():
                return
            delay = min(CONNECT_RETRY_MAX_S, delay * 2)

    async def _every(self, period_s: float, work: Callable[[], object]) -> None:
        """Run ``work()`` (blocking: in a worker thread), then sleep ``period_s``, forever."""
        while True:
            try:
                await asyncio.to_thread(work)
            except Exception:  # noqa: BLE001 - one failed round must not end re-sending for good
                log.exception(
                    "%s failed; trying again in %.1f s", getattr(work, "__name__", work), period_s
                )
            await self.clocks.sleep(period_s)

    async def _systemd(self) -> None:
        """WATCHDOG=1 at half of WatchdogSec= and a STATUS= line, from the event loop itself
        (so a stuck loop stops the pings). Its own task: a long re-send pass must not delay it."""
        notifier = self.notifier
        wd = notifier.watchdog_interval_s
        period = min(HOUSEKEEPING_S, wd) if wd is not None else HOUSEKEEPING_S
        next_status = 0
        while True:
            if wd is not None:
                notifier.watchdog()
            t = self.clocks.mono_ns()
            if t >= next_status:
                notifier.status(self._summary())
                next_status = t + int(self.cfg.status_interval_s * 1e9)
            await self.clocks.sleep(period)

    def _no_ack_cause(self) -> str:
        cfg = self.cfg
        if cfg.tls is not None and self.cert_cn is not None and self.cert_cn != cfg.agent_id:
            return (
                f"agent id {cfg.agent_id!r} differs from the certificate's CN {self.cert_cn!r}, "
                "and the collector's ACL drops what this certificate publishes under another id"
            )
        if cfg.tls is not None:
            return (
                f"the collector's ACL may not list agent {cfg.agent_id!r} (certificate CN "
                f"{self.cert_cn!r}), or the collector cannot write (see `collector status`)"
            )
        return f"is agent id {cfg.agent_id!r} published on the collector's site {cfg.site!r}?"

    def _watch_acks(self) -> None:
        """Connected to a router, batches waiting, and no acknowledgement for NO_ACK_WARN_S:
        our puts are being dropped somewhere. Say so at WARNING, with the likely cause."""
        pub = self._publisher
        now = self.clocks.mono_ns()
        if not pub.connected() or not pub.outstanding():
            self._ack_wait_since = None
            return
        if self._ack_wait_since is None:
            self._ack_wait_since = now
        waited = now - max(self._ack_wait_since, pub.last_ack_ns or 0)
        if waited < self.no_ack_warn_s * 1e9:
            return
        if self._ack_warned is not None and now - self._ack_warned < NO_ACK_REPEAT_S * 1e9:
            return
        self._ack_warned = now
        log.warning(
            "connected to %s, but no acknowledgement from the collector for %.0f s "
            "(%d stream(s) waiting): its puts are being dropped; likely cause: %s",
            ", ".join(self.cfg.connect),
            waited / 1e9,
            len(pub.outstanding()),
            self._no_ack_cause(),
        )

    def _refresh_chrony(self) -> None:
        self._chrony = read_chrony()

    def _housekeeping_tasks(self) -> list[asyncio.Task[Any]]:
        """Spool fsync, re-sends, chrony and systemd pings, each on its own period."""
        tasks = [
            asyncio.create_task(
                self._every(HOUSEKEEPING_S, self._publisher.resend_due), name="resend"
            ),
            asyncio.create_task(self._every(HOUSEKEEPING_S, self._watch_acks), name="ack-watch"),
            asyncio.create_task(self._every(CHRONY_REFRESH_S, self._refresh_chrony), name="chrony"),
        ]
        if self.notifier.enabled:
            tasks.append(asyncio.create_task(self._systemd(), name="systemd"))
        if self._spool is not None:
            tasks.append(
                asyncio.create_task(
                    self._every(HOUSEKEEPING_S, self._spool.sync), name="spool-sync"
                )
            )
        return tasks

    def _summary(self) -> str:
        """One line for systemd's STATUS=."""
        pub = self._publisher
        parts = [
            f"{self.readings} readings",
            f"{len(self.backend.adapters)} adapter(s)",
            "connected" if pub is not None and pub.connected() else "not connected",
        ]
        sp = self.spool_status()
        if sp is not None:
            parts.append(
                f"spool {sp['records']} unacked, {sp['bytes'] // 1024} KiB"
                + (", DISK FULL" if sp["disk_full"] else "")
            )
        return "; ".join(parts)

    async def _pump(self) -> bool:
        """Flush every batch_ms until the source finishes (True) or stop() (False)."""
        period = self.cfg.batch_ms / 1000
        done = asyncio.create_task(self.backend.wait_finished(), name="backend-finished")
        stop = asyncio.create_task(self._stop.wait(), name="stop")
        status_every = max(1, round(self.cfg.status_interval_s / period))
        ticks = 0
        try:
            while True:
                finished, _ = await asyncio.wait(
                    {done, stop}, timeout=period, return_when=asyncio.FIRST_COMPLETED
                )
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
            log.info(
                "adapter %s: %.1f adverts/s, %d readings", mac, st.rate(now), st.readings_total
            )

    async def _wait_acked(self, timeout_s: float) -> None:
        """Wait (bounded) until the collector acknowledged every published batch, else AckTimeout."""
        deadline = self.clocks.mono_ns() + int(timeout_s * 1e9)
        while True:
            pending = self._publisher.outstanding()
            if not pending:
                log.info("every batch acknowledged by the collector")
                return
            if self.clocks.mono_ns() >= deadline or self._stop.is_set():
                missing = sum(pending.values())
                acked_any = self._publisher.any_ack()
                hint = ""
                if not acked_any:
                    hint = (
                        f" (connected, but no acknowledgement at all: {self._no_ack_cause()})"
                        if self._publisher.connected()
                        else " (no acknowledgement at all: is a collector running?)"
                    )
                log.warning("%d batch(es) of %d stream(s) not acknowledged", missing, len(pending))
                raise AckTimeout(
                    f"the collector did not acknowledge {missing} batch(es) of "
                    f"{len(pending)} stream(s) within {timeout_s:g} s{hint}"
                )
            await self.clocks.sleep(ACK_POLL_S)


def _cert_cn(cfg: AgentConfig) -> str | None:
    """The CN of the agent's TLS certificate (what the collector's ACL sees), if it has one."""
    if cfg.tls is None:
        return None
    from bgt_core.certname import CertificateError, certificate_cn

    try:
        return certificate_cn(cfg.tls.cert)
    except (OSError, CertificateError) as e:
        log.warning("cannot read the CN of %s: %s", cfg.tls.cert, e)
        return None


def _adapter_status(
    info: AdapterInfo, st: AdapterStats | None, now_mono: int, restarts: int, power_cycles: int
) -> AdapterStatus:
    last_age = None
    if st is not None and st.last_mono_ns is not None:
        last_age = round(max(0, now_mono - st.last_mono_ns) / 1e9, 3)
    return AdapterStatus(
        name=info.name,
        mac=info.mac,
        backend=info.backend,
        mode=info.mode,
        adverts_per_s=0.0 if st is None else round(st.rate(now_mono), 2),
        last_advert_age_s=last_age,
        restarts=restarts,
        readings_total=0 if st is None else st.readings_total,
        bad_readings=0 if st is None else st.bad_readings,
        power_cycles=power_cycles,
    )


async def run_agent(
    cfg: AgentConfig,
    *,
    wait_ack: bool = True,
    clocks: Clocks | None = None,
    handle_signals: bool = False,
) -> RunResult:
    """Build the backend and run an agent until its source ends or SIGINT/SIGTERM."""
    clocks = clocks or Clocks()
    agent = Agent(cfg, make_backend(cfg, clocks), clocks)
    if handle_signals:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, agent.stop)
    return await agent.run(wait_ack=wait_ack)
