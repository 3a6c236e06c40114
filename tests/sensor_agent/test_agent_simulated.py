"""The path model and the simulated backend: determinism, RSSI vs distance, cover events."""

from __future__ import annotations

import asyncio
import math
import statistics

import pytest

from bgt_core.motion import CoverEvent, MotionError, PathModel, cover_at
from sensor_agent.config import SimulatedConfig
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import Clocks
from sensor_agent.scanning.simulated import (
    RadioModel,
    Sensor,
    SimulatedBackend,
    Simulation,
    load_site,
    pick_sensors,
)

T0 = 1_700_000_000_000_000_000
BEACON = "e78f135624ce"


def test_path_position_speed_and_dwell() -> None:
    p = PathModel(((0, 0, 1), (4, 0, 1), (4, 3, 2)), speed_mps=1.0, dwell_s=1.0)
    # segments: 4 m, sqrt(9+1) m, sqrt(16+9+1) m, plus 3 dwells of 1 s
    assert p.period_s == pytest.approx(3 + 4 + math.sqrt(10) + math.sqrt(26))
    assert p.position_at(0.5) == (0.0, 0.0, 1.0)  # dwelling at the first waypoint
    assert p.position_at(3.0) == pytest.approx((2.0, 0.0, 1.0))
    assert p.position_at(5.0) == pytest.approx((4.0, 0.0, 1.0))
    assert not p.is_moving(5.5)
    assert p.is_moving(3.0)
    assert p.direction_at(3.0) == pytest.approx((1.0, 0.0, 0.0))
    assert p.position_at(3.0 + p.period_s) == pytest.approx(p.position_at(3.0))  # loops


def test_default_path_stays_in_the_room_at_hand_height() -> None:
    p = PathModel()
    assert p.speed_mps == 0.4
    for i in range(400):
        x, y, z = p.position_at(i * p.period_s / 400)
        assert 0 < x < 20.66
        assert 0 < y < 17.64
        assert 1.2 <= z <= 1.9


def test_bad_paths_and_events() -> None:
    with pytest.raises(MotionError, match="at least 2 waypoints"):
        PathModel(((0, 0, 0),))
    with pytest.raises(MotionError, match="speed_mps must be > 0"):
        PathModel(((0, 0, 0), (1, 0, 0)), speed_mps=0)
    with pytest.raises(MotionError, match="drop_prob"):
        CoverEvent(0, 1, drop_prob=1.5)
    assert PathModel.from_dict(PathModel().to_dict()) == PathModel()


def test_cover_at_picks_the_strongest_active_event() -> None:
    a, b = CoverEvent(10, 5, 10.0), CoverEvent(12, 1, 30.0)
    assert cover_at([a, b], 9.9) is None
    assert cover_at([a, b], 11) is a
    assert cover_at([a, b], 12.5) is b
    assert cover_at([a, b], 15) is None


def still_path(x: float) -> PathModel:
    """A beacon that effectively stays at (x, 0, 1): a tiny loop walked very slowly."""
    return PathModel(((x, 0, 1), (x + 1e-6, 0, 1)), speed_mps=1e-9)


def test_same_seed_same_readings_and_chunking_does_not_matter() -> None:
    sensors = pick_sensors(load_site("tetam"), ())
    runs = []
    for chunks in ((30.0,), (0.05 * i for i in range(1, 601))):
        sim = Simulation(sensors, [BEACON], PathModel(), T0, seed=42)
        out = []
        for t in chunks:
            out += sim.generate(t)
        runs.append(out)
    assert runs[0] == runs[1]
    other = Simulation(sensors, [BEACON], PathModel(), T0, seed=43).generate(30.0)
    assert other != runs[0]
    # ~10 adverts/s per sensor, 5 % dropped, 12 sensors
    assert 0.8 * 3600 < len(runs[0]) < 3600
    assert all(T0 <= r.t_ns < T0 + 30 * 10**9 for _, r in runs[0])


