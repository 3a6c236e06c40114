"""`annotator simulate` writes the RSSI its walk gives (issue 30): a collector run the annotator
reads, with the site's sensors, about two readings per second each, RSSI falling with distance by
the log-distance model, and the hands-cover drop where the renderer covers the lenses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.io.rssi import load_rssi
from annotator.render.rssi import MARGIN_S, site_sensors, write_simulated_run
from annotator.render.trajectory import LoopTrajectory
from bgt_core.radio_sim import RadioModel
from bgt_core.safe_yaml import load_file

T0 = 1_700_000_000.0
DURATION = 60.0


def test_the_run_holds_the_walks_readings(tmp_path: Path) -> None:
    walk = LoopTrajectory(t0=T0)
    run = write_simulated_run(
        tmp_path / "run", walk, (T0, T0 + DURATION), covers=[(10.0, 2.0)], seed=3
    )
    sensors, beacon = site_sensors()
    assert run.beacon == beacon == "e78f135624ce"
    assert sorted(run.files) == sorted(s.mac for s in sensors)
    assert all(p.parent == tmp_path / "run" / "rssi" / "simulated" for p in run.files.values())
    table = load_rssi(tmp_path / "run")
    assert len(table) == run.readings
    info = load_file(tmp_path / "run" / "run.yaml")
    assert info["readings"] == run.readings
    assert info["agents"]["simulated"]["sensors"]["b827eb4521b4"]["adapter"] == "sensor10"
    # from MARGIN_S before the first frame to MARGIN_S after the last
    t = table.t_seconds()
    assert T0 - MARGIN_S <= t.min() < T0 - MARGIN_S + 1.0
    assert T0 + DURATION + MARGIN_S - 1.0 < t.max() <= T0 + DURATION + MARGIN_S
    # about 2 readings per second per sensor (2 adverts/s, 5 % lost), fewer while covered
    span = DURATION + 2 * MARGIN_S
    rate = len(table) / len(sensors) / span
    assert 1.7 < rate < 2.0
    covered = (t >= T0 + 10.1) & (t < T0 + 11.9)
    assert covered.sum() / len(sensors) / 1.8 < 1.0
    # the RSSI follows tx_1m - 10 n log10(d) + noise: fit n and tx over the uncovered readings
    pos, _ = walk(t)
    where = {s.mac: np.array(s.position) for s in sensors}
    d = np.linalg.norm(pos - np.array([where[s] for s in table.sensor]), axis=1)
    keep = ~covered
    slope, intercept = np.polyfit(np.log10(d[keep]), table.rssi[keep].astype(float), 1)
    radio = RadioModel()
    assert abs(-slope / 10 - radio.path_loss_exponent) < 0.15
    assert abs(intercept - radio.tx_1m) < 1.5
    # while covered the beacon is ~20 dB weaker
    residual = table.rssi - (radio.tx_1m - 10 * radio.path_loss_exponent * np.log10(d))
    assert -24 < np.median(residual[covered]) < -16
    assert abs(np.median(residual[keep])) < 1.0


def test_same_seed_same_readings(tmp_path: Path) -> None:
    walk = LoopTrajectory(t0=T0)
    a = write_simulated_run(tmp_path / "a", walk, (T0, T0 + 5), seed=1)
    b = write_simulated_run(tmp_path / "b", walk, (T0, T0 + 5), seed=1)
    c = write_simulated_run(tmp_path / "c", walk, (T0, T0 + 5), seed=2)
    mac = next(iter(a.files))
    assert a.files[mac].read_text() == b.files[mac].read_text()
    assert a.files[mac].read_text() != c.files[mac].read_text()


def test_receiver_mode_hears_every_site_beacon(tmp_path: Path) -> None:
    """The other direction (issue 36): beacons at the sensors' positions, one receiver on the
    bundle at its antenna; RSSI by the same model, every beacon dimmed while covered."""
    walk = LoopTrajectory(t0=T0)
    antenna = (0.0, 0.05, 0.10)
    run = write_simulated_run(
        tmp_path / "run",
        walk,
        (T0, T0 + DURATION),
        covers=[(10.0, 2.0)],
        seed=3,
        receiver="020000000001",
        receiver_antenna=antenna,
    )
    sensors, _ = site_sensors()
    assert run.receiver == "020000000001"
    assert run.beacon == ""
    assert sorted(run.beacons) == sorted(s.mac for s in sensors)
    assert list(run.files) == ["020000000001"]
    table = load_rssi(tmp_path / "run")
    assert set(table.sensor) == {"020000000001"}
    assert set(table.beacon) == set(run.beacons)
    info = load_file(tmp_path / "run" / "run.yaml")
    assert info["simulated"]["receiver"] == "020000000001"
    assert list(info["agents"]["simulated"]["sensors"]) == ["020000000001"]
    t = table.t_seconds()
    span = DURATION + 2 * MARGIN_S
    assert 1.7 < len(table) / len(sensors) / span < 2.0
    # the distance is from each beacon to the receiver's antenna, not to the bundle's origin
    pos, rot = walk(t)
    at = pos + rot.apply(np.array(antenna))
    where = {s.mac: np.array(s.position) for s in sensors}
    d = np.linalg.norm(at - np.array([where[b] for b in table.beacon]), axis=1)
    covered = (t >= T0 + 10.1) & (t < T0 + 11.9)
    radio = RadioModel()
    residual = table.rssi - (radio.tx_1m - 10 * radio.path_loss_exponent * np.log10(d))
    assert abs(np.median(residual[~covered])) < 1.0
    assert abs(np.std(residual[~covered]) - radio.sigma_db) < 0.3
    # every beacon is ~20 dB weaker while the hands cover the receiver (and 60 % more lost)
    assert -24 < np.median(residual[covered]) < -16
    assert len(set(table.beacon[covered])) >= 8
    assert covered.sum() / len(sensors) / 1.8 < 1.0
