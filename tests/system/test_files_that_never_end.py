"""Files that never end, in the places a user names files (issue 35): /dev/zero or a FIFO as
the marker map, an RSSI file, a replay file and a run's run.yaml are each one line within 2 s,
at bounded memory; before, /dev/zero grew to 5 GB and a FIFO hung forever."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from annotator.io.experiment import load_experiment
from annotator.io.rssi import load_rssi
from collector.store import export_merged, list_runs
from sensor_agent.errors import BackendError
from sensor_agent.scanning.replay import ReplayBackend
from tests.annotator.io.test_input_fuzz import make_experiment


def _endless(path: Path, kind: str) -> None:
    path.unlink(missing_ok=True)
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")


def _one_line_fast(
    call: Callable[[], object], error: type[Exception] | tuple[type[Exception], ...]
) -> str:
    t = time.monotonic()
    with pytest.raises(error) as err:
        call()
    assert time.monotonic() - t < 2.0
    message = str(err.value)
    assert "\n" not in message
    assert "not a regular file" in message
    return message


@pytest.mark.parametrize("kind", ["zero", "fifo"])
def test_marker_map_and_rssi_file(tmp_path: Path, kind: str) -> None:
    exp = make_experiment(tmp_path / "exp")
    _endless(exp.parent / "marker_positions.dat", kind)
    from bgt_core.formats.markers import MarkerMapError

    _one_line_fast(lambda: load_experiment(exp), MarkerMapError)
    exp = make_experiment(tmp_path / "exp2")
    _endless(exp.parent / "rssi" / "aabbccddeeff.mbd", kind)
    from annotator.errors import AnnotatorError
    from bgt_core.formats.mbd import MbdError

    _one_line_fast(lambda: load_rssi(exp.parent / "rssi"), (MbdError, AnnotatorError))


@pytest.mark.parametrize("kind", ["zero", "fifo"])
def test_replay_file(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "rec.mbd"
    _endless(path, kind)
    _one_line_fast(lambda: ReplayBackend([path]).check(), BackendError)


def test_run_files_of_the_collector(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    good, bad = tmp_path / "20260101T000000Z-good", tmp_path / "20260102T000000Z-bad"
    (good / "rssi" / "pi-1").mkdir(parents=True)
    (good / "run.yaml").write_text("id: 20260101T000000Z-good\nname: good\nreadings: 1\n")
    (good / "rssi" / "pi-1" / "aabbccddeeff.mbd").write_text(
        "1700000000.5,aabbccddeeff,112233445566,-60\n"
    )
    bad.mkdir()
    os.mkfifo(bad / "run.yaml")
    t = time.monotonic()
    runs = list_runs(tmp_path)  # the FIFO run.yaml is skipped with a warning, not waited on
    assert time.monotonic() - t < 2.0
    assert [r["run_id"] for r in runs] == ["20260101T000000Z-good"]
    assert "not a regular file" in caplog.text
    assert export_merged(good, tmp_path / "merged") == {"aabbccddeeff": 1}
    _endless(good / "rssi" / "pi-1" / "aabbccddeeff.mbd", "zero")
    from collector.errors import CollectorError

    _one_line_fast(lambda: export_merged(good, tmp_path / "merged2"), CollectorError)
