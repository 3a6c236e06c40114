"""Malformed input: one-line errors naming the file and the line (or row)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bgt_core.formats import devices, grd, hst, markers, occ, tables
from bgt_core.formats.mbd import MbdError

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"
GOOD_HIST = "[" + ", ".join(["0.0"] * 79 + ["1.0"]) + "]"
BINS = "[" + ", ".join(f"{float(v)}" for v in range(-100, -19)) + "]"
HEADER = f"000000000101::[[0.0, 0.0], [2.0, 2.0]]::1.0::{BINS}"


def _hst_text(fingerprints: str) -> str:
    return (
        f'Bins:{BINS}\nDongles:{{"000000000101": [[1.0, 2.0, 3.0], 0, "s"]}}\n'
        f'Beacons:{{"e78f135624ce": [[], 0, "b"]}}\nFingerprints:{fingerprints}\n'
    )


# (reader, file name, content, expected line number in the message)
CASES = [
    (
        tables.load_mbd,
        "bad.mbd",
        "1.5,aabbccddeeff,112233445566,-60\n1.6,aabbccddeeff,-61\n",
        MbdError,
        ":2:",
    ),
    (
        tables.load_mbd,
        "bad.mbd",
        "1.5,aabbccddeeff,112233445566,-60\n1.6,xx,112233445566,-61\n",
        MbdError,
        ":2:",
    ),
    (tables.load_mbd, "pose.mbd", "1.5,aabbccddeeff,112233445566,-60,1,2,3\n", MbdError, "row 1"),
    (
        occ.read_occ,
        "bad.occ",
        "[[0.0, 0.0], [2.0, 2.0]]::1.0\n[0.0, 0.0]::1\n[1.0, 0.0]::2\n",
        occ.GridFormatError,
        ":3:",
    ),
    (occ.read_occ, "bad.occ", "[[0.0, 0.0], [2.0, 2.0]]::0\n", occ.GridFormatError, ":1:"),
    (
        occ.read_occ,
        "dup.occ",
        "[[0.0, 0.0], [2.0, 2.0]]::1.0\n[0.0, 0.0]::1\n[0.0, 0.0]::0\n",
        occ.GridFormatError,
        ":3:",
    ),
    (
        grd.read_grd,
        "bad.grd",
        f"{HEADER}\n[0.0, 0.0]::e78f135624ce::{GOOD_HIST}\n[1.0, 0.0]::e78f135624ce::[0.5, 0.5]\n",
        grd.GridFormatError,
        ":3:",
    ),
    (
        grd.read_grd,
        "bad.grd",
        "000000000101::[[0.0, 0.0]]::1.0::[1, 2]\n",
        grd.GridFormatError,
        ":1:",
    ),
    (hst.read_hst, "bad.hst", _hst_text('{"(1.0, 2.0)": {}}'), hst.HstError, ":4:"),
    (
        hst.read_hst,
        "bad.hst",
        _hst_text('{"(1.0, 2.0, 3.0)": {"000000000101": {"e78f135624ce": [1.0]}}}'),
        hst.HstError,
        ":4:",
    ),
    (
        hst.read_hst,
        "bad.hst",
        "Bins:[-100.0, -101.0]\nDongles:{}\nFingerprints:{}\n",
        hst.HstError,
        ":1:",
    ),
    (hst.read_hst, "bad.hst", _hst_text("{'unclosed"), hst.HstError, ":4:"),
    (
        devices.read_dev,
        "bad.dev",
        'Dongles:{"000000000101": [[1, 2, 3], 0, "s"]}\nBeacons:{oops}\n',
        devices.SiteConfigError,
        ":2:",
    ),
    (
        markers.read_marker_map,
        "bad.dat",
        "0: [1, 2, 3]:[0, 0, 0]\n1: [1, 2]:[0, 0, 0]\n",
        markers.MarkerMapError,
        ":2:",
    ),
]


@pytest.mark.parametrize(("reader", "name", "content", "error", "where"), CASES)
def test_malformed_input_names_file_and_line(tmp_path: Path, reader, name, content, error, where):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(error) as info:
        reader(path)
    message = str(info.value)
    assert str(path) in message
    assert where in message
    assert "\n" not in message


@pytest.mark.parametrize("reader", [tables.load_mbd, occ.read_occ, grd.read_grd, hst.read_hst])
def test_missing_file_is_a_one_line_error(tmp_path: Path, reader):
    with pytest.raises(ValueError, match="cannot read") as info:
        reader(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(info.value)


def test_failed_write_keeps_the_previous_file(tmp_path: Path):
    out = tmp_path / "x.hst"
    out.write_text("previous\n")
    bad = hst.FingerprintHistograms(
        (0.0, 1.0), devices.Devices({}, {}), {(0.0, 0.0, 0.0): {"a": {"b": (object(),)}}}
    )
    with pytest.raises(TypeError):
        hst.write_hst(bad, out)
    assert out.read_text() == "previous\n"
    assert [p.name for p in tmp_path.iterdir()] == ["x.hst"]


def test_track_writer_refuses_non_rotations_by_default(tmp_path: Path):
    df = tables.load_mbd(DATASET / "trk" / "straight_01_all_sensors.mbd")
    # the published annotation rounds to three decimals, so its matrices are not rotations
    assert tables.rotation_problems(df[tables.ROTATION_COLUMNS].to_numpy()).all()
    with pytest.raises(ValueError, match=r"row 0: orientation is not a rotation matrix") as info:
        tables.write_track_mbd(df, tmp_path / "t.mbd")
    assert "\n" not in str(info.value)
    assert not (tmp_path / "t.mbd").exists()


def test_track_writer_projects_to_true_rotations(tmp_path: Path):
    df = tables.load_mbd(DATASET / "trk" / "straight_01_all_sensors.mbd")
    out = tmp_path / "t.mbd"
    assert tables.write_track_mbd(df, out, rotations="project") == len(df)
    again = tables.load_mbd(out)
    r = again[tables.ROTATION_COLUMNS].to_numpy().reshape(-1, 3, 3)
    assert not tables.rotation_problems(r, tol=1e-9).any()
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    # positions, timestamps and readings are untouched; a published matrix that was nearly a
    # rotation (three-decimal rounding only) moves by no more than that rounding
    assert again["t_ns"].tolist() == df["t_ns"].tolist()
    np.testing.assert_array_equal(again[["x", "y", "z"]].to_numpy(), df[["x", "y", "z"]].to_numpy())
    published = df[tables.ROTATION_COLUMNS].to_numpy().reshape(-1, 3, 3)
    nearly = ~tables.rotation_problems(published, tol=0.005)
    assert nearly.sum() > 100
    assert np.abs(r[nearly] - published[nearly]).max() < 0.005
    # and the strict default accepts what was just written
    tables.write_track_mbd(again, tmp_path / "t2.mbd")


def test_track_writer_rejects_reflections(tmp_path: Path):
    df = tables.load_mbd(DATASET / "trk" / "straight_01_all_sensors.mbd").head(3).copy()
    df[tables.ROTATION_COLUMNS] = [1.0, 0, 0, 0, 1.0, 0, 0, 0, -1.0]
    with pytest.raises(ValueError, match="det <= 0"):
        tables.write_track_mbd(df, tmp_path / "t.mbd", rotations="project")


def test_format_modules_import_without_pandas_or_numpy():
    code = (
        "import sys; sys.modules['pandas'] = None; sys.modules['numpy'] = None\n"
        "from bgt_core.formats import hst, grd, occ, tables, mbd, devices, markers\n"
        "print('ok')"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.stdout.strip() == "ok", done.stderr
