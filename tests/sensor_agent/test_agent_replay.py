"""Replay backend with injected clocks: pacing, time shift, keep-time, speed 0, bad files."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from bgt_core.wire import Reading
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import Clocks
from sensor_agent.scanning.replay import ReplayBackend

T0 = 1_581_249_601_000_000_000
NOW = 1_800_000_000_123_456_789


class FakeTime:
    """Wall and monotonic clocks that only move when the code under test sleeps."""

    def __init__(self) -> None:
        self.mono = 5_000_000_000
        self.wall = NOW
        self.sleeps: list[float] = []

    def clocks(self) -> Clocks:
        return Clocks(wall_ns=lambda: self.wall, mono_ns=lambda: self.mono, sleep=self.sleep)

    async def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.mono += round(s * 1e9)
        self.wall += round(s * 1e9)


def write_mbd(path: Path, rows: list[tuple[int, str, str, int]], extra: str = "") -> Path:
    path.write_text(
        "".join(f"{t // 10**9}.{t % 10**9:09d},{s},{b},{r}{extra}\n" for t, s, b, r in rows)
    )
    return path


def play(
    paths: list[Path], ft: FakeTime, **kw
) -> tuple[ReplayBackend, list[tuple[int, str, Reading]]]:
    got: list[tuple[int, str, Reading]] = []
    backend = ReplayBackend(paths, clocks=ft.clocks(), **kw)

    async def main() -> None:
        await backend.start(lambda mac, r: got.append((ft.mono, mac, r)))
        await backend.wait_finished()
        await backend.stop()

    asyncio.run(main())
    return backend, got


@pytest.fixture
def two_files(tmp_path: Path) -> list[Path]:
    a = write_mbd(
        tmp_path / "a.mbd",
        [
            (T0, "aa0000000001", "e78f135624ce", -70),
            (T0 + 2_000_000_000, "aa0000000001", "e78f135624ce", -71),
        ],
        extra=",1.0,2.0,3.0",
    )  # track-file columns are ignored
    b = write_mbd(
        tmp_path / "b.mbd",
        [
            (T0 + 500_000_000, "aa0000000002", "e78f135624ce", -80),
            (T0 + 1_000_000_001, "aa0000000002", "e78f135624cf", -81),
        ],
    )
    return [a, b]


def test_pacing_and_time_shift(two_files: list[Path]) -> None:
    ft = FakeTime()
    start_mono = ft.mono
    backend, got = play(two_files, ft, speed=1.0)
    assert [a.mac for a in backend.adapters] == ["aa0000000001", "aa0000000002"]
    # merged in time order, each delivered when its recorded offset has elapsed
    assert [(m - start_mono, mac, r.rssi) for m, mac, r in got] == [
        (0, "aa0000000001", -70),
        (500_000_000, "aa0000000002", -80),
        (1_000_000_001, "aa0000000002", -81),
        (2_000_000_000, "aa0000000001", -71),
    ]
    # first row is "now", intervals kept to the nanosecond
    assert [r.t_ns - NOW for _, _, r in got] == [0, 500_000_000, 1_000_000_001, 2_000_000_000]
    assert [r.mono_ns for _, _, r in got] == [m for m, _, _ in got]
    assert got[2][2].beacon == "e78f135624cf"


def test_speed_scales_pacing_not_timestamps(two_files: list[Path]) -> None:
    ft = FakeTime()
    start_mono = ft.mono
    _, got = play(two_files, ft, speed=4.0)
    assert [m - start_mono for m, _, _ in got] == [0, 125_000_000, 250_000_000, 500_000_000]
    assert [r.t_ns - NOW for _, _, r in got] == [0, 500_000_000, 1_000_000_001, 2_000_000_000]


def test_keep_time_keeps_exact_timestamps(two_files: list[Path]) -> None:
    ft = FakeTime()
    _, got = play(two_files, ft, speed=1.0, keep_time=True)
    assert [r.t_ns for _, _, r in got] == [
        T0,
        T0 + 500_000_000,
        T0 + 1_000_000_001,
        T0 + 2_000_000_000,
    ]
    assert all(r.mono_ns == 0 for _, _, r in got)


def test_speed_zero_does_not_wait(tmp_path: Path) -> None:
    rows = [(T0 + i * 10**9, "aa0000000001", "e78f135624ce", -60) for i in range(1000)]
    ft = FakeTime()
    start = ft.mono
    backend, got = play([write_mbd(tmp_path / "x.mbd", rows)], ft, speed=0, yield_every=100)
    assert len(got) == 1000
    assert backend.rows_delivered == 1000
    assert ft.mono == start  # only zero-length yields to the loop
    assert ft.sleeps == [0] * 10


def test_bad_row_names_file_and_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.mbd"
    p.write_text("1581249601.1,aa0000000001,e78f135624ce,-70\n\n1581249601.2,aa0000000001,zz,-70\n")
    with pytest.raises(BackendError, match=r"bad\.mbd:3: not a MAC address: 'zz'"):
        ReplayBackend([p]).check()


def test_missing_file_and_implausible_keep_time(tmp_path: Path) -> None:
    with pytest.raises(BackendError, match="no such replay file"):
        ReplayBackend([tmp_path / "none.mbd"]).check()
    p = write_mbd(tmp_path / "old.mbd", [(12_000_000_000, "aa0000000001", "e78f135624ce", -70)])
    with pytest.raises(BackendError, match="not a plausible Unix time"):
        ReplayBackend([p], keep_time=True).check()
    ReplayBackend([p]).check()  # fine once shifted to now


def test_dense_rows_are_delivered_in_granules_with_exact_times(tmp_path: Path) -> None:
    # 200 rows 5 ms apart: the replay wakes every 20 ms, not for every row
    rows = [(T0 + i * 5_000_000, "aa0000000001", "e78f135624ce", -60) for i in range(200)]
    ft = FakeTime()
    start = ft.mono
    _, got = play([write_mbd(tmp_path / "d.mbd", rows)], ft, speed=1.0)
    assert len(ft.sleeps) <= 55
    assert [r.t_ns - NOW for _, _, r in got] == [i * 5_000_000 for i in range(200)]
    # monotonic stamp = scheduled reception; actual delivery at most one granule later
    assert [r.mono_ns - start for _, _, r in got] == [i * 5_000_000 for i in range(200)]
    assert all(0 <= m - r.mono_ns <= 20_000_000 for m, _, r in got)


def test_implausible_rssi_is_skipped_and_the_rest_replayed(dataset_dir: Path, caplog) -> None:
    # The published straight_05 track: sensor30 heard e78f135624ce at +42 dBm (and +29 dBm).
    f = dataset_dir / "trk" / "straight_05" / "sensor30_0.00_0.00_0.00.mbd"
    lines = [ln for ln in f.read_text().splitlines() if ln.strip()]
    backend = ReplayBackend([f], speed=0)
    backend.check()
    assert (backend.rows_total, backend.rows_skipped) == (len(lines) - 2, 2)
    assert any(
        "skipped 2 implausible reading(s) of sensor30_0.00_0.00_0.00.mbd (first: " in r.getMessage()
        and ":13: RSSI 42 dBm out of range" in r.getMessage()
        for r in caplog.records
    )
