"""RSSI loading and the annotated outputs: write, read back with the mbd reader, compare."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.labeling import label_readings
from annotator.core.trajectory import Trajectory
from annotator.errors import ConfigError, NoDataError
from annotator.io.outputs import write_annotated_mbd, write_parquet, write_report
from annotator.io.rssi import bundle_beacon, load_rssi
from annotator.plots.run import (
    builtin_site_for,
    load_site,
    plot_rssi_on_trajectory,
    plot_rssi_time,
    plot_trajectory_map,
)
from bgt_core.formats.markers import read_marker_map
from bgt_core.formats.mbd import MbdError, format_row, iter_rows
from bgt_core.sites import site_dir
from bgt_core.wire import format_ts

BEACON = "e78f135624ce"
SENSORS = ["b827eb4521b4", "000000000101", "000000000202"]
T0_NS = 1_700_000_000_123_456_789


def write_run(run: Path, rng: np.random.Generator, n: int = 300, duration_s: float = 10.0) -> None:
    """A collector-style run dir: rssi/<sensor>.mbd with odd-nanosecond timestamps + run.yaml."""
    (run / "rssi").mkdir(parents=True)
    (run / "run.yaml").write_text("site: tetam\nrun: test\n", encoding="utf-8")
    for s in SENSORS:
        t = np.sort(T0_NS + rng.integers(0, int(duration_s * 1e9), n))
        rssi = rng.integers(-95, -50, n)
        (run / "rssi" / f"{s}.mbd").write_text(
            "".join(format_row(int(a), s, BEACON, int(r)) for a, r in zip(t, rssi, strict=True)),
            encoding="utf-8",
        )


def make_poses(t0_s: float, n: int = 200, dt: float = 0.04) -> Trajectory:
    t = t0_s + np.arange(n) * dt
    p = np.column_stack([2 + 0.4 * (t - t0_s), 3 + np.sin(t - t0_s), np.full(n, 1.6)])
    p[80:110] = np.nan  # a 1.2 s tracking gap
    r = Rotation.from_euler("z", 0.5 * (t - t0_s)[:, None])
    return Trajectory.from_rotation(
        t, p, r, {"sigma_m": np.full(n, 0.004), "markers": np.full(n, 3)}
    )


def test_load_run_dir_and_plain_folder(tmp_path: Path) -> None:
    write_run(tmp_path / "run", np.random.default_rng(0))
    table = load_rssi(tmp_path / "run")
    assert len(table) == 3 * 300
    assert (np.diff(table.t_ns) >= 0).all()
    assert table.run_info is not None
    assert table.run_info.run_id == "run"  # the directory's name: the file states no id
    assert dict(table.run_info.meta) == {"site": "tetam", "run": "test"}
    assert set(table.sensor.tolist()) == set(SENSORS)
    assert bundle_beacon(table) == BEACON
    # Exact ns survive: the first row of one file is in the table.
    first = next(iter_rows(tmp_path / "run" / "rssi" / f"{SENSORS[0]}.mbd"))
    assert first.t_ns in set(table.t_ns.tolist())
    # A plain folder of .mbd files (the run's rssi/ folder itself) works too.
    assert len(load_rssi(tmp_path / "run" / "rssi")) == 900


def test_dataset_folder_skips_the_merged_file(dataset_dir: Path, tmp_path: Path) -> None:
    per_sensor = load_rssi(dataset_dir / "trk" / "straight_01")
    merged = load_rssi(dataset_dir / "trk" / "straight_01_all_sensors.mbd")
    assert len(per_sensor) == len(merged)
    assert sorted(per_sensor.t_ns.tolist()) == sorted(merged.t_ns.tolist())
    # all_sensors.mbd beside per-sensor files would repeat every row: it is ignored.
    folder = tmp_path / "f"
    folder.mkdir()
    for f in (dataset_dir / "trk" / "straight_01").glob("*.mbd"):
        (folder / f.name).write_bytes(f.read_bytes())
    (folder / "x_all_sensors.mbd").write_bytes(
        (dataset_dir / "trk" / "straight_01_all_sensors.mbd").read_bytes()
    )
    assert len(load_rssi(folder)) == len(merged)


def test_rssi_input_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file or folder"):
        load_rssi(tmp_path / "missing")
    with pytest.raises(ConfigError, match="no .mbd files"):
        load_rssi(tmp_path)
    bad = tmp_path / "s.mbd"
    bad.write_text("1700000000.1,000000000101,e78f135624ce,-60\nnot,a,row\n", encoding="utf-8")
    with pytest.raises(MbdError, match=r"s\.mbd:2"):
        load_rssi(tmp_path)
    bad.write_text("\n", encoding="utf-8")
    with pytest.raises(NoDataError, match="hold no readings"):
        load_rssi(tmp_path)


def test_annotated_mbd_round_trip(tmp_path: Path) -> None:
    write_run(tmp_path / "run", np.random.default_rng(1))
    table = load_rssi(tmp_path / "run")
    poses = make_poses(T0_NS / 1e9 + 1.0)  # tracked span: 1.0 .. 8.96 s of the 10 s run
    labels = label_readings(poses, table.t_ns)
    n_lab = int(labels.labelled.sum())
    assert 0 < n_lab < len(table)
    stale = tmp_path / "out" / "annotated" / "0000000000ff.mbd"  # from an earlier run
    stale.parent.mkdir(parents=True)
    stale.write_text("1.0,0000000000ff,e78f135624ce,-60\n")
    written = write_annotated_mbd(tmp_path / "out" / "annotated", table, labels)
    assert not stale.exists()
    assert set(written) == {*SENSORS, "all"}

    merged = list(iter_rows(written["all"]))
    assert len(merged) == n_lab
    assert [r.t_ns for r in merged] == sorted(r.t_ns for r in merged)
    lab = np.flatnonzero(labels.labelled)
    by_key = {(int(table.t_ns[i]), str(table.sensor[i])): i for i in lab}
    for row in merged:
        i = by_key[(row.t_ns, row.sensor)]  # exact ns and sensor identify the reading
        assert row.beacon == BEACON
        assert row.rssi == int(table.rssi[i])
        vals = np.array([float(v) for v in row.rest])
        assert vals.size == 12
        np.testing.assert_allclose(vals[:3], labels.positions[i], atol=6e-6)
        np.testing.assert_allclose(vals[3:].reshape(3, 3), labels.rotations[i], atol=6e-7)
    for s in SENSORS:
        rows = list(iter_rows(written[s]))
        assert {r.sensor for r in rows} == {s}
        assert len(rows) == int(np.sum(labels.labelled & (table.sensor == s)))
    # ts text is the exact ns, 9 decimals.
    assert written["all"].read_text().split(",", 1)[0] == format_ts(merged[0].t_ns)


def test_parquet_and_report(tmp_path: Path) -> None:
    write_run(tmp_path / "run", np.random.default_rng(2))
    table = load_rssi(tmp_path / "run")
    labels = label_readings(make_poses(T0_NS / 1e9 + 1.0), table.t_ns)
    path = write_parquet(tmp_path / "annotated.parquet", table, labels)
    df = pd.read_parquet(path)
    assert len(df) == int(labels.labelled.sum())
    assert (
        list(df.columns[:16])
        == [
            "ts",
            "t_ns",
            "sensor",
            "beacon",
            "rssi",
            "x",
            "y",
            "z",
            "r11",
            "r12",
            "r13",
            "r21",
            "r22",
            "r23",
            "r31",
            "r32",
        ][:16]
    )
    assert {"r33", "pos_sigma", "markers_used", "gap_s"} <= set(df.columns)
    assert df["t_ns"].is_monotonic_increasing
    i = np.flatnonzero(labels.labelled)[np.argsort(table.t_ns[labels.labelled], kind="stable")]
    np.testing.assert_array_equal(df["t_ns"].to_numpy(), table.t_ns[i])
    np.testing.assert_allclose(df[["x", "y", "z"]].to_numpy(), labels.positions[i])
    np.testing.assert_allclose(df["pos_sigma"].to_numpy(), 0.004)
    assert (df["markers_used"] == 3).all()
    assert (df["gap_s"] <= 0.02 + 1e-9).all()

    rep = write_report(
        tmp_path / "report.json",
        {"offset": np.float64(1.5), "sigma": math.nan, "counts": {"a": np.int64(3)}, "p": tmp_path},
    )
    assert json.loads(rep.read_text()) == {
        "offset": 1.5,
        "sigma": None,
        "counts": {"a": 3},
        "p": str(tmp_path),
    }


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_builtin_site_recognised_and_plots_written(tmp_path: Path) -> None:
    markers = read_marker_map(site_dir("tetam") / "marker_positions.dat")
    assert builtin_site_for(markers) == "tetam"
    moved = dict(markers)
    k = next(iter(moved))
    moved[k] = type(moved[k])(k, (0.0, 0.0, 0.0), moved[k].euler_xyz)
    assert builtin_site_for(moved) is None

    floor, devices = load_site("tetam")
    # The .par maps the room's far corner inside the image.
    px, py = floor.params.world_to_pixel(20.0, 17.0)
    assert 0 < px < floor.image.shape[1]
    assert 0 < py < floor.image.shape[0]
    traj = np.column_stack([np.linspace(2, 18, 50), np.linspace(2, 15, 50), np.full(50, 1.5)])
    p1 = plot_trajectory_map(tmp_path / "map.png", traj, floor=floor, devices=devices)
    p2 = plot_trajectory_map(tmp_path / "plain.png", traj)
    assert _png_size(p1)[0] > 300
    assert _png_size(p2)[0] > 300
    t = 1_700_000_000 + np.linspace(0, 10, 300)
    sensor = np.array(SENSORS * 100)
    rssi = np.random.default_rng(0).integers(-90, -50, 300)
    _, h3 = _png_size(
        plot_rssi_time(
            tmp_path / "rssi.png",
            t,
            rssi,
            sensor,
            events=[(t[0] + 1, t[0] + 2.5)],
            span=(t[0] + 3, t[-1]),
        )
    )
    assert h3 > 300
    pos = traj[np.arange(300) % 50]
    assert (
        _png_size(
            plot_rssi_on_trajectory(
                tmp_path / "on.png", traj, pos, rssi, sensor, floor=floor, devices=devices
            )
        )[0]
        > 300
    )
