"""The agent's on-disk spool: round trips, restarts, kill -9, damaged files, the size bound and a
full disk (injected through FileOps, and for real on a tiny tmpfs when this machine lets us mount)."""

from __future__ import annotations

import errno
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from bgt_core import wire
from full_disk import QuotaFiles
from sensor_agent.spool import (
    ACK_FILE,
    SEGMENT_SUFFIX,
    Spool,
    SpoolError,
    encode_record,
)

WALL_NS = 1_790_000_000 * 10**9
SEG_HEAD = 20  # bytes before the first record of a segment


class FakeClock:
    """Monotonic ns that only moves when the test says so."""

    def __init__(self) -> None:
        self.now = 10**12

    def __call__(self) -> int:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += int(seconds * 1e9)


def make_payload(sensor: str, seq: int, readings: int = 1) -> bytes:
    """A real encoded batch, distinct per (sensor, seq)."""
    rows = tuple(
        wire.Reading(WALL_NS + seq * 10**8 + j, "e78f135624ce", -40 - (seq + j) % 50)
        for j in range(readings)
    )
    return wire.to_wire(wire.Batch("pi-01", "0123456789abcdef", sensor, seq, rows))


def open_spool(path: Path, max_bytes: int = 1 << 20, **kw) -> Spool:
    kw.setdefault("clock", FakeClock())
    kw.setdefault("wall_ns", lambda: WALL_NS)
    return Spool(path, max_bytes, **kw)


def segments(path: Path) -> list[Path]:
    return sorted(path.glob("*" + SEGMENT_SUFFIX))


def record_size(stream: str, payload: bytes) -> int:
    return len(encode_record(stream, 0, WALL_NS, payload))


S1, S2, S3 = (
    "0123456789abcdef/b827eb000001",
    "0123456789abcdef/b827eb000002",
    "feedc0de00000000/b827eb000001",
)


# ---------------------------------------------------------------------------------------------
# Round trips and restarts


def test_pending_returns_unacked_records_in_append_order(tmp_path: Path) -> None:
    written = []
    with open_spool(tmp_path, segment_bytes=2048) as sp:
        for seq in range(30):
            for stream in (S1, S2, S3):
                p = make_payload(stream[-12:], seq)
                assert sp.append(stream, seq, p) is True
                written.append((stream, seq, p))
        assert list(sp.pending()) == written
        assert sp.stats().records == 90
        assert sp.stats().streams == 3

        sp.ack(S1, 19)
        sp.ack(S2, 29)
        expect = [w for w in written if not (w[0] == S1 and w[1] <= 19) and w[0] != S2]
        assert list(sp.pending()) == expect
        st = sp.stats()
        assert (st.records, st.streams) == (len(expect), 2)
        # Acks never move backwards.
        sp.ack(S1, 3)
        assert sp.acked()[S1] == 19
    # Payloads come back byte for byte: they still decode to the batch that was spooled.
    first_s1 = next(p for s, _, p in expect if s == S1)
    assert wire.from_wire(first_s1).seq == 20


def test_restart_returns_only_unacked(tmp_path: Path) -> None:
    with open_spool(tmp_path, segment_bytes=1024) as sp:
        for seq in range(50):
            sp.append(S1, seq, make_payload("b827eb000001", seq))
            sp.append(S2, seq, make_payload("b827eb000002", seq))
        sp.ack(S1, 44)
        sp.ack(S2, 9)
    with open_spool(tmp_path) as sp:
        got = [(s, q) for s, q, _ in sp.pending()]
        assert sorted(got) == sorted(
            [(S1, q) for q in range(45, 50)] + [(S2, q) for q in range(10, 50)]
        )
        # Ordering across streams is append order.
        assert got[:2] == [(S2, 10), (S2, 11)]
        assert sp.acked() == {S1: 44, S2: 9}
        # New records go to a new segment; old ones are still read back after them.
        sp.append(S3, 0, b"new")
        assert list(sp.pending())[-1] == (S3, 0, b"new")