def test_rssi_falls_with_distance() -> None:
    radio = RadioModel(
        tx_1m=-59, path_loss_exponent=2.0, sigma_db=3.0, drop_prob=0.0, floor_dbm=-127
    )
    near, far = Sensor("000000000001", (1, 0, 1)), Sensor("000000000002", (10, 0, 1))
    sim = Simulation([near, far], [BEACON], still_path(0.0), T0, seed=1, radio=radio)
    out = sim.generate(60.0)
    by = {m: [r.rssi for mac, r in out if mac == m] for m in (near.mac, far.mac)}
    # log-distance truth: -59 dBm at 1 m, -79 dBm at 10 m; the mean of ~600 samples is within 0.5 dB
    assert statistics.mean(by[near.mac]) == pytest.approx(-59, abs=0.5)
    assert statistics.mean(by[far.mac]) == pytest.approx(-79, abs=0.5)
    assert statistics.stdev(by[near.mac]) == pytest.approx(3.0, abs=0.4)


def test_cover_event_attenuates_and_drops() -> None:
    radio = RadioModel(sigma_db=1.0, drop_prob=0.0, floor_dbm=-127)
    s = Sensor("000000000001", (2, 0, 1))
    ev = CoverEvent(start_s=20, duration_s=20, attenuation_db=20, drop_prob=0.5)
    sim = Simulation([s], [BEACON], still_path(0.0), T0, seed=3, radio=radio, events=[ev])
    out = sim.generate(60.0)
    t = [(r.t_ns - T0) / 1e9 for _, r in out]
    during = [r.rssi for (_, r), ts in zip(out, t, strict=True) if 20 <= ts < 40]
    outside = [r.rssi for (_, r), ts in zip(out, t, strict=True) if not 20 <= ts < 40]
    assert statistics.mean(outside) - statistics.mean(during) == pytest.approx(20, abs=1.0)
    # 40 s uncovered at 10/s with no drops vs 20 s covered at 10/s with half dropped
    assert len(outside) == pytest.approx(400, rel=0.1)
    assert len(during) == pytest.approx(100, rel=0.25)


def test_pick_sensors_by_mac_or_alias() -> None:
    devices = load_site("tetam")
    got = pick_sensors(devices, ["sensor20", "00:00:00:00:01:01"])
    assert [s.mac for s in got] == ["b827eb917e19", "000000000101"]
    assert got[0].position == (7.25, 11.36, 1.22)
    with pytest.raises(BackendError, match="'sensor99' is neither"):
        pick_sensors(devices, ["sensor99"])
    with pytest.raises(BackendError, match="no built-in site"):
        load_site("atlantis")


def test_backend_paces_with_the_injected_clock() -> None:
    wall0, mono0 = T0 + 5 * 10**9, 10**9
    state = {"mono": mono0}

    async def sleep(s: float) -> None:
        state["mono"] += round(s * 1e9)
        await asyncio.sleep(0)  # let the test's loop look at the clock

    clocks = Clocks(
        wall_ns=lambda: wall0 + state["mono"] - mono0, mono_ns=lambda: state["mono"], sleep=sleep
    )
    cfg = SimulatedConfig(seed=5, sensors=("sensor10", "sensor30"), t0=T0 / 1e9, drop_prob=0.0)
    backend = SimulatedBackend.from_config(cfg, clocks)
    got = []

    async def main() -> None:
        await backend.start(lambda mac, r: got.append((mac, r)))
        while state["mono"] < mono0 + 3 * 10**9:  # noqa: ASYNC110 - the fake clock is the condition
            await asyncio.sleep(0)
        await backend.stop()

    asyncio.run(main())
    assert [a.mac for a in backend.adapters] == ["b827eb4521b4", "b827ebf7d096"]
    # t0 was 5 s before start: readings begin at path time 5 s, not 0
    ts = [(r.t_ns - T0) / 1e9 for _, r in got]
    assert 5.0 <= min(ts) < 5.2
    assert max(ts) < 8.05
    assert 50 <= len(got) <= 70  # 2 sensors x ~10/s x 3 s
    # readings carry the monotonic time matching their advert time
    assert all(r.mono_ns - mono0 == r.t_ns - wall0 for _, r in got)


def test_site_from_a_dev_file_or_folder(dataset_dir) -> None:
    by_file = load_site(str(dataset_dir / "cnf" / "tetam.dev"))
    by_dir = load_site(str(dataset_dir / "cnf"))
    assert len(by_file.dongles) == 12
    assert by_dir == by_file == load_site("tetam")
