"""The RSSI a rendered walk would give: the bundle's beacon heard by the site's fixed sensors, or
(receiver mode) beacons at the site's sensor positions heard by a receiver on the bundle.

`annotator simulate` writes these readings beside the videos, in the run layout the collector
writes (``run.yaml`` and ``rssi/<agent>/<sensor>.mbd``), so that `annotator run` and `evaluate`
work on any render. The radio is :mod:`bgt_core.radio_sim`'s (log-distance path loss, Gaussian
noise, independent losses, the hands-cover drop), the same model the simulated sensor agents of
the demo use; the beacon sits at the bundle's origin, as the rig's contract says.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bgt_core import __version__
from bgt_core.formats.devices import read_dev
from bgt_core.formats.mbd import format_row
from bgt_core.motion import CoverEvent
from bgt_core.radio_sim import RadioModel, Sensor, Simulation, receiver_readings
from bgt_core.run_record import AgentEntry, RunRecord, SensorEntry
from bgt_core.safe_yaml import dump
from bgt_core.sites import site_dir

PoseAt = Callable[[np.ndarray], tuple[np.ndarray, Rotation]]

# The one agent of a simulated run (a collector run has a folder per agent).
AGENT = "simulated"
# Hands take this long to close over the bundle (the renderer's ramp): the beacon counts as
# covered from the middle of the closing to the middle of the opening, as in the demo.
COVER_RAMP_S = 0.15
# The published dataset has about 2 readings per second per sensor.
DEFAULT_RATE_HZ = 2.0
# The readings start this long before the first frame and end this long after the last: the
# sensors run before and after the cameras, as in a real capture.
MARGIN_S = 2.0
# Positions are sampled this often along the walk and interpolated in between.
_SAMPLE_S = 0.01


# Receiver mode (`annotator simulate --receiver`): the receiver the bundle carries, and where
# its antenna sits in the bundle frame (x forward, z up): 10 cm above the beacon, 5 cm left.
RECEIVER_MAC = "dca632b0d1e5"
RECEIVER_ANTENNA = (0.0, 0.05, 0.10)


@dataclass(frozen=True)
class SimulatedRun:
    """What :func:`write_simulated_run` wrote."""

    run_dir: Path
    files: dict[str, Path]  # sensor MAC -> its .mbd file
    readings: int
    beacon: str  # the bundle's beacon; in receiver mode, empty
    receiver: str = ""  # receiver mode: the bundle's receiver
    beacons: tuple[str, ...] = ()  # receiver mode: the fixed beacons it hears


class _SampledWalk:
    """The position of a point of the bundle (``offset`` in the bundle frame; the origin, its
    beacon, by default) along ``pose_at``, sampled once and interpolated: the
    :class:`bgt_core.radio_sim.Track` a simulation asks at every advert."""

    def __init__(
        self,
        pose_at: PoseAt,
        t0: float,
        start_s: float,
        end_s: float,
        offset: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> None:
        self._t = np.arange(start_s, end_s + _SAMPLE_S, _SAMPLE_S)
        pos, rot = pose_at(t0 + self._t)
        self._pos = np.asarray(pos, float) + rot.apply(np.asarray(offset, float))

    @property
    def period_s(self) -> float:
        return float(self._t[-1] - self._t[0])

    def position_at(self, t_s: float) -> tuple[float, float, float]:
        p = [float(np.interp(t_s, self._t, self._pos[:, k])) for k in range(3)]
        return (p[0], p[1], p[2])


def cover_events(covers: Sequence[tuple[float, float]]) -> list[CoverEvent]:
    """The renderer's hands-cover events ((start, duration) s after the first frame) as the
    radio feels them: 20 dB weaker and 60 % of the adverts lost while covered."""
    return [
        CoverEvent(s + COVER_RAMP_S / 2, d, attenuation_db=20.0, drop_prob=0.6) for s, d in covers
    ]


def site_sensors(site: str = "tetam") -> tuple[tuple[Sensor, ...], str]:
    """The built-in site's fixed sensors (from its .dev) and its first beacon's MAC."""
    devices = read_dev(site_dir(site) / f"{site}.dev")
    sensors = tuple(
        Sensor(mac, (float(d.position[0]), float(d.position[1]), float(d.position[2])), d.alias)
        for mac, d in devices.dongles.items()
        if len(d.position) == 3
    )
    return sensors, next(iter(devices.beacons))


def write_simulated_run(
    run_dir: str | Path,
    pose_at: PoseAt,
    t_span: tuple[float, float],
    *,
    covers: Sequence[tuple[float, float]] = (),
    seed: int = 0,
    rate_hz: float = DEFAULT_RATE_HZ,
    radio: RadioModel | None = None,
    site: str = "tetam",
    receiver: str | None = None,
    receiver_antenna: Sequence[float] = RECEIVER_ANTENNA,
) -> SimulatedRun:
    """Simulate the bundle's beacon along ``pose_at`` from ``MARGIN_S`` before ``t_span[0]``
    to ``MARGIN_S`` after ``t_span[1]`` (Unix s) and write it as a collector run into
    ``run_dir``: ``run.yaml`` and ``rssi/simulated/<sensor>.mbd``. ``covers`` are the renderer's
    (start, duration) after ``t_span[0]``; ``rate_hz`` is the beacon's advertising rate (each
    advert heard by each sensor unless lost).

    With ``receiver`` (a MAC) the other direction is simulated: a beacon at each of the site's
    sensor positions (with that sensor's MAC), each advertising at ``rate_hz``, heard by the
    receiver at ``receiver_antenna`` (bundle frame) on the bundle; the covers dim every beacon.
    One file, ``rssi/simulated/<receiver>.mbd``."""
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= 100):
        raise ValueError(f"rate {rate_hz!r} Hz: expected a number in (0, 100]")
    t0, t1 = float(t_span[0]), float(t_span[1])
    sensors, beacon = site_sensors(site)
    # The simulation's own time 0 is where the readings start, MARGIN_S before the first frame.
    start, stop = t0 - MARGIN_S, t1 + MARGIN_S
    radio = radio or RadioModel()
    events = cover_events([(s + MARGIN_S, d) for s, d in covers])
    rows: dict[str, list[str]]
    if receiver is not None:
        walk = _SampledWalk(pose_at, start, 0.0, stop - start, receiver_antenna)
        heard = receiver_readings(
            sensors,
            walk,
            round(start * 1e9),
            stop - start,
            seed=seed,
            rate_hz=rate_hz,
            radio=radio,
            events=events,
        )
        rows = {receiver: [format_row(r.t_ns, receiver, r.beacon, r.rssi) for r in heard]}
        listening = [(receiver, "receiver")]
    else:
        walk = _SampledWalk(pose_at, start, 0.0, stop - start)
        sim = Simulation(
            sensors,
            (beacon,),
            walk,
            round(start * 1e9),
            seed=seed,
            rate_hz=rate_hz,
            radio=radio,
            events=events,
        )
        rows = {s.mac: [] for s in sensors}
        for mac, r in sim.generate(stop - start):
            rows[mac].append(format_row(r.t_ns, mac, r.beacon, r.rssi))
        listening = [(sn.mac, sn.alias) for sn in sensors]
    out = Path(run_dir)
    folder = out / "rssi" / AGENT
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for mac, lines in rows.items():
        files[mac] = folder / f"{mac}.mbd"
        files[mac].write_text("".join(lines), encoding="utf-8")
    n = sum(len(v) for v in rows.values())
    record = RunRecord(
        run_id="simulated",
        name="simulated",
        start_ns=round(start * 1e9),
        stop_ns=round(stop * 1e9),
        readings=n,
        meta={
            "site": site,
            "software_version": __version__,
            "simulated": {
                **(
                    {
                        "receiver": receiver,
                        "receiver_antenna": [float(v) for v in receiver_antenna],
                        "beacons": {b.mac: list(b.position) for b in sensors},
                    }
                    if receiver is not None
                    else {"beacon": beacon}
                ),
                "rate_hz": rate_hz,
                "seed": seed,
                "radio": {
                    "tx_1m": radio.tx_1m,
                    "path_loss_exponent": radio.path_loss_exponent,
                    "sigma_db": radio.sigma_db,
                    "drop_prob": radio.drop_prob,
                    "floor_dbm": radio.floor_dbm,
                },
                # seconds after the start of the readings, MARGIN_S before the first frame
                "covers": [e.to_dict() for e in events],
            },
        },
        summary={"layout": "rssi/<agent>/<sensor_mac>.mbd"},
        agents={
            AGENT: AgentEntry(
                backend="simulated",
                sensors={
                    mac: SensorEntry(
                        adapter=alias,
                        mac=mac,
                        file=f"rssi/{AGENT}/{mac}.mbd",
                        readings=len(rows[mac]),
                    )
                    for mac, alias in listening
                },
            )
        },
    )
    header = (
        "# Written by `annotator simulate --receiver`: the RSSI the site's fixed beacons give at "
        "the bundle's receiver.\n"
        if receiver is not None
        else "# Written by `annotator simulate`: the RSSI the rendered walk gives at the site's "
        "sensors.\n"
    )
    (out / "run.yaml").write_text(
        header + dump(record.to_dict(), sort_keys=False), encoding="utf-8"
    )
    if receiver is not None:
        return SimulatedRun(out, files, n, "", receiver, tuple(s.mac for s in sensors))
    return SimulatedRun(out, files, n, beacon)


def add_receiver(
    experiment: Path, mac: str = RECEIVER_MAC, antenna: Sequence[float] = RECEIVER_ANTENNA
) -> None:
    """Receiver mode for a rendered experiment: `receiver:` into experiment.yaml and the
    receiver's antenna into its rig.yaml, for the written files and the exact ones under true/
    (the antenna is written exact: a ruler measures it to a millimetre)."""
    antennas = {"antennas": {"receiver": [float(v) for v in antenna]}}
    for path in (experiment, experiment.parent / "true" / experiment.name):
        if not path.is_file():
            continue
        with path.open("a", encoding="utf-8") as f:
            f.write(f"receiver: '{mac}'  # the sensor on the bundle (receiver mode)\n")
        with (path.parent / "rig.yaml").open("a", encoding="utf-8") as f:
            f.write("# where the bundle's receiver sits in the bundle frame, m\n")
            f.write(dump(antennas, default_flow_style=None))
