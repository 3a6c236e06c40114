"""state.json as a typed, versioned record (collector/run_state.py): what the writer writes reads
back the same, and a damaged or foreign file is one line naming it."""

from __future__ import annotations

import json

import pytest

from bgt_core.messages import ClockSample
from collector.errors import CollectorError
from collector.run_state import STATE_VERSION, RunState, SensorRecord
from collector.store import RunWriter

T0 = 1_795_318_500 * 10**9


def _state() -> RunState:
    return RunState(
        run_id="r1",
        name="walk-03",
        start_ns=T0,
        meta={"site": "tetam"},
        readings=12,
        files={"pi-1/b827eb4521b4": 640},
        sensors={
            "pi-1/b827eb4521b4": SensorRecord(readings=12, batches=3, beacons={"e78f135624ce": 12})
        },
        tracker={"streams": {}},
        lost_base={"pi-1/boot/b827eb4521b4": 2},
        clock={"pi-1": (ClockSample("2026-11-27T20:00:00.000Z", 1.5, 0.8),)},
        restarts=1,
        quarantined_bytes=77,
    )


def test_a_state_survives_its_json_round_trip() -> None:
    st = _state()
    doc = json.loads(json.dumps(st.to_dict()))
    assert doc["version"] == STATE_VERSION
    assert doc["active"] is True
    assert RunState.from_dict(doc, "state.json") == st


def test_the_run_writer_records_what_it_wrote(tmp_path) -> None:
    w = RunWriter(tmp_path, "r1", "walk-03", T0, {"site": "tetam"})
    w.append("pi-1", "b827eb4521b4", "x\n" * 3, 3)
    w.fsync()
    st = w.state(restarts=2)
    w.close()
    assert (st.run_id, st.name, st.start_ns, st.readings, st.restarts) == (
        "r1",
        "walk-03",
        T0,
        3,
        2,
    )
    assert st.files == {"pi-1/b827eb4521b4": 6}
    assert st.sensors["pi-1/b827eb4521b4"]["readings"] == 3
    again = RunWriter(tmp_path, "r1", "walk-03", T0, {"site": "tetam"}, resume=st)
    assert again.readings == 3
    assert again.sensors[("pi-1", "b827eb4521b4")].batches == 1
    again.close()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"version": 1}, r"state.json: version 1 state of an unfinished run, written by an older"),
        ({"start_ns": "soon"}, r"state.json: cannot resume the run: ValueError"),
        (
            {"files": ["a"]},
            r"state.json: cannot resume the run: TypeError\('files is not a mapping'",
        ),
        ({"sensors": {"a/b": {"readings": 1}}}, r"cannot resume the run: KeyError\('batches'\)"),
    ],
)
def test_a_damaged_state_is_one_line_naming_the_file(change: dict, message: str) -> None:
    doc = {**_state().to_dict(), **change}
    with pytest.raises(CollectorError, match=message) as e:
        RunState.from_dict(doc, "state.json")
    assert "\n" not in str(e.value)


def test_not_a_mapping_is_not_a_state_file() -> None:
    with pytest.raises(CollectorError, match="state.json: not a collector state file"):
        RunState.from_dict([1, 2], "state.json")
