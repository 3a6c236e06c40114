"""Malformed annotator inputs (issue 11): each one is a one-line error and exit code 1, never a
traceback, and nothing is printed before the error (no progress bar).

The commands run in-process through typer's CliRunner (the error handling is the same code as
in a real process); a few cases also run as a real `annotator` process."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from bgt_core.sites import site_dir

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"
T0 = 1_700_000_000.0

CALIBRATION = """\
image_width: 64
image_height: 48
camera_matrix: {rows: 3, cols: 3, data: [60.0, 0.0, 32.0, 0.0, 60.0, 24.0, 0.0, 0.0, 1.0]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [0.0, 0.0, 0.0, 0.0, 0.0]}
"""
RIG = """\
cameras:
  front:
    calibration: front.yaml
    R_bundle_camera: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    t_bundle_camera: [0.04, 0.0, 0.0]
"""
SYNC = f"sync:\n  mode: manual\n  video_start: {{front: {T0}}}\n"
EXPERIMENT = """\
markers: {file: marker_positions.dat, dictionary: DICT_6X6_50, length: 0.298}
rig: rig.yaml
videos: {front: front.mp4}
rssi: rssi
"""
GOOD_ROW = f"{T0 + 1:.6f},aabbccddeeff,112233445566,-60\n"

# 9 levels of 9 aliases: 342 bytes that a plain safe_load expands to 9^9 = 387 million strings.
BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{n}: &{n} [{','.join(['*' + p] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)


def make_experiment(folder: Path) -> Path:
    """A tiny valid experiment: one 64x48 camera, the tetam marker map, one RSSI file."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "front.yaml").write_text(CALIBRATION)
    (folder / "rig.yaml").write_text(RIG)
    shutil.copy(site_dir("tetam") / "marker_positions.dat", folder / "marker_positions.dat")
    w = cv2.VideoWriter(str(folder / "front.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (64, 48))
    for i in range(3):
        w.write(np.full((48, 64, 3), 40 * i, np.uint8))
    w.release()
    (folder / "rssi").mkdir()
    (folder / "rssi" / "aabbccddeeff.mbd").write_text(GOOD_ROW * 3)
    (folder / "experiment.yaml").write_text(EXPERIMENT + SYNC)
    return folder / "experiment.yaml"


def write(rel: str, data: str | bytes) -> Callable[[Path], None]:
    def mutate(folder: Path) -> None:
        p = folder / rel
        if isinstance(data, bytes):
            p.write_bytes(data)
        else:
            p.write_text(data)

    return mutate


def sync(text: str) -> Callable[[Path], None]:
    return write("experiment.yaml", EXPERIMENT + "sync:\n" + text)


def rssi(text: str | bytes) -> Callable[[Path], None]:
    return write("rssi/aabbccddeeff.mbd", text)


DAT_ROW = "0: [6.38, 5.93, 2.00]:[1.5707963267948966, 0, -1.5707963267948966]\n"

# (id, mutation of the valid experiment, what the one-line message must contain)
EXPERIMENT_CASES = [
    (
        "video_start NaN",
        sync("  mode: manual\n  video_start: {front: .nan}\n"),
        "sync.video_start.front",
    ),
    (
        "video_start 1e300",
        sync("  mode: manual\n  video_start: {front: 1.0e+300}\n"),
        "sync.video_start.front",
    ),
    ("video_start '1e300'", sync("  mode: manual\n  video_start: {front: 1e300}\n"), "1970"),
    (
        "video_start text",
        sync("  mode: manual\n  video_start: {front: soon}\n"),
        "must be a number",
    ),
    (
        "video_start bool",
        sync("  mode: manual\n  video_start: {front: true}\n"),
        "must be a number",
    ),
    (
        "sync key typo",
        sync(f"  mode: manual\n  video_strat: {{front: {T0}}}\n"),
        "unknown key 'sync.video_strat'",
    ),
    (
        "sync cover NaN",
        sync(f"  mode: auto\n  video_start: {{front: {T0}}}\n  min_cover_s: .nan\n"),
        "sync.min_cover_s",
    ),
    (
        "sync number text",
        sync(f"  mode: auto\n  video_start: {{front: {T0}}}\n  max_start_error: abc\n"),
        "sync.max_start_error: must be a number, not 'abc'",
    ),
    (
        "sync cover order",
        sync("  mode: auto\n  min_cover_s: 5\n  max_cover_s: 1\n"),
        "less than sync.max_cover_s",
    ),
    (
        "sync beacon",
        sync(f"  mode: manual\n  video_start: {{front: {T0}}}\n  beacon: nope\n"),
        "sync.beacon",
    ),
    (
        "marker pose NaN",
        write("marker_positions.dat", DAT_ROW + "1: [NaN, 5.59, 2.00]:[0, 0, 0]\n"),
        "marker_positions.dat:2",
    ),
    (
        "marker pose inf",
        write("marker_positions.dat", DAT_ROW + "1: [6.7, 5.59, 2.00]:[Infinity, 0, 0]\n"),
        "finite",
    ),
    (
        "marker pose 1e400",
        write("marker_positions.dat", DAT_ROW + "1: [1e400, 5.59, 2.00]:[0, 0, 0]\n"),
        "finite",
    ),
    (
        "marker id 20 digits",
        write("marker_positions.dat", "12345678901234567890: [6.7, 5.59, 2.0]:[0, 0, 0]\n"),
        "0..9999",
    ),
    (
        "marker map not UTF-8",
        write("marker_positions.dat", DAT_ROW.encode() + b"1: [6.7, \xff]:[0, 0, 0]\n"),
        "marker_positions.dat:2: not UTF-8 text (byte 0xff at offset",
    ),
    ("calibration billion laughs", write("front.yaml", BILLION_LAUGHS), "front.yaml:1: anchors"),
    (
        "calibration deep",
        write("front.yaml", "a: " + "[" * 100 + "]" * 100 + "\n"),
        "nested deeper",
    ),
    (
        "calibration not UTF-8",
        write("front.yaml", b"image_width: 64\nimage_height: \xc3\x28\n"),
        "front.yaml:2: not UTF-8",
    ),
    (
        "calibration NaN",
        write("front.yaml", CALIBRATION.replace("60.0, 0.0, 32.0", ".nan, 0.0, 32.0")),
        "non-finite",
    ),
    (
        "calibration width 1e300",
        write("front.yaml", CALIBRATION.replace("image_width: 64", "image_width: 1.0e+300")),
        "image_width",
    ),
    (
        "rig alias",
        write("rig.yaml", RIG.replace("cameras:", "x: &r [1]\ny: *r\ncameras:")),
        "anchors",
    ),
    ("video empty", write("front.mp4", b""), "front.mp4: cannot open as video"),
    (
        "video random bytes",
        write("front.mp4", bytes(range(256)) * 12),
        "front.mp4: cannot open as video",
    ),
    ("experiment huge int", write("experiment.yaml", "x: " + "9" * 5000 + "\n"), "experiment.yaml"),
    (
        "refine sigma 1e400",
        write(
            "experiment.yaml", EXPERIMENT + SYNC + "refine: {survey_sigma_m: 1" + "0" * 400 + "}\n"
        ),
        "refine.survey_sigma_m",
    ),
    (
        "refine marker key inf",
        write("experiment.yaml", EXPERIMENT + SYNC + "refine: {markers: {.inf: unknown}}\n"),
        "is not a marker id",
    ),
]

# (id, mutation, message) for `annotator run`, which reads the RSSI files before any video
RUN_CASES = [
    (
        "mbd not UTF-8",
        rssi(GOOD_ROW.encode() + b"1700000002.0,aabbccddeeff,\xff\xfe,-60\n"),
        "aabbccddeeff.mbd:2: not UTF-8 text (byte 0xff at offset 74)",
    ),  # 48 + 26 bytes before it
    (
        "mbd RSSI beyond int16",
        rssi(GOOD_ROW + f"{T0 + 2},aabbccddeeff,112233445566,40000\n"),
        "-128..127",
    ),
    (
        "mbd RSSI huge",
        rssi(GOOD_ROW + f"{T0 + 2},aabbccddeeff,112233445566,{'9' * 30}\n"),
        "-128..127",
    ),
    (
        "mbd timestamp 1e30",
        rssi(GOOD_ROW + f"1{'0' * 30}.5,aabbccddeeff,112233445566,-60\n"),
        "1970..2100",
    ),
    (
        "mbd timestamp 1e30 spelled",
        rssi(GOOD_ROW + "1e30,aabbccddeeff,112233445566,-60\n"),
        "not a timestamp",
    ),
    ("run.yaml billion laughs", write("rssi/run.yaml", BILLION_LAUGHS), "run.yaml:1: anchors"),
]


def invoke(args: list[str]):
    return CliRunner().invoke(app, args)


def assert_one_line_error(res, must_contain: str) -> str:
    assert res.exit_code == 1, (res.exit_code, res.output, res.exception)
    assert isinstance(res.exception, SystemExit), f"escaped: {res.exception!r}"
    text = res.stderr
    assert "Traceback" not in text
    assert "Traceback" not in res.stdout
    lines = text.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: "), lines[0]
    assert must_contain in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_experiment(tmp_path_factory.mktemp("template") / "exp").parent


@pytest.fixture
def experiment(template: Path, tmp_path: Path) -> Path:
    shutil.copytree(template, tmp_path / "exp")
    return tmp_path / "exp"


def test_the_template_experiment_is_valid(experiment: Path):
    from annotator.io.experiment import load_experiment

    exp = load_experiment(experiment / "experiment.yaml")
    assert exp.video_start == {"front": T0}
    assert len(exp.markers.markers) == 30


def test_sync_values_are_checked_and_normalised(experiment: Path):
    """Good values pass and come out as the pipeline reads them: floats and a 12-hex MAC."""
    from annotator.io.experiment import SyncSettings, load_experiment

    sync(
        "  mode: auto\n  video_start: {front: 1.7e9}\n  beacon: 'AA:BB:CC:DD:EE:FF'\n"
        "  min_cover_s: 1\n  max_cover_s: 4\n  max_start_error: 30\n"
    )(experiment)
    exp = load_experiment(experiment / "experiment.yaml")
    assert exp.sync_mode == "auto"
    assert exp.video_start == {"front": 1.7e9}  # YAML 1.1 reads 1.7e9 as a string: accepted
    assert exp.sync == SyncSettings(
        mode="auto",
        video_start={"front": 1.7e9},
        beacon="aabbccddeeff",
        min_cover_s=1.0,
        max_cover_s=4.0,
        max_start_error=30.0,
    )


@pytest.mark.parametrize(
    ("mutate", "message"), [c[1:] for c in EXPERIMENT_CASES], ids=[c[0] for c in EXPERIMENT_CASES]
)
@pytest.mark.parametrize("command", ["track", "run"])
def test_bad_experiment_files_are_one_line_errors(
    experiment: Path, tmp_path: Path, command: str, mutate, message: str
):
    mutate(experiment)
    res = invoke(
        [
            command,
            str(experiment / "experiment.yaml"),
            "--out",
            str(tmp_path / "out"),
            "--jobs",
            "1",
        ]
    )
    line = assert_one_line_error(res, message)
    assert str(experiment) in line  # names the file
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("mutate", "message"), [c[1:] for c in RUN_CASES], ids=[c[0] for c in RUN_CASES]
)
def test_bad_rssi_files_are_one_line_errors_before_any_progress(
    experiment: Path, tmp_path: Path, mutate, message: str
):
    mutate(experiment)
    res = invoke(
        ["run", str(experiment / "experiment.yaml"), "--out", str(tmp_path / "out"), "--jobs", "1"]
    )
    line = assert_one_line_error(res, message)  # one line: no progress display before it
    assert str(experiment / "rssi") in line


# --- fingerprints / radiomap / evaluate -------------------------------------------------------


def _fpt(tmp_path: Path, content: str | bytes) -> Path:
    folder = tmp_path / "fpt"
    folder.mkdir()
    shutil.copy(DATASET / "fpt" / "sensor10_2.59_2.19_2.05.mbd", folder)
    bad = folder / "sensor11_2.59_2.19_2.05.mbd"
    bad.write_bytes(content if isinstance(content, bytes) else content.encode())
    return folder


BINS = "[" + ", ".join(f"{float(v)}" for v in range(-100, -19)) + "]"
HIST = "[" + ", ".join(["0.0"] * 79 + ["1.0"]) + "]"
HST_HEAD = f'Bins:{BINS}\nDongles:{{"000000000101": [[1.0, 2.0, 3.0], 0, "s"]}}\nBeacons:{{}}\n'
GOOD_HST = (
    HST_HEAD
    + f'Fingerprints:{{"(1.0, 2.0, 1.0)": {{"000000000101": {{"e78f135624ce": {HIST}}}}}}}\n'
)
TRAJ_HEAD = "t,x,y,z,r11,r12,r13,r21,r22,r23,r31,r32,r33\n"
TRAJ_ROW = "{t},1,2,3,1,0,0,0,1,0,0,0,1\n"
GOOD_TRAJ = TRAJ_HEAD + "".join(TRAJ_ROW.format(t=T0 + i) for i in range(5))


def fingerprints_case(content: str | bytes) -> Callable[[Path], list[str]]:
    def args(tmp_path: Path) -> list[str]:
        return ["fingerprints", str(_fpt(tmp_path, content)), "--out", str(tmp_path / "x.hst")]

    return args


def radiomap_case(hst: str | bytes, occ: str | bytes | None = None) -> Callable[[Path], list[str]]:
    def args(tmp_path: Path) -> list[str]:
        p = tmp_path / "in.hst"
        p.write_bytes(hst if isinstance(hst, bytes) else hst.encode())
        extra = ["--cell", "1.0"]
        if occ is not None:
            o = tmp_path / "in.occ"
            o.write_bytes(occ if isinstance(occ, bytes) else occ.encode())
            extra = ["--occupancy", str(o)]
        return ["radiomap", str(p), "--out", str(tmp_path / "maps"), "--no-plots", *extra]

    return args


def evaluate_case(traj: str | bytes, path_yaml: str | None = None) -> Callable[[Path], list[str]]:
    def args(tmp_path: Path) -> list[str]:
        t = tmp_path / "trajectory.csv"
        t.write_bytes(traj if isinstance(traj, bytes) else traj.encode())
        if path_yaml is None:
            truth = tmp_path / "truth.csv"
            truth.write_text(GOOD_TRAJ)
            return ["evaluate", str(t), "--truth", str(truth)]
        p = tmp_path / "path.yaml"
        p.write_text(path_yaml)
        return ["evaluate", str(t), "--path", str(p)]

    return args


def deep(n: int) -> str:
    return "[" * n + "]" * n


OTHER_CASES = [
    (
        "fingerprints mbd not UTF-8",
        fingerprints_case(b"1581249601.1,aabbccddeeff,112233445566,-60\n\xff\n"),
        "sensor11_2.59_2.19_2.05.mbd:2: not UTF-8",
    ),
    (
        "fingerprints RSSI beyond int16",
        fingerprints_case("1581249601.1,aabbccddeeff,112233445566,99999\n"),
        "-128..127",
    ),
    (
        "fingerprints timestamp 1e30",
        fingerprints_case(f"1{'0' * 30},aabbccddeeff,112233445566,-60\n"),
        "1970..2100",
    ),
    (
        "fingerprints pose NaN",
        fingerprints_case("1581249601.1,aabbccddeeff,112233445566,-60,nan,1,1,1,0,0,0,1,0,0,0,1\n"),
        "finite",
    ),
    (
        "radiomap hst not UTF-8",
        radiomap_case(GOOD_HST.encode().replace(b'"s"', b'"\xff"')),
        "in.hst:2: not UTF-8",
    ),
    (
        "radiomap hst deep key",
        radiomap_case(
            HST_HEAD + 'Fingerprints:{"' + "(" * 5000 + "1.0, 2.0, 1.0" + ")" * 5000 + '": {}}\n'
        ),
        "in.hst:4",
    ),
    (
        "radiomap hst deep value",
        radiomap_case(HST_HEAD + f"Fingerprints:{deep(100_000)}\n"),
        "nested deeper",
    ),
    (
        "radiomap hst huge number",
        radiomap_case(GOOD_HST.replace("[1.0, 2.0, 3.0]", "[1" + "0" * 400 + ", 2, 3]")),
        "in.hst:2",
    ),
    ("radiomap hst NaN histogram", radiomap_case(GOOD_HST.replace(", 1.0]}", ", NaN]}")), "finite"),
    ("radiomap occ deep JSON", radiomap_case(GOOD_HST, deep(50_000) + "::1.0\n"), "in.occ:1"),
    (
        "radiomap occ not UTF-8",
        radiomap_case(GOOD_HST, b"[[0.0, 0.0], [2.0, 2.0]]::1.0\n[0.0, 0.0]::\xff\n"),
        "in.occ:2: not UTF-8",
    ),
    (
        "evaluate trajectory not UTF-8",
        evaluate_case(GOOD_TRAJ.encode() + b"\xfe\n"),
        "trajectory.csv:7: not UTF-8",
    ),
    (
        "evaluate trajectory inf",
        evaluate_case(GOOD_TRAJ + TRAJ_ROW.format(t=T0 + 9).replace(",2,", ",inf,")),
        "trajectory.csv:7: y",
    ),
    (
        "evaluate trajectory t NaN",
        evaluate_case(GOOD_TRAJ + "nan,1,2,3,1,0,0,0,1,0,0,0,1\n"),
        "trajectory.csv:7: t",
    ),
    (
        "evaluate trajectory t 1e30",
        evaluate_case(GOOD_TRAJ + TRAJ_ROW.format(t="1e30")),
        "1970..2100",
    ),
    (
        "evaluate path billion laughs",
        evaluate_case(GOOD_TRAJ, BILLION_LAUGHS),
        "path.yaml:1: anchors",
    ),
    ("evaluate path deep", evaluate_case(GOOD_TRAJ, "waypoints: " + deep(200)), "nested deeper"),
]


@pytest.mark.parametrize(
    ("make_args", "message"), [c[1:] for c in OTHER_CASES], ids=[c[0] for c in OTHER_CASES]
)
def test_bad_files_of_the_other_commands_are_one_line_errors(
    tmp_path: Path, make_args, message: str
):
    res = invoke(make_args(tmp_path))
    assert_one_line_error(res, message)


def test_a_good_evaluate_still_works(tmp_path: Path):
    """The checks refuse bad files only: the same commands on good files succeed."""
    res = invoke(evaluate_case(GOOD_TRAJ)(tmp_path))
    assert res.exit_code == 0, res.output
    res = invoke(radiomap_case(GOOD_HST)(tmp_path))
    assert res.exit_code == 0, res.output


# --- as a real process ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("mutate", "command", "message"),
    [
        (rssi(GOOD_ROW.encode() + b"\xff\n"), "run", "aabbccddeeff.mbd:2: not UTF-8"),
        (write("front.yaml", BILLION_LAUGHS), "track", "anchors (&a) are not allowed"),
        (
            sync("  mode: manual\n  video_start: {front: 1.0e+300}\n"),
            "run",
            "sync.video_start.front",
        ),
        # FFmpeg writes to the process's stderr itself, which only a real process shows
        (write("front.mp4", bytes(range(256)) * 12), "track", "front.mp4: cannot open as video"),
    ],
    ids=["run-mbd", "track-billion-laughs", "run-video-start", "track-not-a-video"],
)
def test_the_annotator_process_prints_one_line_and_exits_1(
    experiment: Path, tmp_path: Path, mutate, command: str, message: str
):
    mutate(experiment)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "annotator.cli",
            command,
            str(experiment / "experiment.yaml"),
            "--out",
            str(tmp_path / "out"),
            "--jobs",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1, lines
    assert message in lines[0]
    assert res.stdout == ""
