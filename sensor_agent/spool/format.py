"""The spool's bytes on disk: the segment and record layouts, their constants, and reading and
writing records (CRC-checked; a torn or corrupt tail ends a scan). Also what each segment holds,
kept in memory (never the payloads)."""

from __future__ import annotations

import errno
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from sensor_agent.errors import AgentError

SEGMENT_MAGIC = b"BGTSPOOL"
SEGMENT_VERSION = 1
RECORD_MAGIC = b"BGTR"
# A batch is at most 4 MiB on the wire; anything claiming to be much larger is garbage.
MAX_RECORD_BODY = 8 * 1024 * 1024
MAX_STREAM_BYTES = 255

DEFAULT_SEGMENT_BYTES = 8 * 1024 * 1024
DEFAULT_FSYNC_INTERVAL_S = 0.2
DEFAULT_ACK_INTERVAL_S = 1.0
DEFAULT_RETRY_INTERVAL_S = 5.0
DROP_WARNING_INTERVAL_S = 60.0

ACK_FILE = "acks.json"
LOCK_FILE = "lock"
SEGMENT_SUFFIX = ".seg"

SEG_HEAD = struct.Struct("<8sHHQ")  # magic, version, reserved, segment number
_REC_HEAD = struct.Struct("<4sII")  # magic, body length, crc32(length + body)
_REC_BODY = struct.Struct("<qqB")  # seq, wall-clock ns at append, stream length
_U32 = struct.Struct("<I")

# Errors that mean "no room"; anything else (EIO, EROFS, ...) also pauses writing but is not "full".
FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


class SpoolError(AgentError):
    """The spool directory cannot be used (not creatable, not writable, owned by another process)."""


@dataclass(frozen=True, slots=True)
class SpoolStats:
    directory: str
    bytes: int  # on disk, all segments
    segments: int
    records: int  # on disk and not yet acknowledged
    streams: int  # streams with unacknowledged records
    dropped_oldest: int  # unacknowledged records deleted to stay under max_bytes
    unspooled: int  # batches that could not be written (disk full, write error, too large)
    disk_full: bool  # the last write failed with ENOSPC/EDQUOT and writing is paused
    writing: bool  # False while writing is paused after an error
    last_error: str | None
    recovered_bytes: int  # garbage skipped or truncated when the spool was opened
    max_bytes: int


# ---------------------------------------------------------------------------------------------
# Records


def encode_record(stream: str, seq: int, t_ns: int, payload: bytes) -> bytes:
    """One record as written to a segment (header + body)."""
    sb = stream.encode()
    body = b"".join((_REC_BODY.pack(seq, t_ns, len(sb)), sb, payload))
    n = _U32.pack(len(body))
    return b"".join((RECORD_MAGIC, n, _U32.pack(zlib.crc32(body, zlib.crc32(n))), body))


@dataclass(frozen=True, slots=True)
class _Rec:
    start: int
    end: int
    seq: int
    t_ns: int
    stream: str
    payload_start: int


def _parse_at(data: bytes, off: int) -> _Rec | None:
    """The valid record starting exactly at ``off``, or None."""
    if len(data) - off < _REC_HEAD.size + _REC_BODY.size:
        return None
    magic, n, crc = _REC_HEAD.unpack_from(data, off)
    if magic != RECORD_MAGIC or n < _REC_BODY.size or n > MAX_RECORD_BODY:
        return None
    b0 = off + _REC_HEAD.size
    end = b0 + n
    if end > len(data):
        return None
    body = memoryview(data)[b0:end]
    if zlib.crc32(body, zlib.crc32(data[off + 4 : off + 8])) != crc:
        return None
    seq, t_ns, slen = _REC_BODY.unpack_from(body, 0)
    p0 = b0 + _REC_BODY.size + slen
    if p0 > end:
        return None
    try:
        stream = bytes(body[_REC_BODY.size : _REC_BODY.size + slen]).decode()
    except UnicodeDecodeError:
        return None
    return _Rec(off, end, seq, t_ns, stream, p0)


def scan_records(data: bytes, start: int) -> Iterator[_Rec]:
    """Every valid record from ``start``; a damaged stretch is skipped by searching for the next
    record magic whose CRC checks out (a false match needs a CRC32 collision)."""
    off = start
    while off < len(data):
        rec = _parse_at(data, off)
        if rec is not None:
            yield rec
            off = rec.end
            continue
        nxt = data.find(RECORD_MAGIC, off + 1)
        while nxt != -1 and _parse_at(data, nxt) is None:
            nxt = data.find(RECORD_MAGIC, nxt + 1)
        if nxt == -1:
            return
        off = nxt


# ---------------------------------------------------------------------------------------------
# Segments (in memory: what each one holds, never the payloads)


@dataclass(slots=True)
class Segment:
    number: int
    path: Path
    size: int
    records: int = 0
    # stream -> contiguous seq runs [[first, last], ...]; gaps (batches not spooled) are rare.
    runs: dict[str, list[list[int]]] = field(default_factory=dict)
    fd: int | None = None  # open only for the segment being appended to

    def add(self, stream: str, seq: int) -> None:
        self.records += 1
        rs = self.runs.setdefault(stream, [])
        if rs and rs[-1][1] + 1 == seq:
            rs[-1][1] = seq
        else:
            rs.append([seq, seq])

    def unacked(self, acked: dict[str, int]) -> int:
        n = 0
        for stream, rs in self.runs.items():
            a = acked.get(stream, -1)
            n += sum(max(0, last - max(first - 1, a)) for first, last in rs)
        return n

    def unacked_streams(self, acked: dict[str, int]) -> set[str]:
        return {s for s, rs in self.runs.items() if max(r[1] for r in rs) > acked.get(s, -1)}


def segment_name(number: int) -> str:
    return f"{number:016d}{SEGMENT_SUFFIX}"
