"""Fingerprint histograms: the pure stages on arrays, and `annotator fingerprints` on the bundled
dataset, checked against histograms computed independently here with plain Python + numpy."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.core import fingerprints as fp
from bgt_core.formats.hst import read_hst

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"
FPT = DATASET / "fpt"
BEACON = "e78f135624ce"
runner = CliRunner()


def independent_histogram(rssi: list[int], lo: int = -100, hi: int = -20) -> np.ndarray:
    """One bin per integer dBm from lo; the top edge hi shares the last bin (numpy's closed last
    bin, which the published files used); everything else outside is dropped."""
    counts = np.zeros(hi - lo)
    for r in rssi:
        if lo <= r <= hi:
            counts[min(r - lo, hi - lo - 1)] += 1
    return counts / counts.sum()


def read_plain(path: Path) -> list[tuple[str, str, int]]:
    with path.open(newline="") as f:
        return [(row[1], row[2], int(row[3])) for row in csv.reader(f) if row]


def run(*args: str):
    return runner.invoke(app, [*map(str, args)], catch_exceptions=False)


def flat(text: str) -> str:
    """Without whitespace: rich wraps long messages (even inside paths) at the terminal width."""
    return "".join(text.split())


# ---------------------------------------------------------------------------------------------
# pure stages


def test_counts_follow_numpy_histogram_bins():
    edges = fp.rssi_edges(-100, -20)
    assert len(edges) == 81
    c = fp.counts(np.array([-101, -100, -99.5, -21, -20, -19, -60]), edges)
    assert c.sum() == 5
    assert c[0] == 2  # -100 and -99.5
    assert c[79] == 2  # -21 and -20 (last bin closed)
    assert c[40] == 1


def test_normalise_marks_empty_histograms_as_gaps():
    p = fp.normalise(np.array([[1, 3, 0], [0, 0, 0]]))
    np.testing.assert_array_equal(p[0], [0.25, 0.75, 0.0])
    assert np.isnan(p[1]).all()


def test_parse_fingerprint_name():
    assert fp.parse_fingerprint_name("sensor10_12.95_16.80_1.85.mbd") == (
        "sensor10",
        (12.95, 16.8, 1.85),
    )
    assert fp.parse_fingerprint_name("my_dongle_-1_2.5_0.mbd") == ("my_dongle", (-1.0, 2.5, 0.0))
    with pytest.raises(ValueError, match="alias"):
        fp.parse_fingerprint_name("sensor10.mbd")


@pytest.mark.parametrize("text", ["-100", "a:b", "-20:-100", "-50:-50"])
def test_parse_range_rejects(text):
    with pytest.raises(ValueError, match="bins"):
        fp.parse_range(text)


def test_bin_to_cells_and_cell_counts():
    xy = np.array([[0.1, 0.1], [0.49, 0.2], [0.5, 0.2], [1.2, 0.7], [np.nan, 1.0], [0.3, 0.4]])
    bins = fp.bin_to_cells(xy, 0.5)
    np.testing.assert_array_equal(bins.keys, [[0, 0], [1, 0], [2, 1]])
    np.testing.assert_array_equal(bins.inverse, [0, 0, 1, 2, -1, 0])
    edges = fp.rssi_edges(-100, -20)
    rssi = np.array([-60, -61, -60, -70, -50, -120])
    c = fp.cell_counts(rssi, bins.inverse, 3, edges)
    assert c.shape == (3, 80)
    assert c[0, 40] == 1 and c[0, 39] == 1 and c[0].sum() == 2  # -120 is out of range  # noqa: PT018
    assert c[1, 40] == 1
    assert c[2, 30] == 1
    # the same rule as the per-recording counts
    np.testing.assert_array_equal(c[0], fp.counts(rssi[bins.inverse == 0], edges))


# ---------------------------------------------------------------------------------------------
# stationary fingerprints from the dataset


@pytest.fixture(scope="module")
def dataset_hst(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("hst") / "tetam.hst"
    result = run("fingerprints", FPT, "--out", out, "--devices", DATASET / "cnf" / "tetam.dev")
    assert result.exit_code == 0, result.output
    return out


def test_hst_from_fpt_matches_an_independent_histogram(dataset_hst: Path):
    h = read_hst(dataset_hst)
    assert list(h.fingerprints) == [(2.59, 2.19, 2.05)]
    per_sensor = h.fingerprints[(2.59, 2.19, 2.05)]
    files = sorted(FPT.glob("*.mbd"))
    assert len(per_sensor) == len(files) == 12
    for f in files:
        rows = read_plain(f)
        sensors = {s for s, _, _ in rows}
        assert len(sensors) == 1
        expected = independent_histogram([r for _, b, r in rows if b == BEACON])
        got = np.array(per_sensor[sensors.pop()][BEACON])
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-15)
        assert got.sum() == pytest.approx(1.0, abs=1e-12)


def test_hst_layout_is_the_published_one(dataset_hst: Path):
    lines = dataset_hst.read_text().splitlines()
    assert len(lines) == 4
    bins = json.loads(lines[0].removeprefix("Bins:"))
    assert bins == [float(v) for v in range(-100, -19)]
    # the devices line spells the published file's way (json, floats as Python prints them)
    assert lines[1].startswith(
        'Dongles:{"b827eb4521b4": [[7.0, 7.09, 1.22], 16711680, "sensor10"], '
        '"000000000101": [[7.18, 0.68, 2.3], 16711730, "sensor11"]'
    )
    assert lines[2] == 'Beacons:{"e78f135624ce": [[], 1328790, "beacon1"]}'
    assert lines[3].startswith('Fingerprints:{ "(2.59, 2.19, 2.05)": {"')
    body = json.loads(lines[3].removeprefix("Fingerprints:"))
    hist = next(iter(body["(2.59, 2.19, 2.05)"].values()))[BEACON]
    assert len(hist) == 80


def test_bins_option_drops_readings_outside(tmp_path: Path):
    out = tmp_path / "narrow.hst"
    f = FPT / "sensor20_2.59_2.19_2.05.mbd"
    assert run("fingerprints", f, "--out", out, "--bins", "-80:-65").exit_code == 0
    h = read_hst(out)
    assert len(h.bins) == 16
    got = h.fingerprints[(2.59, 2.19, 2.05)]["b827eb917e19"][BEACON]
    rows = read_plain(f)
    np.testing.assert_allclose(
        got, independent_histogram([r for *_, r in rows], -80, -65), atol=1e-15
    )
    # without --devices the built-in tetam site (which knows this sensor) supplies the devices
    assert h.devices.dongles["b827eb917e19"].alias == "sensor20"


def test_recordings_of_the_same_position_are_pooled(tmp_path: Path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    src = FPT / "sensor11_2.59_2.19_2.05.mbd"
    lines = src.read_text().splitlines(keepends=True)
    (a / src.name).write_text("".join(lines[:1000]))
    (b / src.name).write_text("".join(lines[1000:]))
    out = tmp_path / "pooled.hst"
    assert run("fingerprints", a, b, "--out", out).exit_code == 0
    got = read_hst(out).fingerprints[(2.59, 2.19, 2.05)]["000000000101"][BEACON]
    expected = independent_histogram([r for *_, r in read_plain(src)])
    np.testing.assert_allclose(got, expected, atol=1e-15)


def test_devices_file_restricts_beacons(tmp_path: Path):
    d = tmp_path / "fpt"
    d.mkdir()
    src = FPT / "sensor12_2.59_2.19_2.05.mbd"
    text = src.read_text() + "1568634999.0,000000000102,aaaaaaaaaaaa,-50\n"
    (d / src.name).write_text(text)
    open_out, strict_out = tmp_path / "open.hst", tmp_path / "strict.hst"
    assert run("fingerprints", d, "--out", open_out).exit_code == 0
    assert (
        run(
            "fingerprints", d, "--out", strict_out, "--devices", DATASET / "cnf" / "tetam.dev"
        ).exit_code
        == 0
    )
    assert set(read_hst(open_out).fingerprints[(2.59, 2.19, 2.05)]["000000000102"]) == {
        BEACON,
        "aaaaaaaaaaaa",
    }
    assert set(read_hst(strict_out).fingerprints[(2.59, 2.19, 2.05)]["000000000102"]) == {BEACON}


# ---------------------------------------------------------------------------------------------
# moving captures


def test_from_annotated_gives_cells_along_the_path(tmp_path: Path):
    track = DATASET / "trk" / "straight_01"
    out = tmp_path / "auto.hst"
    result = run("fingerprints", "--from-annotated", track, "--cell", "0.5", "--out", out)
    assert result.exit_code == 0, result.output
    h = read_hst(out)
    rows = []
    for f in sorted(track.glob("*.mbd")):
        with f.open(newline="") as fh:
            rows += [
                (r[1], r[2], int(r[3]), float(r[4]), float(r[5]), float(r[6]))
                for r in csv.reader(fh)
                if r
            ]
    xs = np.array([r[3] for r in rows])
    ys = np.array([r[4] for r in rows])
    expected_cells = {
        (int(np.floor(x / 0.5)), int(np.floor(y / 0.5))) for x, y in zip(xs, ys, strict=True)
    }
    got_cells = {(round(x / 0.5 - 0.5), round(y / 0.5 - 0.5)) for x, y, _ in h.fingerprints}
    assert got_cells == expected_cells
    assert len(got_cells) >= 30  # an 18 m straight line in 0.5 m cells
    for x, y, z in h.fingerprints:
        assert xs.min() - 0.5 < x < xs.max() + 0.5
        assert 8.0 < y < 9.0  # the straight line runs along y = 8.2 .. 8.7
        assert 1.5 < z < 2.2
    # one cell checked bin by bin against the rows that fall in it
    (x, y, z), per_sensor = next(iter(h.fingerprints.items()))
    sensor = sorted(per_sensor)[0]
    mine = [
        r[2] for r in rows if r[0] == sensor and abs(r[3] - x) <= 0.25 and abs(r[4] - y) <= 0.25
    ]
    np.testing.assert_allclose(per_sensor[sensor][BEACON], independent_histogram(mine), atol=1e-15)


def test_from_annotated_min_readings_thins_cells(tmp_path: Path):
    track = DATASET / "trk" / "straight_01"
    a, b = tmp_path / "a.hst", tmp_path / "b.hst"
    assert (
        run("fingerprints", "--from-annotated", track, "--cell", "1.0", "--out", a).exit_code == 0
    )
    assert (
        run(
            "fingerprints",
            "--from-annotated",
            track,
            "--cell",
            "1.0",
            "--out",
            b,
            "--min-readings",
            "10",
        ).exit_code
        == 0
    )
    n = [sum(len(s) for s in read_hst(p).fingerprints.values()) for p in (a, b)]
    assert n[1] < n[0]


def test_merged_file_is_not_counted_twice(tmp_path: Path):
    d = tmp_path / "annotated"
    shutil.copytree(DATASET / "trk" / "straight_01", d)
    shutil.copy(DATASET / "trk" / "straight_01_all_sensors.mbd", d / "all_sensors.mbd")
    with_merged, without = tmp_path / "a.hst", tmp_path / "b.hst"
    assert run("fingerprints", "--from-annotated", d, "--out", with_merged).exit_code == 0
    assert (
        run(
            "fingerprints", "--from-annotated", DATASET / "trk" / "straight_01", "--out", without
        ).exit_code
        == 0
    )
    assert read_hst(with_merged) == read_hst(without)


# ---------------------------------------------------------------------------------------------
# errors


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--out", "x.hst"], "either stationary PATHS or --from-annotated"),
        ([str(FPT), "--from-annotated", str(FPT), "--out", "x.hst"], "not both"),
        ([str(FPT), "--bins", "-20:-100", "--out", "x.hst"], "--bins"),
        ([str(DATASET / "trk" / "straight_01"), "--out", "x.hst"], "use --from-annotated"),
        (
            [str(DATASET / "trk" / "straight_01_all_sensors.mbd"), "--out", "x.hst"],
            "<alias>_<x>_<y>_<z>.mbd",
        ),
        (["--from-annotated", str(FPT), "--out", "x.hst"], "no positions"),
        (["does-not-exist", "--out", "x.hst"], "no such file"),
    ],
)
def test_bad_input_is_one_red_line(tmp_path: Path, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    result = run("fingerprints", *args)
    assert result.exit_code == 1
    assert flat(message) in flat(result.output)
    assert "Traceback" not in result.output
    assert not (tmp_path / "x.hst").exists()


def test_malformed_recording_names_file_and_line(tmp_path: Path):
    bad = tmp_path / "sensor10_1.00_2.00_3.00.mbd"
    bad.write_text("1568633989.99,b827eb4521b4,e78f135624ce,-66\nnot,a,row\n")
    out = tmp_path / "x.hst"
    result = run("fingerprints", bad, "--out", out)
    assert result.exit_code == 1
    assert flat(f"{bad}:2:") in flat(result.output)
    assert not out.exists()


def test_help_explains():
    result = run("fingerprints", "--help")
    assert result.exit_code == 0
    assert "--from-annotated" in result.output
    assert "<alias>_<x>_<y>_<z>.mbd" in result.output


def test_recordings_with_nothing_in_range_are_an_error(tmp_path: Path):
    f = tmp_path / "sensor10_1.00_2.00_3.00.mbd"
    f.write_text(
        "1568633989.99,b827eb4521b4,e78f135624ce,-110\n1568633990.5,b827eb4521b4,e78f135624ce,-15\n"
    )
    result = run("fingerprints", f, "--out", tmp_path / "x.hst")
    assert result.exit_code == 1
    assert flat("no readings inside -100..-20 dBm") in flat(result.output)
    assert not (tmp_path / "x.hst").exists()
