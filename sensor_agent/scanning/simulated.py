"""Simulated backend: seeded beacons walking a path through a site, heard by the site's sensors.

RSSI follows the log-distance model ``tx_1m - 10 n log10(d) + N(0, sigma)``; each advert is lost
independently per sensor with ``drop_prob``, and cover events add attenuation and extra loss.
``generate()`` is pure (same seed, same t0 -> same readings); the backend only paces it in real time.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats.devices import Devices, SiteConfigError, read_dev
from bgt_core.motion import CoverEvent, PathModel, cover_at
from bgt_core.sites import site_dir
from bgt_core.wire import RSSI_MAX, RSSI_MIN, Reading
from sensor_agent.config import SimulatedConfig
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, Clocks, ScannerBackend

# Advert intervals are jittered by up to this fraction, like real beacons' random delay.
_JITTER = 0.2
# Below this distance the log model is meaningless (the beacon is at the antenna).
_MIN_DISTANCE_M = 0.1
_TICK_S = 0.05


@dataclass(frozen=True, slots=True)
class Sensor:
    mac: str
    position: tuple[float, float, float]
    alias: str = ""


@dataclass(frozen=True, slots=True)
class RadioModel:
    tx_1m: float = -59.0
    path_loss_exponent: float = 2.0
    sigma_db: float = 3.0
    drop_prob: float = 0.05
    floor_dbm: float = -100.0

    def mean_rssi(self, distance_m: float) -> float:
        d = max(distance_m, _MIN_DISTANCE_M)
        return self.tx_1m - 10.0 * self.path_loss_exponent * math.log10(d)


def load_site(site: str) -> Devices:
    """A built-in site by name, or a folder holding ``<folder name>.dev`` (or one .dev file)."""
    p = Path(site)
    try:
        if p.suffix == ".dev" and p.is_file():
            return read_dev(p)
        if p.is_dir():
            devs = sorted(p.glob("*.dev"))
            if len(devs) != 1:
                raise BackendError(f"{p}: expected exactly one .dev file, found {len(devs)}")
            return read_dev(devs[0])
        d = site_dir(site)
        return read_dev(d / f"{site}.dev")
    except FileNotFoundError:
        raise BackendError(
            f"simulated.site: no built-in site or .dev file named {site!r}"
        ) from None
    except SiteConfigError as e:
        raise BackendError(str(e)) from None


def pick_sensors(devices: Devices, wanted: Sequence[str]) -> tuple[Sensor, ...]:
    """The site's sensors, or those named (by MAC or alias) in ``wanted``, in the order given."""
    all_ = {mac: Sensor(mac, _xyz(d.position, mac), d.alias) for mac, d in devices.dongles.items()}
    if not wanted:
        return tuple(all_.values())
    by_alias = {s.alias: s for s in all_.values()}
    out = []
    for w in wanted:
        flat = w.replace(":", "").replace("-", "").lower()
        s = all_.get(flat) or by_alias.get(w)
        if s is None:
            raise BackendError(
                f"simulated.sensors: {w!r} is neither a sensor MAC nor an alias in the site's .dev"
            )
        out.append(s)
    return tuple(out)


def _xyz(pos: Sequence[float], mac: str) -> tuple[float, float, float]:
    if len(pos) != 3:
        raise BackendError(f"sensor {mac} has no [x, y, z] position in the site's .dev")
    return (float(pos[0]), float(pos[1]), float(pos[2]))


class Simulation:
    """Deterministic advert generator. Call ``generate(until_s)`` with increasing times."""

    def __init__(
        self,
        sensors: Sequence[Sensor],
        beacons: Sequence[str],
        path: PathModel,
        t0_ns: int,
        *,
        seed: int = 0,
        rate_hz: float = 10.0,
        radio: RadioModel | None = None,
        events: Sequence[CoverEvent] = (),
    ) -> None:
        if not sensors:
            raise BackendError("the simulation has no sensors")
        if not beacons:
            raise BackendError("the simulation has no beacons")
        self.sensors = tuple(sensors)
        self.beacons = tuple(beacons)
        self.path = path
        self.t0_ns = t0_ns
        self.rate_hz = rate_hz
        self.radio = radio or RadioModel()
        self.events = tuple(events)
        self._rng = random.Random(seed)
        # Several beacons share the path, spread evenly along it.
        self._phase = [i * path.period_s / len(self.beacons) for i in range(len(self.beacons))]
        self._next = [self._rng.uniform(0, 1 / rate_hz) for _ in self.beacons]

    def beacon_position(self, index: int, t_s: float) -> tuple[float, float, float]:
        return self.path.position_at(t_s + self._phase[index])

    def skip_to(self, t_s: float) -> None:
        """Start advertising at ``t_s`` instead of 0 (an agent started long after t0)."""
        interval = 1 / self.rate_hz
        self._next = [max(n, t_s + self._rng.uniform(0, interval)) for n in self._next]

    def generate(self, until_s: float) -> list[tuple[str, Reading]]:
        """Every (sensor MAC, reading) of adverts sent before ``until_s`` (seconds after t0)."""
        out: list[tuple[str, Reading]] = []
        rng, radio, interval = self._rng, self.radio, 1 / self.rate_hz
        while True:
            i = min(range(len(self.beacons)), key=self._next.__getitem__)
            t = self._next[i]
            if t >= until_s:
                return out
            self._next[i] = t + interval * (1 + rng.uniform(-_JITTER, _JITTER))
            pos = self.beacon_position(i, t)
            cover = cover_at(self.events, t)
            t_ns = self.t0_ns + round(t * 1e9)
            for s in self.sensors:
                # Draw every random number whether or not the advert survives, so that a
                # change of drop probability does not reshuffle the noise of other readings.
                lost = rng.random() < radio.drop_prob
                lost_cover = rng.random() < (cover.drop_prob if cover else 0.0)
                noise = rng.gauss(0.0, radio.sigma_db)
                if lost or lost_cover:
                    continue
                rssi = radio.mean_rssi(math.dist(pos, s.position)) + noise
                if cover is not None:
                    rssi -= cover.attenuation_db
                if rssi < radio.floor_dbm:
                    continue
                rssi_i = max(RSSI_MIN, min(RSSI_MAX, round(rssi)))
                out.append((s.mac, Reading(t_ns, self.beacons[i], rssi_i)))


