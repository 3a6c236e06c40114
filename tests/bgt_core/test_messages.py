"""The typed control messages: what each one reads and writes, and the one-line errors that name
the bad field. The durable file replacement they share the core with is checked at the end."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from bgt_core import wire
from bgt_core.atomic import FileOps, temp_path, write_atomic
from bgt_core.control_messages import CollectorStatus, Reply, StartReply, StartRequest, StopReply
from bgt_core.messages import Ack, AgentStatus, ClockReply, ClockRequest, ClockSample, clock_offset


def test_clock_offset_is_the_four_timestamp_estimate() -> None:
    # The peer is 30 ms ahead; 2 ms out, 1 ms inside the peer, 4 ms back.
    t1 = 1_800_000_000_000_000_000
    t2 = t1 + 2_000_000 + 30_000_000
    t3 = t2 + 1_000_000
    t4 = t1 + 7_000_000
    assert clock_offset(t1, t2, t3, t4) == (29_000_000, 6_000_000)
    s = ClockSample.measure(ClockReply(t1, t2, t3, {"stratum": 2}), t1, t4, "at")
    assert (s.offset_ms, s.rtt_ms, s.chrony) == (29.0, 6.0, {"stratum": 2})
    assert ClockSample.from_dict(s.to_dict()) == s


@pytest.mark.parametrize(
    "msg",
    [
        ClockRequest(5),
        ClockReply(1, 2, 3, None),
        Ack("0123456789abcdef", {"b827eb4521b4": 7}),
        StartRequest("walk", 50.0, True),
        StartRequest(),
        StopReply("r", "/d", 10, 1, 2, 3),
    ],
)
def test_messages_round_trip_through_json(msg) -> None:
    assert type(msg).from_dict(wire.from_json(wire.to_json(msg.to_dict()))) == msg


@pytest.mark.parametrize(
    ("cls", "data", "message"),
    [
        (ClockRequest, {"t1": "soon"}, "t1 must be an integer (ns), got 'soon'"),
        (ClockReply, {"t1": 1, "t2": 2.5, "t3": 3}, "clock reply needs integer t1, t2 and t3 (ns)"),
        (
            ClockReply,
            {"t1": 1, "t2": 2, "t3": 3, "chrony": 4},
            "clock reply chrony must be an object",
        ),
        (Ack, {"boot": "b", "streams": []}, "ack: streams must be an object"),
        (Ack, {"boot": "b", "streams": {"m": True}}, "ack: streams.m must be an integer, got True"),
        (Ack, {"streams": {}}, "ack: boot is missing"),
        (StartRequest, {"name": 3}, "start: name must be a string or null"),
        (StartRequest, {"max_offset_ms": -1}, "start: max_offset_ms must be a finite number"),
        (StartRequest, {"max_offset_ms": float("nan")}, "start: max_offset_ms must be a finite"),
        (StartRequest, {"max_offset_ms": float("inf")}, "start: max_offset_ms must be a finite"),
        (StartRequest, {"name": "a" * 201}, "start: name must be at most 200 printable"),
        (StartRequest, {"name": "run\x1b[2J"}, "start: name must be at most 200 printable"),
        (StartRequest, {"strict": "yes"}, "start: strict must be true or false"),
        (AgentStatus, {"agent_id": "a", "now_ns": "x"}, "agent status: now_ns must be an integer"),
        (
            AgentStatus,
            {"agent_id": "a", "adapters": [{"mac": 5}]},
            "agent status: adapters[0]: mac must be a string, got 5",
        ),
        (StopReply, {"run_id": "r", "run_dir": "d"}, "stop reply: readings is missing"),
        (
            CollectorStatus,
            {"agents": {"a": {"alive": "yes"}}},
            "status: agents.a: alive must be true",
        ),
        (
            CollectorStatus,
            {"streams": {"total": "many"}},
            "status: streams: total must be an integer",
        ),
    ],
)
def test_bad_fields_are_named_in_one_line(cls, data, message) -> None:
    with pytest.raises(wire.InvalidField) as err:
        cls.from_dict(data)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_agent_status_keeps_what_older_agents_send() -> None:
    st = AgentStatus.from_dict(
        {
            "agent_id": "pi-01",
            "version": 1.0,
            "adapters": [{"name": "hci0", "mac": "B8:27:EB:45:21:B4"}],
        }
    )
    assert (st.version, st.hostname, st.resent) == ("1.0", None, 0)
    assert st.adapter("b827eb4521b4").name == "hci0"
    assert st.adapter("000000000000") is None
    assert AgentStatus.from_dict(st.to_dict()) == st


def test_reply_envelope_and_start_reply() -> None:
    body = StartReply("r1", "/data/r1").to_dict()
    ok = Reply.from_dict({"ok": True, **body}, "start")
    assert ok.ok
    assert StartReply.from_dict(ok.body) == StartReply("r1", "/data/r1")
    failed = Reply.from_dict({"ok": False, "error": "no run is active"}, "stop")
    assert (failed.ok, failed.error) == (False, "no run is active")
    with pytest.raises(wire.InvalidField, match="stop reply: ok must be true or false"):
        Reply.from_dict({"error": "x"}, "stop")


def test_status_reads_a_partial_reply_with_defaults() -> None:
    st = CollectorStatus.from_dict({"run": {"run_id": "r", "readings": 3}, "agents": {}})
    assert st.run is not None
    assert (st.run.run_id, st.run.readings, st.run.restarts) == ("r", 3, 0)
    assert (st.disk_full, st.streams.total, st.refused_streams.by_agent) == (False, 0, {})
    assert CollectorStatus.from_dict(st.to_dict()) == st


class FailingWrite(FileOps):
    """Writes a few bytes, then the disk is full."""

    def write(self, fd: int, data: bytes | memoryview) -> int:
        if len(data) > 4:
            os.write(fd, bytes(data[:4]))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)


def test_write_atomic_replaces_whole_files_or_leaves_the_old_one(tmp_path: Path) -> None:
    target = tmp_path / "state.json"
    write_atomic(target, "old contents")
    assert target.read_text() == "old contents"
    with pytest.raises(OSError, match="No space left"):
        write_atomic(target, b"new contents that do not fit", files=FailingWrite())
    assert target.read_text() == "old contents"
    assert not temp_path(target).exists()
    write_atomic(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