def test_fully_acked_segments_are_deleted(tmp_path: Path) -> None:
    with open_spool(tmp_path, segment_bytes=1024) as sp:
        for seq in range(100):
            sp.append(S1, seq, make_payload("b827eb000001", seq))
        n_before, bytes_before = len(segments(tmp_path)), sp.stats().bytes
        assert n_before >= 5
        sp.ack(S1, 49)
        st = sp.stats()
        # Only segments whose every record is acked go; the rest stay whole.
        assert 2 <= len(segments(tmp_path)) < n_before
        assert st.bytes < bytes_before
        assert st.bytes == sum(p.stat().st_size for p in segments(tmp_path))
        assert [q for _, q, _ in sp.pending()] == list(range(50, 100))
        sp.ack(S1, 99)
        assert sp.stats().records == 0
    # Closing deletes the last, now fully acked, segment too.
    assert segments(tmp_path) == []


def test_acks_saved_atomically_and_pruned(tmp_path: Path) -> None:
    clock = FakeClock()
    with open_spool(tmp_path, clock=clock, ack_interval_s=1.0, segment_bytes=1024) as sp:
        for seq in range(20):
            sp.append(S1, seq, b"x" * 40)
        sp.ack(S1, 5)
        assert not (tmp_path / ACK_FILE).exists()  # not due yet: acks are batched
        clock.advance(1.0)
        sp.ack(S1, 6)
        assert wire.from_json((tmp_path / ACK_FILE).read_bytes())["acked"] == {S1: 6}
        sp.ack(S2, 7)  # a stream with nothing on disk is not worth remembering
        sp.sync()
        assert wire.from_json((tmp_path / ACK_FILE).read_bytes())["acked"] == {S1: 6}
    assert not (tmp_path / (ACK_FILE + ".tmp")).exists()


