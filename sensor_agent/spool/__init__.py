"""The agent's on-disk spool: every encoded batch is appended here before it is published and kept
until the collector acknowledges it, so an outage, a collector restart or an agent crash loses nothing.

Layout of the spool directory (``docs/reliability.md`` describes it in prose)::

    0000000000000001.seg   segments, append-only, numbered in write order
    acks.json              per stream: the highest seq the collector has handled (temp + rename)
    lock                   flock'ed while a Spool owns the directory

A segment is a 20-byte header (``b"BGTSPOOL"``, version, reserved, segment number) followed by
records; a record is ``b"BGTR"``, body length, CRC32 (of length + body), then the body
``seq, t_ns, stream length, stream, payload``. The spool never interprets payloads.

The package: ``format`` (the bytes on disk) and ``store`` (the Spool).
"""

from sensor_agent.spool.format import (
    ACK_FILE,
    DEFAULT_FSYNC_INTERVAL_S,
    SEGMENT_SUFFIX,
    SpoolError,
    SpoolStats,
    encode_record,
)
from sensor_agent.spool.store import Spool

__all__ = [
    "ACK_FILE",
    "DEFAULT_FSYNC_INTERVAL_S",
    "SEGMENT_SUFFIX",
    "Spool",
    "SpoolError",
    "SpoolStats",
    "encode_record",
]
