"""Property-based fuzz of every reader of an annotator input file: whatever the bytes, a reader
returns or raises its documented error type, with one line that names the file. Inputs are
valid files with hostile pieces spliced in (NaN, huge numbers, deep brackets, bytes that are not
UTF-8, long digit strings, YAML anchors) or plain random bytes."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from annotator.errors import AnnotatorError
from annotator.io.experiment import load_calibration
from annotator.io.trajectory import read_trajectory
from bgt_core import safe_yaml
from bgt_core.formats import devices, grd, hst, markers, occ, tables
from bgt_core.formats.mbd import MbdError, iter_rows

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"
BINS = "[" + ", ".join(f"{float(v)}" for v in range(-100, -19)) + "]"
HIST = "[" + ", ".join(["0.0"] * 79 + ["1.0"]) + "]"


def head(path: Path, n: int) -> bytes:
    """The whole lines within the first ``n`` bytes of a file."""
    data = path.read_bytes()[:n]
    return data[: data.rfind(b"\n") + 1]


SAMPLES = {
    "mbd": head(DATASET / "trk" / "straight_01_all_sensors.mbd", 2000),
    "fpt": head(DATASET / "fpt" / "sensor10_2.59_2.19_2.05.mbd", 600),
    "hst": (
        f'Bins:{BINS}\nDongles:{{"000000000101": [[1.0, 2.0, 3.0], 0, "s"]}}\n'
        f'Beacons:{{"e78f135624ce": [[], 0, "b"]}}\n'
        f'Fingerprints:{{"(1.0, 2.0, 1.0)": {{"000000000101": {{"e78f135624ce": {HIST}}}}}}}\n'
    ).encode(),
    "grd": (
        f"000000000101::[[0.0, 0.0], [2.0, 2.0]]::1.0::{BINS}\n[0.0, 0.0]::e78f135624ce::{HIST}\n"
    ).encode(),
    "occ": head(DATASET / "occ" / "tetam_1.0.occ", 400),
    "dev": (DATASET / "cnf" / "tetam.dev").read_bytes(),
    "par": (DATASET / "cnf" / "tetam.par").read_bytes(),
    "dat": head(DATASET / "vid" / "marker_positions.dat", 400),
    "markers_yaml": b"markers:\n  - {id: 3, position: [1.0, 2.0, 0.5], rotation_xyz: [0.0, 0.0, 1.57]}\n",
    "calibration": b"""\
