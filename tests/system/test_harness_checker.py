"""The scenario checker itself: it must see every kind of loss, duplicate and damage it claims
to, or a green scenario would mean nothing. Fast; no processes."""

from __future__ import annotations

from pathlib import Path

from bgt_core import wire
from reliability_harness import beacon_macs, make_replay, sensor_macs, spool_batches, tally
from sensor_agent.spool import Spool


def _run_dir(tmp_path: Path, files: dict[str, str]) -> Path:
    (tmp_path / "rssi" / "pi-01").mkdir(parents=True)
    for sensor, text in files.items():
        (tmp_path / "rssi" / "pi-01" / f"{sensor}.mbd").write_text(text, encoding="utf-8")
    return tmp_path


def test_make_replay_rows_are_unique_and_match_the_files(tmp_path: Path) -> None:
    data = make_replay(
        tmp_path,
        sensors=sensor_macs(3),
        beacons=beacon_macs(4),
        rate_hz=10,
        duration_s=2.5,
        t0_ns=1_800_000_000 * 10**9,
    )
    assert len(data.rows) == 3 * 4 * 25
    lines = [ln for p in data.paths for ln in p.read_text().splitlines()]
    assert sorted(lines) == sorted(data.rows)
    assert data.first_ns == 1_800_000_000 * 10**9


def test_tally_counts_lost_duplicated_unexpected_and_torn(tmp_path: Path) -> None:
    s1, s2 = sensor_macs(2)
    rows = [f"1800000000.{i:09d},{s1},e78f13560000,-50" for i in range(5)]
    extra = f"1800000009.000000000,{s1},e78f13560000,-51"
    text = "\n".join([rows[0], rows[1], rows[1], rows[2], extra, rows[3]]) + "\n"
    # rows[4] is lost; rows[1] is there twice; one unexpected row; the other file ends torn
    run = _run_dir(tmp_path, {s1: text, s2: f"1800000001.0,{s2},e78f13560000,-5"})
    t = tally(run, rows, [s1, s2])
    assert (t.expected, t.recorded, t.lost, t.duplicated, t.unexpected, t.torn) == (
        5,
        6,
        1,
        1,
        1,
        1,
    )
    assert t.lost_examples == [rows[4]]
    assert not t.ok()
    # the same run is clean once the faults are accounted as allowed / not looked at
    t2 = tally(run, [*rows[:4], extra], [s1])
    assert (t2.lost, t2.duplicated, t2.unexpected, t2.torn) == (0, 1, 0, 0)


def test_tally_flags_rows_filed_under_the_wrong_sensor_and_garbage(tmp_path: Path) -> None:
    s1, s2 = sensor_macs(2)
    good = f"1800000000.000000001,{s1},e78f13560000,-50"
    run = _run_dir(tmp_path, {s1: f"{good}\nnot,a,row\n", s2: f"{good}\n"})
    t = tally(run, [good])
    assert (t.lost, t.duplicated, t.torn) == (0, 0, 2)


def test_spool_reader_reads_what_the_agent_spool_wrote(tmp_path: Path) -> None:
    sensor = sensor_macs(1)[0]
    written = []
    with Spool(tmp_path, 16 * 1024 * 1024) as sp:
        for seq in range(5):
            b = wire.Batch(
                "pi-01",
                "0123456789abcdef",
                sensor,
                seq,
                (wire.Reading(1_800_000_000 * 10**9 + seq, "e78f13560000", -60),),
            )
            payload = wire.to_wire(b)
            assert sp.append(f"0123456789abcdef/{sensor}", seq, payload)
            written.append((f"0123456789abcdef/{sensor}", seq, payload))
    assert spool_batches(tmp_path) == written
