"""Receiver mode's configuration (issue 36): `receiver:` in experiment.yaml (exclusive with
sync.beacon), the antennas the bundle carries in rig.yaml, and the outputs written per beacon
heard, with the receiver antenna's path as the truth `annotator score` takes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.labeling import label_readings
from annotator.core.trajectory import Trajectory
from annotator.errors import ConfigError, NoDataError
from annotator.io.experiment import load_experiment
from annotator.io.outputs import write_annotated_mbd
from annotator.io.rssi import RssiTable, receiver_readings
from annotator.io.scoring import read_truth
from annotator.io.trajectory import write_trajectory
from bgt_core.formats.mbd import iter_rows
from tests.annotator.io.test_input_fuzz import make_experiment


def test_receiver_and_antennas_load(tmp_path: Path) -> None:
    exp = make_experiment(tmp_path / "exp")
    loaded = load_experiment(exp)
    assert loaded.receiver is None
    assert np.array_equal(loaded.rig.antenna("receiver"), np.zeros(3))
    exp.write_text(exp.read_text() + "receiver: 'DC:A6:32:B0:D1:E5'\n")
    rig = exp.parent / "rig.yaml"
    rig.write_text(rig.read_text() + "antennas: {receiver: [0.0, 0.05, 0.1]}\n")
    loaded = load_experiment(exp)
    assert loaded.receiver == "dca632b0d1e5"
    assert np.allclose(loaded.rig.antenna("receiver"), [0.0, 0.05, 0.1])
    assert np.array_equal(loaded.rig.antenna("beacon"), np.zeros(3))


@pytest.mark.parametrize(
    ("experiment", "rig", "says"),
    [
        ("receiver: 020000000001\n", "", "receiver: 2147483649 was read as a number; quote"),
        ("receiver: phone\n", "", "receiver: not a MAC address: 'phone'"),
        (
            "receiver: aabbccddeeff\n",
            "",
            "receiver and sync.beacon exclude each other",
        ),
        ("", "antennas: {receiver: [0, 0, 3]}\n", "antennas.receiver: 3 m from the bundle"),
        ("", "antennas: {receiver: [0, 0]}\n", r"antennas.receiver: expected shape \(3,\)"),
    ],
)
def test_receiver_config_errors(tmp_path: Path, experiment: str, rig: str, says: str) -> None:
    exp = make_experiment(tmp_path / "exp")
    text = exp.read_text()
    if "exclude" in says:
        text = text.replace("sync:\n", "sync:\n  beacon: '112233445566'\n")
    exp.write_text(text + experiment)
    rig_path = exp.parent / "rig.yaml"
    rig_path.write_text(rig_path.read_text() + rig)
    with pytest.raises(ConfigError, match=says) as err:
        load_experiment(exp)
    assert "\n" not in str(err.value)


def test_at_point_moves_by_the_rotated_lever() -> None:
    rot = Rotation.from_euler("z", [[0.0], [90.0]], degrees=True)
    traj = Trajectory.from_rotation(np.array([0.0, 1.0]), np.array([[1.0, 2.0, 3.0]] * 2), rot)
    moved = traj.at_point(np.array([0.1, 0.0, 0.2]))
    assert np.allclose(moved.position, [[1.1, 2.0, 3.2], [1.0, 2.1, 3.2]])
    assert np.array_equal(moved.rotation, traj.rotation)
    assert traj.at_point(np.zeros(3)) is traj


def receiver_table() -> RssiTable:
    t = 1_700_000_000 * 10**9 + np.arange(6, dtype=np.int64) * 100_000_000
    sensor = np.array(["020000000001"] * 4 + ["b827eb4521b4"] * 2)
    beacon = np.array(["aa0000000001", "aa0000000002"] * 3)
    return RssiTable(t, sensor, beacon, np.full(6, -70, dtype=np.int16))


def test_receiver_readings_are_its_own() -> None:
    table = receiver_readings(receiver_table(), "020000000001")
    assert len(table) == 4
    assert set(table.sensor) == {"020000000001"}
    with pytest.raises(NoDataError, match="receiver 0a0000000000 took no readings .*sensors: 02"):
        receiver_readings(receiver_table(), "0a0000000000")


def test_files_per_beacon_and_the_antennas_truth(tmp_path: Path) -> None:
    table = receiver_readings(receiver_table(), "020000000001")
    t = 1_700_000_000.0 + np.arange(-10, 11) * 0.1
    position = np.column_stack([1.0 + (t - t[0]) / 2, np.ones(21), np.ones(21)])
    traj = Trajectory.from_rotation(t, position, Rotation.identity(21))
    antenna = np.array([0.0, 0.05, 0.1])
    labels = label_readings(traj.at_point(antenna), table.t_ns)
    written = write_annotated_mbd(tmp_path / "annotated", table, labels, by="beacon")
    assert sorted(written) == ["aa0000000001", "aa0000000002", "all"]
    rows = list(iter_rows(written["aa0000000002"]))
    assert {r.beacon for r in rows} == {"aa0000000002"}
    assert len(rows) == 2
    # reading at T0 + 0.1 s: the bundle's origin is at (1.55, 1, 1), the receiver 5 cm left, 10 up
    assert [float(v) for v in rows[0].rest[:3]] == pytest.approx([1.55, 1.05, 1.1])
    # a run directory's truth is the labelled antenna's path when there is one
    write_trajectory(tmp_path / "trajectory.csv", traj)
    assert read_truth(tmp_path).position[0] == pytest.approx([1.0, 1.0, 1.0])
    write_trajectory(tmp_path / "receiver_trajectory.csv", traj.at_point(antenna))
    assert read_truth(tmp_path).position[0] == pytest.approx([1.0, 1.05, 1.1])
