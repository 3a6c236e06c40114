"""Every file of the bundled dataset subset: parse -> write -> parse gives the same values, and
where our writer reproduces the published spelling, the same bytes."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bgt_core.formats import devices, grd, hst, markers, occ, tables
from bgt_core.formats.mbd import iter_rows

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"

MBD_FILES = sorted(DATASET.rglob("*.mbd"))
OCC_FILES = sorted(DATASET.rglob("*.occ"))


def _ids(paths: list[Path]) -> list[str]:
    return [str(p.relative_to(DATASET)) for p in paths]


def test_the_dataset_subset_is_all_covered():
    # 12 fingerprint files, 12 straight_01 sensors + their merged file, straight_05's sensor 30
    assert len(MBD_FILES) == 12 + 12 + 1 + 1
    assert len(OCC_FILES) == 2


@pytest.mark.parametrize("path", MBD_FILES, ids=_ids(MBD_FILES))
def test_mbd_round_trip(path: Path, tmp_path: Path):
    df = tables.load_mbd(path)
    out = tmp_path / path.name
    if "x" in df.columns:
        n = tables.write_track_mbd(df, out, rotations="keep")
    else:
        n = tables.write_mbd(df, out)
    assert n == len(df) == sum(1 for line in path.read_text().splitlines() if line.strip())
    pd.testing.assert_frame_equal(tables.load_mbd(out), df)
    assert out.read_text() == path.read_text()  # the published spelling, byte for byte


def test_load_mbd_columns_and_exact_timestamps():
    fpt = DATASET / "fpt" / "sensor10_2.59_2.19_2.05.mbd"
    df = tables.load_mbd(fpt)
    assert list(df.columns) == ["ts", "t_ns", "sensor", "beacon", "rssi"]
    first = fpt.read_text().splitlines()[0].split(",")
    assert first[0] == "1568633989.991605997"
    assert df["t_ns"].iloc[0] == 1568633989991605997  # no float rounding
    assert df["ts"].iloc[0] == pytest.approx(1568633989.991606, abs=1e-6)
    assert df["sensor"].iloc[0] == "b827eb4521b4"
    assert df["beacon"].iloc[0] == "e78f135624ce"
    assert df["rssi"].iloc[0] == int(first[3])
    assert df["t_ns"].dtype == np.int64

    trk = tables.load_mbd(DATASET / "trk" / "straight_01_all_sensors.mbd")
    assert list(trk.columns) == ["ts", "t_ns", "sensor", "beacon", "rssi", *tables.POSE_COLUMNS]
    assert trk.loc[0, ["x", "y", "z", "r11", "r33"]].tolist() == [
        18.031,
        8.465,
        1.816,
        0.062,
        0.002,
    ]


def test_load_mbd_of_several_files_keeps_file_order():
    files = sorted((DATASET / "trk" / "straight_01").glob("*.mbd"))
    df = tables.load_mbd(files)
    expected = [r.t_ns for f in files for r in iter_rows(f)]
    assert df["t_ns"].tolist() == expected
    merged = tables.load_mbd(DATASET / "trk" / "straight_01_all_sensors.mbd")
    assert sorted(df["t_ns"]) == sorted(merged["t_ns"])


def test_mixed_fingerprint_and_track_rows_give_nan_poses(tmp_path: Path):
    f = tmp_path / "mixed.mbd"
    f.write_text(
        "1.5,aabbccddeeff,112233445566,-60\n"
        "2.5,aabbccddeeff,112233445566,-61,1,2,3,1,0,0,0,1,0,0,0,1\n"
    )
    df = tables.load_mbd(f)
    assert np.isnan(df.loc[0, "x"])
    assert df.loc[1, "x"] == 1.0


def test_dev_round_trip(tmp_path: Path):
    path = DATASET / "cnf" / "tetam.dev"
    d = devices.read_dev(path)
    assert len(d.dongles) == 12
    assert list(d.beacons) == ["e78f135624ce"]
    again = devices.parse_dev(devices.format_dev(d))
    assert again == d
    assert again.dongles["b827eb4521b4"].position == (7.0, 7.09, 1.22)
    # the .hst embedding of the same devices round-trips too
    assert devices.devices_from_obj(*devices.devices_to_obj(d)) == d


def test_par_round_trip():
    p = devices.read_par(DATASET / "cnf" / "tetam.par")
    assert devices.parse_par(devices.format_par(p)) == p
    assert p.direction == (1, 0, 1, 1)
    assert p.origin == (22.0, 9.0)


def test_marker_map_round_trip():
    path = DATASET / "vid" / "marker_positions.dat"
    m = markers.read_marker_map(path)
    assert len(m) == 30
    again = markers.parse_dat(markers.format_dat(m))
    assert again == m
    assert m[0].position == (6.38, 5.93, 2.0)


@pytest.mark.parametrize("path", OCC_FILES, ids=_ids(OCC_FILES))
def test_occ_round_trip(path: Path, tmp_path: Path):
    o = occ.read_occ(path)
    out = tmp_path / path.name
    occ.write_occ(o, out)
    assert out.read_text() == path.read_text()
    assert occ.read_occ(out) == o
    # the cells are exactly the published grid layout (arange(x0, x1 + cell, cell))
    xs, ys = occ.grid_corners(o.limits, o.cell)
    assert set(o.cells) == {(x, y) for x in xs for y in ys}
    # and the numpy view agrees with the file, value by value
    xs_a, ys_a, mask = tables.occ_to_mask(o)
    assert mask.sum() == sum(o.cells.values())
    assert tables.mask_to_occ(xs_a, ys_a, mask, o.limits, o.cell).cells == o.cells
    frame = tables.occ_to_frame(o)
    assert len(frame) == len(o.cells)
    assert frame["value"].sum() == mask.sum()


def test_grid_corners_of_the_published_grids():
    lim = ((0.0, 0.0), (20.660138018121128, 17.64103475472807))
    xs, ys = occ.grid_corners(lim, 1.0)
    assert (len(xs), len(ys)) == (22, 19)
    assert xs[-1] == 21.0
    xs, ys = occ.grid_corners(lim, 0.5)
    assert (len(xs), len(ys)) == (43, 37)
    assert ys[-1] == 18.0
    xs, _ = occ.grid_corners(((0.0, 0.0), (2.0, 1.0)), 1.0)
    assert xs == [0.0, 1.0, 2.0]


def _histograms() -> hst.FingerprintHistograms:
    d = devices.read_dev(DATASET / "cnf" / "tetam.dev")
    rng = np.random.default_rng(3)

    def h():
        p = rng.random(80) * (rng.random(80) < 0.1)
        p[rng.integers(80)] += 0.5
        return p / p.sum()

    table = {
        (2.59, 2.19, 2.05): {
            "b827eb4521b4": {"e78f135624ce": h()},
            "000000000101": {"e78f135624ce": h()},
        },
        (12.95, 16.8, 1.85): {"b827eb4521b4": {"e78f135624ce": h()}},
    }
    return hst.histograms_from_mapping(hst.DEFAULT_BINS, d, table)


def test_hst_round_trip(tmp_path: Path):
    h = _histograms()
    out = tmp_path / "x.hst"
    hst.write_hst(h, out)
    text = out.read_text()
    again = hst.read_hst(out)
    assert again == h
    assert hst.format_hst(again) == text
    lines = text.splitlines()
    assert [line.split(":", 1)[0] for line in lines] == [
        "Bins",
        "Dongles",
        "Beacons",
        "Fingerprints",
    ]
    assert lines[3].startswith(
        'Fingerprints:{ "(2.59, 2.19, 2.05)": {"b827eb4521b4": {"e78f135624ce": ['
    )
    assert text.endswith("]}}}\n")


def test_hst_reads_python_literal_spelling():
    h = _histograms()
    # the same content written with Python's repr (single quotes) instead of JSON
    d_obj, b_obj = devices.devices_to_obj(h.devices)
    fps = {
        hst.position_key(p): {s: {b: list(v) for b, v in bs.items()} for s, bs in ss.items()}
        for p, ss in h.fingerprints.items()
    }
    text = f"Bins:{list(h.bins)!r}\nDongles:{d_obj!r}\nBeacons:{b_obj!r}\nFingerprints:{fps!r}\n"
    assert hst.parse_hst(text) == h


def test_hst_frame_round_trip():
    h = _histograms()
    frame = tables.hst_to_frame(h)
    assert len(frame) == 3 * 80
    assert frame.groupby(["x", "y", "sensor"])["p"].sum().round(12).eq(1.0).all()
    assert tables.hst_from_frame(frame, h.bins, h.devices) == h
    positions, sensors, beacons, p = tables.hst_to_arrays(h)
    assert positions.shape == (2, 3)
    assert p.shape == (2, 2, 1, 80)
    assert np.isnan(p[1, sensors.index("000000000101"), 0]).all()  # explicit gap
    np.testing.assert_array_equal(
        p[0, sensors.index("b827eb4521b4"), 0],
        h.fingerprints[(2.59, 2.19, 2.05)]["b827eb4521b4"]["e78f135624ce"],
    )


def test_grd_round_trip(tmp_path: Path):
    h = _histograms()
    hist = next(iter(next(iter(h.fingerprints.values())).values()))["e78f135624ce"]
    lim = ((0.0, 0.0), (20.660138018121128, 17.64103475472807))
    g = grd.RadioMapGrid(
        "000000000101",
        lim,
        1.0,
        hst.DEFAULT_BINS,
        {(0.0, 0.0): {"e78f135624ce": hist}, (2.0, 0.0): {"e78f135624ce": hist}},
    )
    out = tmp_path / "m.grd"
    grd.write_grd(g, out)
    again = grd.read_grd(out)
    assert again == g
    lines = out.read_text().splitlines()
    assert lines[0].startswith(
        "000000000101::[[0.0, 0.0], [20.660138018121128, 17.64103475472807]]::1.0::[-100.0, -99.0,"
    )
    assert lines[1].startswith("[0.0, 0.0]::e78f135624ce::[")
    frame = tables.grd_to_frame(again)
    assert len(frame) == 2 * 80
    assert set(frame["gx"]) == {0.0, 2.0}
    # one value per bin edge, the last 0, as the published files
    values = lines[1].split("::")[2].strip("[]").split(", ")
    assert len(values) == 81
    assert values[-1] == "0.0"


PUBLISHED_GRD = Path(__file__).resolve().parents[2] / "data" / "grd" / "published_layout.grd"


def test_grd_published_line_round_trip(tmp_path: Path):
    # built from the dataset's format description (no published .grd is bundled; see its README)
    text = PUBLISHED_GRD.read_text(encoding="utf-8")
    g = grd.parse_grd(text)
    assert g.sensor == "b827eb4521b4"
    assert len(g.bins) == 81
    for hist in (b["e78f135624ce"] for b in g.cells.values()):
        assert len(hist) == 80
        assert sum(hist) == pytest.approx(1.0, abs=1e-9)
    assert grd.format_grd(g) == text  # byte for byte
    # our older files (80 values per cell) still read, to the same grid
    old = (
        "\n".join(
            line if i == 0 else line.replace(", 0.0]", "]")
            for i, line in enumerate(text.splitlines())
        )
        + "\n"
    )
    assert grd.parse_grd(old) == g
    # an 81st value that is not 0 is not a published layout
    bad = text.replace(", 0.0]\n", ", 0.5]\n", 1)
    with pytest.raises(grd.GridFormatError, match=":2:.*must be 0"):
        grd.parse_grd(bad, "bad.grd")


def test_atomic_writer_leaves_no_temporary_files(tmp_path: Path):
    shutil.copy(DATASET / "occ" / "tetam_1.0.occ", tmp_path / "a.occ")
    occ.write_occ(occ.read_occ(tmp_path / "a.occ"), tmp_path / "b.occ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.occ", "b.occ"]