def test_unreadable_ack_file_means_resend_everything(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with open_spool(tmp_path) as sp:
        for seq in range(5):
            sp.append(S1, seq, b"p%d" % seq)
        sp.ack(S1, 2)
    (tmp_path / ACK_FILE).write_bytes(b"{not json")
    with caplog.at_level(logging.WARNING), open_spool(tmp_path) as sp:
        assert [q for _, q, _ in sp.pending()] == [0, 1, 2, 3, 4]
    assert any(ACK_FILE in r.getMessage() for r in caplog.records)


# ---------------------------------------------------------------------------------------------
# Crashes: kill -9 while appending


CHILD_DETERMINISTIC = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    from sensor_agent.spool import Spool, encode_record, SEGMENT_SUFFIX
    d, n = Path(sys.argv[1]), int(sys.argv[2])
    sp = Spool(d, 1 << 20, segment_bytes=4096)
    for seq in range(n):
        sp.append("boot/aa", seq, bytes([seq % 251]) * (20 + seq % 37))
    sp.ack("boot/aa", 9)
    sp.sync()
    # The process dies half-way through the next record.
    torn = encode_record("boot/aa", n, 0, b"z" * 64)
    last = sorted(d.glob("*" + SEGMENT_SUFFIX))[-1]
    fd = os.open(last, os.O_WRONLY | os.O_APPEND)
    os.write(fd, torn[: len(torn) // 2])
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_kill9_mid_record_keeps_every_whole_record(tmp_path: Path) -> None:
    n = 200
    proc = subprocess.run(
        [sys.executable, "-c", CHILD_DETERMINISTIC, str(tmp_path), str(n)],
        capture_output=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    torn_tail = record_size("boot/aa", b"z" * 64) // 2
    with open_spool(tmp_path) as sp:
        got = list(sp.pending())
        assert got == [("boot/aa", q, bytes([q % 251]) * (20 + q % 37)) for q in range(10, n)]
        st = sp.stats()
        assert st.recovered_bytes == torn_tail
        assert st.bytes == sum(p.stat().st_size for p in segments(tmp_path))
        sp.append("boot/aa", n, b"after")
    # The cut tail left a clean file: a second reopen finds nothing to repair.
    with open_spool(tmp_path) as sp:
        assert sp.stats().recovered_bytes == 0
        assert list(sp.pending())[-1] == ("boot/aa", n, b"after")


CHILD_RACING = textwrap.dedent("""
    import sys
    from sensor_agent.spool import Spool
    sp = Spool(sys.argv[1], 1 << 22, segment_bytes=8192, ack_interval_s=0.0)
    seq = 0
    while True:
        sp.append("boot/bb", seq, seq.to_bytes(4, "big") * (1 + seq % 60))
        print("A", seq, flush=True)
        if seq % 25 == 24:
            sp.ack("boot/bb", seq - 10)
            print("K", seq - 10, flush=True)
        seq += 1
""")


def test_kill9_at_a_random_moment_loses_nothing_appended(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD_RACING, str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    last = {"A": -1, "K": -1}  # the last append and ack the child said had returned

    def note(line: str) -> None:
        kind, value = line.split()
        last[kind] = int(value)

    deadline = time.monotonic() + 60
    try:
        while last["A"] < 400 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            note(line)
    finally:
        proc.send_signal(signal.SIGKILL)
        rest, err = proc.communicate(timeout=30)
    # The child ran on until the kill: what it said meanwhile is still in the pipe (every line is
    # flushed once its call returned; a line the kill cut short is left out).
    for line in rest.splitlines(keepends=True):
        if line.endswith("\n") and len(line.split()) == 2:
            note(line)
    last_appended, last_acked = last["A"], last["K"]
    assert last_appended >= 400, err
    with open_spool(tmp_path) as sp:
        got = list(sp.pending())
    seqs = [q for _, q, _ in got]
    # Contiguous from just after some persisted ack to at least the last append we saw return.
    assert seqs == list(range(seqs[0], seqs[-1] + 1))
    assert last_acked + 1 <= seqs[0] <= last_appended
    assert seqs[-1] >= last_appended
    for _, q, p in got:
        assert p == q.to_bytes(4, "big") * (1 + q % 60)


# ---------------------------------------------------------------------------------------------
# Damaged files


def _spool_with_records(path: Path, n: int) -> list[tuple[str, int, bytes]]:
    recs = [(S1, q, make_payload("b827eb000001", q, readings=1 + q % 3)) for q in range(n)]
    with open_spool(path) as sp:
        for r in recs:
            sp.append(*r)
    return recs


def _offsets(recs: list[tuple[str, int, bytes]]) -> list[int]:
    out, off = [], SEG_HEAD
    for s, _, p in recs:
        out.append(off)
        off += record_size(s, p)
    return out + [off]


@pytest.mark.parametrize(
    "cut", [3, 14, 40, -1], ids=["in-magic", "in-header", "in-body", "last-byte"]
)
def test_truncated_tail_is_cut_and_earlier_records_survive(tmp_path: Path, cut: int) -> None:
    recs = _spool_with_records(tmp_path, 12)
    offs = _offsets(recs)
    (seg,) = segments(tmp_path)
    new_len = offs[-2] + cut if cut > 0 else offs[-1] + cut
    os.truncate(seg, new_len)
    with open_spool(tmp_path) as sp:
        assert list(sp.pending()) == recs[:-1]
        assert sp.stats().recovered_bytes == new_len - offs[-2]
        assert seg.stat().st_size == offs[-2]
        sp.append(S1, 12, b"appended after repair")
    with open_spool(tmp_path) as sp:
        assert list(sp.pending()) == [*recs[:-1], (S1, 12, b"appended after repair")]


def test_garbled_record_in_the_middle_is_skipped(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    recs = _spool_with_records(tmp_path, 12)
    offs = _offsets(recs)
    (seg,) = segments(tmp_path)
    data = bytearray(seg.read_bytes())
    for i in range(offs[5] + 20, offs[5] + 26):  # inside record 5's body
        data[i] ^= 0xFF
    seg.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING), open_spool(tmp_path) as sp:
        assert list(sp.pending()) == recs[:5] + recs[6:]
        assert sp.stats().recovered_bytes == offs[6] - offs[5]
    assert any("damaged" in r.getMessage() for r in caplog.records)
    assert seg.stat().st_size == offs[-1]  # nothing after the damage was cut


def test_garbled_tail_is_truncated(tmp_path: Path) -> None:
    recs = _spool_with_records(tmp_path, 8)
    offs = _offsets(recs)
    (seg,) = segments(tmp_path)
    with open(seg, "r+b") as f:
        f.seek(offs[-2] + 9)  # the last record's CRC
        f.write(b"\x00\x00\x00\x00")
    with open_spool(tmp_path) as sp:
        assert list(sp.pending()) == recs[:-1]
    assert seg.stat().st_size == offs[-2]


def test_foreign_and_headerless_segment_files(tmp_path: Path) -> None:
    recs = _spool_with_records(tmp_path, 3)
    (tmp_path / "0000000000000007.seg").write_bytes(b"BGTSP")  # crashed while creating it
    (tmp_path / "0000000000000009.seg").write_bytes(b"something else entirely" * 3)
    with open_spool(tmp_path) as sp:
        assert list(sp.pending()) == recs
    assert not (tmp_path / "0000000000000007.seg").exists()
    assert (tmp_path / "0000000000000009.seg.bad").exists()


# ---------------------------------------------------------------------------------------------
# The size bound


def test_size_bound_drops_oldest_segments_with_a_counted_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    payload = b"r" * 180
    rec = record_size(S1, payload)
    clock = FakeClock()
    with (
        caplog.at_level(logging.WARNING),
        open_spool(tmp_path, 8192, segment_bytes=1024, clock=clock) as sp,
    ):
        for seq in range(300):
            assert sp.append(S1, seq, payload)
            assert sp.stats().bytes <= 8192
            clock.advance(0.1)
        st = sp.stats()
        kept = [q for _, q, _ in sp.pending()]
        assert kept == list(range(300 - len(kept), 300))
        assert st.dropped_oldest == 300 - len(kept)
        assert st.records == len(kept)
        # At most one segment's worth of slack below the budget.
        assert len(kept) * rec > 8192 - 1024 - 2 * SEG_HEAD
        assert st.bytes == sum(p.stat().st_size for p in segments(tmp_path))
    warnings = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    # 30 s of simulated time: the first drop is reported, then at most one line a minute.
    assert len(warnings) == 1
    assert "dropped the" in warnings[0]


def test_dropping_acked_records_is_not_counted_as_loss(tmp_path: Path) -> None:
    with open_spool(tmp_path, 8192, segment_bytes=1024) as sp:
        for seq in range(60):
            sp.append(S1, seq, b"a" * 180)
            sp.ack(S1, seq)  # S1 is always handled at once; S2 never is
            sp.append(S2, seq, b"b" * 180)
        st = sp.stats()
        kept = [q for s, q, _ in sp.pending() if s == S2]
        assert kept == list(range(60 - len(kept), 60))
        assert len(kept) < 30  # some S2 records were dropped...
        assert st.dropped_oldest == 60 - len(kept)  # ...and only those are counted


def test_budget_smaller_than_a_segment_drops_the_open_segment(tmp_path: Path) -> None:
    with open_spool(tmp_path, 4096, segment_bytes=1 << 20) as sp:
        for seq in range(100):
            assert sp.append(S1, seq, b"q" * 100)
            assert sp.stats().bytes <= 4096
        kept = [q for _, q, _ in sp.pending()]
        assert kept == list(range(100 - len(kept), 100))
        assert len(kept) >= 1
        assert sp.stats().dropped_oldest == 100 - len(kept)
    with open_spool(tmp_path, 4096) as sp:
        assert [q for _, q, _ in sp.pending()] == kept


def test_batch_larger_than_the_budget_is_refused(tmp_path: Path) -> None:
    with open_spool(tmp_path, 4096) as sp:
        assert sp.append(S1, 0, b"small")
        assert sp.append(S1, 1, b"x" * 5000) is False
        assert sp.stats().unspooled == 1
        assert list(sp.pending()) == [(S1, 0, b"small")]


# ---------------------------------------------------------------------------------------------
# Full disk


def test_full_disk_stops_cleanly_and_resumes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    files, clock = QuotaFiles(free=3000), FakeClock()
    stored: list[tuple[str, int, bytes]] = []
    refused = 0
    with (
        caplog.at_level(logging.WARNING),
        open_spool(
            tmp_path, clock=clock, files=files, retry_interval_s=5.0, ack_interval_s=0.0
        ) as sp,
    ):
        seq = 0
        while sp.append(S1, seq, b"%05d" % seq * 30):
            stored.append((S1, seq, b"%05d" % seq * 30))
            seq += 1
            assert seq < 100
        refused += 1
        st = sp.stats()
        assert st.disk_full
        assert not st.writing
        assert st.last_error == os.strerror(errno.ENOSPC)
        assert 10 <= len(stored) < 30
        # The partial record was rolled back: the segment holds exactly the whole records.
        (seg,) = segments(tmp_path)
        assert seg.stat().st_size == SEG_HEAD + sum(record_size(s, p) for s, _, p in stored)
        # While paused nothing touches the disk; the batches are counted.
        writes = files.writes
        for k in range(1, 6):
            assert sp.append(S1, seq + k, b"late") is False
            refused += 1
        assert files.writes == writes
        # Saving acks fails too, but the old acks.json stays intact.
        sp.ack(S1, 0)
        assert not (tmp_path / ACK_FILE).exists() or wire.from_json(
            (tmp_path / ACK_FILE).read_bytes()
        )
        # Space returns; nothing is retried before the retry interval.
        files.free = 10**6
        clock.advance(4.0)
        assert sp.append(S1, seq + 6, b"still paused") is False
        refused += 1
        clock.advance(1.5)
        assert sp.append(S1, seq + 7, b"resumed")
        stored.append((S1, seq + 7, b"resumed"))
        st = sp.stats()
        assert not st.disk_full
        assert st.writing
        assert st.unspooled == refused
        assert list(sp.pending()) == stored[1:]
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1
    assert "disk full" in errors[0].getMessage()
    assert any(
        "writing again" in r.getMessage() and f"{refused} batches" in r.getMessage()
        for r in caplog.records
    )
    with open_spool(tmp_path) as sp:
        assert sp.stats().recovered_bytes == 0
        assert list(sp.pending()) == stored[1:]


@pytest.fixture
def tiny_fs(tmp_path: Path):
    """A 64 KiB tmpfs, or a skip saying why there is none."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip(
            "mounting a 64 KiB tmpfs needs root; the FileOps fault-injection test "
            "covers the full-disk path"
        )
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0:
        pytest.skip(
            f"cannot mount a tmpfs here ({r.stderr.strip()}); the FileOps "
            "fault-injection test covers the full-disk path"
        )
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_full_disk_on_a_real_tiny_filesystem(tiny_fs: Path) -> None:
    filler = tiny_fs / "filler"
    filler.write_bytes(b"\0" * 24 * 1024)
    spool_dir, clock = tiny_fs / "spool", FakeClock()
    stored = []
    with open_spool(spool_dir, 1 << 20, segment_bytes=8192, clock=clock) as sp:
        for seq in range(500):
            p = make_payload("b827eb000001", seq, readings=20)
            if not sp.append(S1, seq, p):
                break
            stored.append((S1, seq, p))
        assert 0 < len(stored) < 500
        st = sp.stats()
        assert st.disk_full
        assert st.last_error == os.strerror(errno.ENOSPC)
        filler.unlink()
        clock.advance(10)
        p = make_payload("b827eb000001", 999, readings=20)
        assert sp.append(S1, 999, p)
        stored.append((S1, 999, p))
        assert not sp.stats().disk_full
    with open_spool(spool_dir, 1 << 20) as sp:
        assert sp.stats().recovered_bytes == 0
        assert list(sp.pending()) == stored


# ---------------------------------------------------------------------------------------------
# Misuse


def test_one_process_per_spool_directory(tmp_path: Path) -> None:
    with open_spool(tmp_path), pytest.raises(SpoolError, match="in use by another agent"):
        open_spool(tmp_path)
    open_spool(tmp_path).close()  # released on close


def test_unusable_directory_is_a_one_line_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a directory")
    with pytest.raises(SpoolError, match=r"spool directory .*file/spool is not usable"):
        open_spool(tmp_path / "file" / "spool")


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="max_bytes"):
        Spool(tmp_path, 100)
    with open_spool(tmp_path) as sp:
        with pytest.raises(ValueError, match="stream"):
            sp.append("", 0, b"x")
        with pytest.raises(ValueError, match="stream"):
            sp.append("s" * 300, 0, b"x")
        with pytest.raises(ValueError, match="seq"):
            sp.append(S1, -1, b"x")
    with pytest.raises(SpoolError, match="closed"):
        sp.append(S1, 0, b"x")
