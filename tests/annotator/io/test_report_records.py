"""report.json as a typed record: what build_report writes reads back, older files read, and a
file that is not a report is refused in one line naming it."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from annotator.core.labeling import label_readings
from annotator.core.trajectory import Trajectory
from annotator.io.outputs import build_report, write_report
from annotator.io.report_records import REPORT_VERSION, ReportError, read_report
from annotator.io.rssi import RssiTable

T0 = 1_700_000_000.0


def small_report() -> dict:
    t = T0 + np.arange(50) * 0.1
    traj = Trajectory(
        t,
        np.column_stack([t - T0, np.ones(50), np.full(50, 1.5)]),
        np.repeat(np.eye(3)[None], 50, axis=0),
        {"sigma_m": np.full(50, 0.005), "markers": np.full(50, 2)},
    )
    t_ns = ((T0 + np.array([0.55, 1.05, 2.25, 9.0])) * 1e9).astype(np.int64)  # the last unposed
    table = RssiTable(
        t_ns,
        np.array(["b827eb4521b4", "b827eb4521b5", "b827eb4521b4", "b827eb4521b5"]),
        np.array(["e78f135624ce"] * 4),
        np.array([-60, -70, -65, -80], dtype=np.int16),
    )
    labels = label_readings(traj, table.t_ns)
    sync = SimpleNamespace(mode="manual", clocks={}, video_events={}, slates={}, rssi_events=[])
    return build_report(
        experiment="exp/experiment.yaml",
        sync=sync,
        beacon="e78f135624ce",
        readings_total=4,
        table=table,
        labels=labels,
        traj_t=traj.t,
        traj_valid=np.ones(50, dtype=bool),
        max_gap=0.2,
        method="rig",
    )


def test_what_build_report_writes_reads_back_as_a_version_1_record(tmp_path: Path) -> None:
    report = small_report()
    assert report["version"] == REPORT_VERSION == 1
    assert report["per_sensor"] == {
        "b827eb4521b4": {"readings": 2, "labelled": 2},
        "b827eb4521b5": {"readings": 2, "labelled": 1},
    }
    assert "per_beacon" not in report
    back = read_report(write_report(tmp_path / "report.json", report))
    assert back["counts"]["readings_of_beacon"] == 4
    assert back["tracked_span"] == {"start": T0, "stop": T0 + 4.9, "poses": 50, "frames": 50}
    assert back["sync"] == {"mode": "manual", "cameras": {}, "rssi_events": []}
    assert back == json.loads((tmp_path / "report.json").read_text())


def test_a_report_from_before_the_version_key_reads_as_version_1(tmp_path: Path) -> None:
    old = json.loads(json.dumps(small_report()))
    del old["version"]
    (tmp_path / "report.json").write_text(json.dumps(old))
    assert read_report(tmp_path / "report.json") == {**old, "version": 1}


@pytest.mark.parametrize(
    ("mangle", "says"),
    [
        (lambda d: [d], "not a report.json"),
        (lambda d: {**d, "version": 2}, "report version 2"),
        (lambda d: {k: v for k, v in d.items() if k != "coverage"}, "coverage is missing"),
        (lambda d: {**d, "counts": [1, 2]}, "counts is missing or not an object"),
        (lambda d: {**d, "sync": {"mode": "auto"}}, "sync.cameras is missing"),
        (lambda d: {**d, "experiment": 3}, "experiment must be a string"),
        (lambda d: {**d, "refinement": "none"}, "refinement must be an object"),
    ],
)
def test_a_file_that_is_not_a_report_is_one_line_naming_it(
    tmp_path: Path, mangle, says: str
) -> None:
    path = tmp_path / "report.json"
    path.write_text(json.dumps(mangle(json.loads(json.dumps(small_report())))))
    with pytest.raises(ReportError) as err:
        read_report(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: ")
    assert says in msg
    assert "\n" not in msg


def test_unreadable_and_garbled_files_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match="cannot read"):
        read_report(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"version": 1,')
    with pytest.raises(ReportError, match="not JSON"):
        read_report(tmp_path / "bad.json")