image_width: 960
image_height: 540
camera_matrix: {rows: 3, cols: 3, data: [620.0, 0.0, 480.5, 0.0, 621.5, 268.25, 0.0, 0.0, 1.0]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [-0.08, 0.02, 0.0004, -0.0003, 0.0]}
""",
    "trajectory": b"t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33,markers\n"
    b"1700000000.0,1,2,3,1,0,0,0,1,0,0,0,1,4\n1700000000.1,nan,nan,nan,nan,nan,nan,nan,nan,nan,"
    b"nan,nan,nan,0\n",
}


def _mbd_rows(path: Path) -> object:
    return list(iter_rows(path))


# (sample, file name, reader, the one error type it documents)
READERS: list[tuple[str, str, Callable[[Path], object], type[Exception]]] = [
    ("mbd", "a.mbd", tables.load_mbd, MbdError),
    ("fpt", "b.mbd", _mbd_rows, MbdError),
    ("hst", "a.hst", hst.read_hst, hst.HstError),
    ("grd", "a.grd", grd.read_grd, grd.GridFormatError),
    ("occ", "a.occ", occ.read_occ, occ.GridFormatError),
    ("dev", "a.dev", devices.read_dev, devices.SiteConfigError),
    ("par", "a.par", devices.read_par, devices.SiteConfigError),
    ("dat", "a.dat", markers.read_marker_map, markers.MarkerMapError),
    ("markers_yaml", "m.yaml", markers.read_marker_map, markers.MarkerMapError),
    ("calibration", "cal.yaml", load_calibration, AnnotatorError),
    ("calibration", "any.yaml", safe_yaml.load_file, safe_yaml.YamlError),
    ("trajectory", "trajectory.csv", read_trajectory, AnnotatorError),
]

HOSTILE = [
    b"NaN",
    b"nan",
    b"Infinity",
    b"-inf",
    b".nan",
    b".inf",
    b"1e400",
    b"-1e309",
    b"1" + b"0" * 400,
    b"9" * 5000,
    b"12345678901234567890",
    b"[" * 3000,
    b"{" * 3000,
    b"(" * 3000,
    b"]",
    b"}",
    b")",
    b'"',
    b"'",
    b"\\",
    b"\xff",
    b"\xc3\x28",
    b"\xed\xa0\x80",
    b"\x00",
    b"\n",
    b"\r",
    b",",
    b":",
    b"::",
    b"&a ",
    b"*a",
    b"!!python/object:os.system ",
    b"true",
    b"null",
    b"-",
    b"1e30",
    b"100000000000000000000000000000",
    b"40000",
    b"-99999",
    b"1.5",
    b"0x10",
]

settings.register_profile(
    "fuzz",
    max_examples=60,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@st.composite
def mangled(draw: st.DrawFn, sample: bytes) -> bytes:
    """The sample with 1..4 edits: a hostile piece inserted or written over some bytes, bytes
    dropped, or random bytes inserted."""
    data = bytearray(sample)
    for _ in range(draw(st.integers(1, 4))):
        pos = draw(st.integers(0, len(data)))
        kind = draw(st.sampled_from(["insert", "overwrite", "delete", "random"]))
        if kind == "delete":
            del data[pos : pos + draw(st.integers(1, 40))]
        elif kind == "random":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=30))
        else:
            piece = draw(st.sampled_from(HOSTILE))
            end = pos + (len(piece) if kind == "overwrite" else 0)
            data[pos:end] = piece
    return bytes(data)


@pytest.mark.parametrize(
    ("sample", "name", "reader", "error"), READERS, ids=[r[1] for r in READERS]
)
@settings(settings.get_profile("fuzz"))
@given(data=st.data())
def test_only_the_documented_error_escapes(tmp_path_factory, sample, name, reader, error, data):
    content = data.draw(
        st.one_of(mangled(SAMPLES[sample]), st.binary(max_size=300)), label="content"
    )
    path = tmp_path_factory.mktemp("fuzz") / name
    path.write_bytes(content)
    try:
        reader(path)
    except error as e:
        message = str(e)
        assert "\n" not in message
        assert "\r" not in message
        assert str(path) in message, message
    # anything else (UnicodeDecodeError, RecursionError, OverflowError, KeyError...) fails the test


@pytest.mark.parametrize(
    ("sample", "name", "reader", "error"), READERS, ids=[r[1] for r in READERS]
)
def test_the_unmangled_samples_are_read(tmp_path: Path, sample, name, reader, error):
    """The fuzz starts from files the readers accept (else it would test nothing but errors), and
    each is read whole: the content checked against what the sample holds."""
    path = tmp_path / name
    path.write_bytes(SAMPLES[sample])
    assert READ_WHOLE[name](reader(path)), name


def _lines(sample: str) -> int:
    return sum(1 for line in SAMPLES[sample].splitlines() if line.strip())


# What reading each unmangled sample must give (a row per line, the keys it names).
READ_WHOLE: dict[str, Callable[[Any], bool]] = {
    "a.mbd": lambda df: len(df) == _lines("mbd") and {"x", "y", "z"} <= set(df.columns),
    "b.mbd": lambda rows: len(rows) == _lines("fpt") and rows[0].sensor == "b827eb4521b4",
    "a.hst": lambda h: (
        list(h.fingerprints) == [(1.0, 2.0, 1.0)] and list(h.devices.dongles) == ["000000000101"]
    ),
    "a.grd": lambda g: g.sensor == "000000000101" and list(g.cells) == [(0.0, 0.0)],
    "a.occ": lambda o: o.cell == 1.0 and len(o.cells) > 0,
    "a.dev": lambda d: (len(d.dongles), len(d.beacons)) == (12, 1),
    "a.par": lambda p: p.origin == (22.0, 9.0) and p.parity > 0,
    "a.dat": lambda m: len(m) == _lines("dat"),
    "m.yaml": lambda m: list(m) == [3],
    "cal.yaml": lambda c: (c.width, c.height, c.camera_matrix[0, 0]) == (960, 540, 620.0),
    "any.yaml": lambda d: d["image_width"] == 960 and len(d) == 5,
    "trajectory.csv": lambda t: len(t) == 2 and int(t.valid.sum()) == 1,
}


GRD_HEAD = f"000000000101::[[0.0, 0.0], [2.0, 2.0]]::1.0::{BINS}\n"

# The inputs of issue 11, reader by reader: (file name, reader, error, content, message part)
ISSUE_CASES = [
    (
        "a.grd",
        grd.read_grd,
        grd.GridFormatError,
        GRD_HEAD + "[" * 100_000 + "::e78f135624ce::" + HIST + "\n",
        "a.grd:2: expected '[gx, gy]::<beacon>::[p, ...]' (nested deeper than 16 levels)",
    ),
    (
        "a.grd",
        grd.read_grd,
        grd.GridFormatError,
        GRD_HEAD + "[0.0, 0.0]::e78f135624ce::" + "[" * 50_000 + "\n",
        "a.grd:2",
    ),
    (
        "a.grd",
        grd.read_grd,
        grd.GridFormatError,
        GRD_HEAD.replace("[[0.0, 0.0]", "[[NaN, 0.0]"),
        "finite",
    ),
    (
        "a.grd",
        grd.read_grd,
        grd.GridFormatError,
        GRD_HEAD.encode() + b"[0.0, 0.0]::\xff\n",
        "a.grd:2: not UTF-8",
    ),
    (
        "a.occ",
        occ.read_occ,
        occ.GridFormatError,
        "[[0.0, 0.0], [2.0, 2.0]]::1.0\n[1e400, 0.0]::1\n",
        "a.occ:2",
    ),
    (
        "a.hst",
        hst.read_hst,
        hst.HstError,
        SAMPLES["hst"]
        .decode()
        .replace('"(1.0, 2.0, 1.0)"', '"' + "(" * 3000 + "1, 2, 3" + ")" * 3000 + '"'),
        "a.hst:4: Fingerprints: position key",
    ),
    (
        "a.hst",
        hst.read_hst,
        hst.HstError,
        SAMPLES["hst"].replace(b"Bins:", b"Bins:\xc3\x28"),
        "a.hst:1: not UTF-8",
    ),
    (
        "a.mbd",
        tables.load_mbd,
        MbdError,
        "1700000000.5,aabbccddeeff,112233445566,32768\n",
        "a.mbd:1: RSSI 32768",
    ),
    (
        "a.mbd",
        tables.load_mbd,
        MbdError,
        "1" + "0" * 30 + ",aabbccddeeff,112233445566,-60\n",
        "a.mbd:1: timestamp",
    ),
    (
        "a.mbd",
        tables.load_mbd,
        MbdError,
        b"1700000000.5,aabbccddeeff,112233445566,-60\n\x80\n",
        "a.mbd:2: not UTF-8 text (byte 0x80 at offset 43)",
    ),
    (
        "a.dat",
        markers.read_marker_map,
        markers.MarkerMapError,
        "99999999999999999999: [1, 2, 3]:[0, 0, 0]\n",
        "0..9999",
    ),
    (
        "a.dat",
        markers.read_marker_map,
        markers.MarkerMapError,
        "1: [1, 2, 3]:[NaN, 0, 0]\n",
        "finite",
    ),
    (
        "m.yaml",
        markers.read_marker_map,
        markers.MarkerMapError,
        "markers:\n  - {id: 1, position: [.inf, 2, 3], rotation_xyz: [0, 0, 0]}\n",
        "finite",
    ),
    (
        "m.yaml",
        markers.read_marker_map,
        markers.MarkerMapError,
        "markers:\n  - {id: 10000, position: [1, 2, 3], rotation_xyz: [0, 0, 0]}\n",
        "0..9999",
    ),
    (
        "a.dev",
        devices.read_dev,
        devices.SiteConfigError,
        'Dongles:{"000000000101": [[NaN, 1, 1], 0, "s"]}\n',
        "finite",
    ),
    (
        "a.par",
        devices.read_par,
        devices.SiteConfigError,
        '{"origin": [1, 2], "limits": [0, 0, 1, 1], "direction": [1, 0, 1, 1], "parity": Infinity}',
        "finite",
    ),
]


@pytest.mark.parametrize(
    ("name", "reader", "error", "content", "message"),
    ISSUE_CASES,
    ids=[f"{c[0]}-{i}" for i, c in enumerate(ISSUE_CASES)],
)
def test_the_issue_inputs_are_one_line_errors(
    tmp_path: Path, name, reader, error, content, message
):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(error) as info:
        reader(path)
    text = str(info.value)
    assert message in text
    assert str(path) in text
    assert "\n" not in text
    assert len(text) < 500
