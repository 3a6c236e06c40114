"""run.yaml as a typed record: written and read back unchanged, older files read, bad ones
refused in one line."""

from __future__ import annotations

import pytest

from bgt_core.run_record import (
    RUN_VERSION,
    AgentEntry,
    BeaconCount,
    RunRecord,
    RunRecordError,
    SensorEntry,
)
from bgt_core.safe_yaml import dump, loads

START = 1_764_201_600_000_000_000  # 2025-11-27T00:00:00Z


def stopped_run() -> RunRecord:
    sensor = SensorEntry(
        adapter="hci0",
        mac="b827eb4521b4",
        file="rssi/pi-01/b827eb4521b4.mbd",
        backend="mgmt",
        mode="active",
        readings=120,
        batches=12,
        beacons={"e78f135624ce": BeaconCount(readings=120, rate_hz=2.0)},
        gaps=0,
        missing_batches=0,
        lost_batches=0,
    )
    return RunRecord(
        run_id="20251127T000000Z-hall",
        name="hall",
        start_ns=START,
        stop_ns=START + 60 * 10**9,
        readings=120,
        meta={"software_version": "0.9.0", "site": "tetam", "notes": "Ayşe walked"},
        summary={"stopped_by": "cli", "gaps": 0, "layout": "rssi/<agent>/<sensor_mac>.mbd"},
        agents={
            "pi-01": AgentEntry(
                hostname="pi-01",
                version="0.9.0",
                backend="mgmt",
                boot_ids=["b1"],
                sensors={"b827eb4521b4": sensor},
            )
        },
    )


def test_a_record_goes_through_yaml_and_comes_back_equal() -> None:
    rec = stopped_run()
    doc = rec.to_dict()
    assert doc["version"] == RUN_VERSION
    assert doc["start"] == "2025-11-27T00:00:00.000Z"
    assert doc["stop"] == "2025-11-27T00:01:00.000Z"
    # The summary keys come after the counts, in their fixed order, whatever order was given.
    keys = list(doc)
    assert (
        keys.index("readings")
        < keys.index("layout")
        < keys.index("stopped_by")
        < keys.index("gaps")
    )
    back = RunRecord.from_dict(loads(dump(doc, sort_keys=False), "run.yaml"), "run.yaml")
    assert back == rec
    assert back.stopped
    assert back.listing() == {
        "run_id": "20251127T000000Z-hall",
        "name": "hall",
        "start": "2025-11-27T00:00:00.000Z",
        "stop": "2025-11-27T00:01:00.000Z",
        "readings": 120,
    }


def test_a_summary_key_the_record_does_not_list_is_written_not_dropped() -> None:
    rec = RunRecord(run_id="r", summary={"gaps": 1, "new_counter": 5})
    doc = rec.to_dict()
    assert (doc["gaps"], doc["new_counter"]) == (1, 5)
    assert list(doc)[-1] == "agents"


def test_a_file_from_before_the_version_key_reads_as_version_1() -> None:
    old = {
        "id": "r1",
        "name": "walk",
        "start": "2025-11-27T00:00:00.000Z",
        "start_ns": START,
        "stop": None,
        "stop_ns": None,
        "software_version": "0.7.0",
        "readings": 3,
        "agents": {},
    }
    rec = RunRecord.from_dict(old, "run.yaml")
    assert (rec.version, rec.run_id, rec.readings, rec.stopped) == (1, "r1", 3, False)
    assert dict(rec.meta) == {"software_version": "0.7.0"}
    # Written back, the file gains only the version key.
    assert rec.to_dict() == {"version": 1, **old}


def test_a_minimal_file_takes_its_directorys_name() -> None:
    rec = RunRecord.from_dict({"readings": 3}, "x/run.yaml", default_id="x")
    assert (rec.run_id, rec.name, rec.start_ns, rec.readings) == ("x", None, None, 3)
    assert RunRecord.from_dict(None, "x/run.yaml", default_id="x").run_id == "x"


@pytest.mark.parametrize(
    ("doc", "says"),
    [
        (["a", "list"], "not a run.yaml"),
        ({"version": 7}, "version 7"),
        ({"readings": "many"}, "readings must be a whole number"),
        ({"start_ns": -5}, "start_ns must be a whole number"),
        ({"stop_ns": True}, "stop_ns must be a whole number"),
        ({"id": ["x"]}, "id must be a string"),
        ({"agents": ["pi-01"]}, "agents must map"),
        ({"agents": {"pi-01": {"sensors": [1]}}}, "agents.pi-01.sensors must be a mapping"),
    ],
)
def test_a_bad_key_is_one_line_naming_the_file(doc: object, says: str) -> None:
    with pytest.raises(RunRecordError) as err:
        RunRecord.from_dict(doc, "runs/r1/run.yaml")
    msg = str(err.value)
    assert msg.startswith("runs/r1/run.yaml: ")
    assert says in msg
    assert "\n" not in msg
