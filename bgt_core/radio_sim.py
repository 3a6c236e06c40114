"""A simulated beacon heard by fixed sensors (or fixed beacons heard by a moving receiver): the
radio model and seeded advert generators.

Standard library only. The simulated sensor agent paces :class:`Simulation` in real time; the
annotator's renderer (``annotator simulate``) runs it at once to write the readings a rendered
walk would give. RSSI follows the log-distance model ``tx_1m - 10 n log10(d) + N(0, sigma)``;
each advert is lost independently per sensor with ``drop_prob``, and cover events add attenuation
and extra loss. ``generate()`` is pure: the same seed and t0 give the same readings.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from bgt_core.motion import CoverEvent, cover_at
from bgt_core.wire import RSSI_MAX, RSSI_MIN, Reading


class SimulationError(ValueError):
    """A simulation that cannot run (no sensors, no beacons)."""


class Track(Protocol):
    """Where the beacon is: a :class:`bgt_core.motion.PathModel` or any walk with these two."""

    @property
    def period_s(self) -> float: ...

    def position_at(self, t_s: float) -> tuple[float, float, float]: ...


# Advert intervals are jittered by up to this fraction, like real beacons' random delay.
_JITTER = 0.2
# Below this distance the log model is meaningless (the beacon is at the antenna).
_MIN_DISTANCE_M = 0.1


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


class Simulation:
    """Deterministic advert generator. Call ``generate(until_s)`` with increasing times."""

    def __init__(
        self,
        sensors: Sequence[Sensor],
        beacons: Sequence[str],
        path: Track,
        t0_ns: int,
        *,
        seed: int = 0,
        rate_hz: float = 10.0,
        radio: RadioModel | None = None,
        events: Sequence[CoverEvent] = (),
    ) -> None:
        if not sensors:
            raise SimulationError("the simulation has no sensors")
        if not beacons:
            raise SimulationError("the simulation has no beacons")
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
                rssi_i = _heard(rng, radio, cover, math.dist(pos, s.position))
                if rssi_i is not None:
                    out.append((s.mac, Reading(t_ns, self.beacons[i], rssi_i)))


def _heard(
    rng: random.Random, radio: RadioModel, cover: CoverEvent | None, distance_m: float
) -> int | None:
    """One advert at one receiver: its RSSI, or None when it is lost or below the floor.

    Every random number is drawn whether or not the advert survives, so that a change of drop
    probability does not reshuffle the noise of other readings."""
    lost = rng.random() < radio.drop_prob
    lost_cover = rng.random() < (cover.drop_prob if cover else 0.0)
    noise = rng.gauss(0.0, radio.sigma_db)
    if lost or lost_cover:
        return None
    rssi = radio.mean_rssi(distance_m) + noise
    if cover is not None:
        rssi -= cover.attenuation_db
    if rssi < radio.floor_dbm:
        return None
    return max(RSSI_MIN, min(RSSI_MAX, round(rssi)))


def receiver_readings(
    beacons: Sequence[Sensor],
    receiver: Track,
    t0_ns: int,
    until_s: float,
    *,
    seed: int = 0,
    rate_hz: float = 10.0,
    radio: RadioModel | None = None,
    events: Sequence[CoverEvent] = (),
) -> list[Reading]:
    """The other direction: fixed ``beacons`` (MAC and position) advertising at ``rate_hz`` each,
    heard by one receiver moving along ``receiver`` (a :class:`Track`) from 0 to ``until_s``
    seconds after ``t0_ns``. Cover events are hands over the receiver: every beacon is dimmed.
    Readings in time order; the same seed gives the same readings."""
    if not beacons:
        raise SimulationError("the simulation has no beacons")
    radio = radio or RadioModel()
    rng = random.Random(seed)
    interval = 1 / rate_hz
    nxt = [rng.uniform(0, interval) for _ in beacons]
    out: list[Reading] = []
    while True:
        i = min(range(len(beacons)), key=nxt.__getitem__)
        t = nxt[i]
        if t >= until_s:
            return out
        nxt[i] = t + interval * (1 + rng.uniform(-_JITTER, _JITTER))
        b = beacons[i]
        rssi = _heard(
            rng, radio, cover_at(events, t), math.dist(receiver.position_at(t), b.position)
        )
        if rssi is not None:
            out.append(Reading(t0_ns + round(t * 1e9), b.mac, rssi))