def simulate_fleet(
    site: str,
    sensor_groups: Sequence[Sequence[str]],
    path: PathModel,
    t0_ns: int,
    *,
    seed: int,
    rate_hz: float = 10.0,
    radio: RadioModel | None = None,
    events: Sequence[CoverEvent] = (),
    start_s: float = -5.0,
) -> list[Simulation]:
    """One simulation per agent, each with its group of the site's sensors, in-process.

    Agent ``i`` draws from seed ``10 * seed + i`` and starts advertising at ``start_s`` (agents
    started before t0), as the demo's agents do; benches and tests use this to get the same
    readings without starting processes.
    """
    devices = load_site(site)
    sims = []
    for i, sensors in enumerate(sensor_groups):
        sim = Simulation(
            pick_sensors(devices, sensors),
            tuple(devices.beacons),
            path,
            t0_ns,
            seed=seed * 10 + i,
            rate_hz=rate_hz,
            radio=radio,
            events=events,
        )
        sim.skip_to(start_s)
        sims.append(sim)
    return sims


class SimulatedBackend(ScannerBackend):
    name = "simulated"

    def __init__(
        self,
        simulation_factory,
        sensors: Sequence[Sensor],
        clocks: Clocks | None = None,
        t0_ns: int | None = None,
    ) -> None:
        self._factory = simulation_factory  # t0_ns -> Simulation; t0 may be known only at start
        self._sensors = tuple(sensors)
        self.clocks = clocks or Clocks()
        self.t0_ns = t0_ns
        self.simulation: Simulation | None = None
        self._task: asyncio.Task[None] | None = None

    @classmethod
    def from_config(cls, cfg: SimulatedConfig, clocks: Clocks | None = None) -> SimulatedBackend:
        devices = load_site(cfg.site)
        sensors = pick_sensors(devices, cfg.sensors)
        beacons = cfg.beacons or tuple(devices.beacons) or ("e78f135624ce",)
        radio = RadioModel(
            cfg.tx_1m, cfg.path_loss_exponent, cfg.sigma_db, cfg.drop_prob, cfg.floor_dbm
        )

        def factory(t0_ns: int) -> Simulation:
            return Simulation(
                sensors,
                beacons,
                cfg.path,
                t0_ns,
                seed=cfg.seed,
                rate_hz=cfg.rate_hz,
                radio=radio,
                events=cfg.events,
            )

        t0 = None if cfg.t0 is None else round(cfg.t0 * 1e9)
        return cls(factory, sensors, clocks, t0)

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return tuple(
            AdapterInfo(s.alias or f"sim-{s.mac}", s.mac, "simulated", "simulated")
            for s in self._sensors
        )

    async def start(self, sink: AdvertSink) -> None:
        now_wall = self.clocks.wall_ns()
        t0 = self.t0_ns if self.t0_ns is not None else now_wall
        self.simulation = self._factory(t0)
        self._task = asyncio.create_task(self._run(sink, now_wall), name="simulated")

    async def _run(self, sink: AdvertSink, start_wall_ns: int) -> None:
        sim = self.simulation
        assert sim is not None
        # Simulated time runs with the wall clock: path time = (wall - t0).
        start_mono = self.clocks.mono_ns()
        offset_s = (start_wall_ns - sim.t0_ns) / 1e9
        sim.skip_to(offset_s)  # nothing "happened" before the agent started (t0 in the past)
        while True:
            await self.clocks.sleep(_TICK_S)
            mono = self.clocks.mono_ns()
            for mac, r in sim.generate(offset_s + (mono - start_mono) / 1e9):
                # The reading was "received" at its advert time; monotonic follows the same offset.
                sink(mac, Reading(r.t_ns, r.beacon, r.rssi, start_mono + (r.t_ns - start_wall_ns)))

    async def stop(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
