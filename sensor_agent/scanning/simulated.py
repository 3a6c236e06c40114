"""Simulated backend: seeded beacons walking a path through a site, heard by the site's sensors.

The radio model and the advert generator are :mod:`bgt_core.radio_sim` (the annotator's renderer
uses them too); this backend picks the site's sensors and paces the generator in real time.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Sequence
from pathlib import Path

from bgt_core.formats.devices import Devices, SiteConfigError, read_dev
from bgt_core.motion import CoverEvent, PathModel
from bgt_core.radio_sim import RadioModel, Sensor, Simulation
from bgt_core.sites import site_dir
from bgt_core.wire import Reading
from sensor_agent.config import SimulatedConfig
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, Clocks, ScannerBackend

_TICK_S = 0.05


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
        simulation_factory: Callable[[int], Simulation],
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
        if not sensors:
            raise BackendError(f"simulated.site {cfg.site!r}: the site's .dev lists no sensors")
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
