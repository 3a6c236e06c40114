"""The spool itself: appending records durably, acknowledgements, dropping the oldest when full,
replaying what is pending, and recovery when the directory is opened again."""

from __future__ import annotations

import fcntl
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from bgt_core.atomic import FileOps, fsync_dir, temp_path, write_all, write_atomic
from sensor_agent.spool.format import (
    ACK_FILE,
    DEFAULT_ACK_INTERVAL_S,
    DEFAULT_FSYNC_INTERVAL_S,
    DEFAULT_RETRY_INTERVAL_S,
    DEFAULT_SEGMENT_BYTES,
    DROP_WARNING_INTERVAL_S,
    FULL_ERRNOS,
    LOCK_FILE,
    MAX_STREAM_BYTES,
    SEG_HEAD,
    SEGMENT_MAGIC,
    SEGMENT_SUFFIX,
    SEGMENT_VERSION,
    Segment,
    SpoolError,
    SpoolStats,
    encode_record,
    scan_records,
    segment_name,
)

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# The spool


class Spool:
    """A bounded, crash-safe, append-only store of encoded batches, keyed by (stream, seq).

    Durability: ``append`` hands the whole record to the kernel in one ``write`` before it
    returns, so it survives a crash or ``kill -9`` of the agent at once; it survives a power
    cut once fsynced (at most ``fsync_interval_s`` later, on every segment roll, on ``sync()``
    and on ``close()``). Acknowledgements are persisted at most every ``ack_interval_s``; after a
    crash, batches acknowledged in that window come back from ``pending()`` once more (the
    collector deduplicates them).

    Thread-safe: one lock guards the state, so Zenoh's ack callback may call ``ack`` while the
    event loop appends. Times come from the injected clocks: ``clock`` (monotonic ns) paces
    fsyncs, retries and warnings; ``wall_ns`` stamps records.
    """

    def __init__(
        self,
        directory: Path | str,
        max_bytes: int,
        *,
        segment_bytes: int | None = None,
        fsync_interval_s: float | None = DEFAULT_FSYNC_INTERVAL_S,
        ack_interval_s: float = DEFAULT_ACK_INTERVAL_S,
        retry_interval_s: float = DEFAULT_RETRY_INTERVAL_S,
        clock: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
        files: FileOps | None = None,
    ) -> None:
        if not isinstance(max_bytes, int) or max_bytes < 4096:
            raise ValueError(f"spool max_bytes must be an integer >= 4096, got {max_bytes!r}")
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        # Dropping works a whole segment at a time, so a segment is a small share of the budget.
        self.segment_bytes = segment_bytes or max(1024, min(DEFAULT_SEGMENT_BYTES, max_bytes // 16))
        self._fsync_ns = None if fsync_interval_s is None else int(fsync_interval_s * 1e9)
        self._ack_ns = int(ack_interval_s * 1e9)
        self._retry_ns = int(retry_interval_s * 1e9)
        self._clock = clock
        self._wall_ns = wall_ns
        self._files = files or FileOps()
        self._lock = threading.RLock()

        self._segments: list[Segment] = []  # oldest first; the last may be the active one
        self._active: Segment | None = None
        self._acked: dict[str, int] = {}
        self._acks_dirty = False
        self._bytes = 0
        self._dropped = 0
        self._dropped_since_warning = 0
        self._next_drop_warning = 0
        self._unspooled = 0
        self._unspooled_in_pause = 0
        self._paused_until: int | None = None
        self._disk_full = False
        self._last_error: str | None = None
        self._recovered = 0
        self._closed = False
        now = clock()
        self._last_sync = now
        self._last_ack_write = now

        self._lock_fd = self._take_directory()
        try:
            self._load_acks()
            self._load_segments()
            self._delete_acked_segments()
        except OSError as e:
            os.close(self._lock_fd)
            raise SpoolError(
                f"spool directory {self.directory} cannot be recovered: {e.strerror or e}"
            ) from e
        except BaseException:
            os.close(self._lock_fd)
            raise

    # -- opening ----------------------------------------------------------------------------

    def _take_directory(self) -> int:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise SpoolError(f"spool directory {self.directory} is not usable: {e.strerror}") from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise SpoolError(
                f"spool directory {self.directory} is in use by another agent "
                "process (each agent needs its own spool.dir)"
            ) from None
        return fd

    def _load_acks(self) -> None:
        path = self.directory / ACK_FILE
        temp_path(self.directory / ACK_FILE).unlink(missing_ok=True)
        try:
            doc = json.loads(path.read_bytes())
        except FileNotFoundError:
            return
        except (OSError, ValueError) as e:
            # Losing acks only means re-sending batches the collector already has; it dedupes.
            log.warning(
                "spool %s: ignoring unreadable %s (%s); unacknowledged state resets",
                self.directory,
                ACK_FILE,
                e,
            )
            return
        acked = doc.get("acked") if isinstance(doc, dict) else None
        if not isinstance(acked, dict):
            log.warning("spool %s: ignoring %s without an 'acked' object", self.directory, ACK_FILE)
            return
        for stream, seq in acked.items():
            if isinstance(seq, int) and not isinstance(seq, bool):
                self._acked[stream] = seq

    def _load_segments(self) -> None:
        numbered = []
        for p in self.directory.glob("*" + SEGMENT_SUFFIX):
            stem = p.name[: -len(SEGMENT_SUFFIX)]
            if stem.isdigit():
                numbered.append((int(stem), p))
        for number, path in sorted(numbered):
            seg = self._recover_segment(number, path)
            if seg is not None:
                self._segments.append(seg)
                self._bytes += seg.size
        if self._recovered:
            log.warning(
                "spool %s: skipped %d damaged bytes while opening (records before and "
                "after them are intact)",
                self.directory,
                self._recovered,
            )

    def _recover_segment(self, number: int, path: Path) -> Segment | None:
        """Index one segment; cut a torn tail back to the last whole record."""
        try:
            data = path.read_bytes()
        except OSError as e:
            raise SpoolError(f"spool segment {path} is not readable: {e.strerror}") from e
        if len(data) < SEG_HEAD.size:
            # Created but the header never made it to disk: it holds nothing.
            self._recovered += len(data)
            path.unlink()
            return None
        magic, version, _, _ = SEG_HEAD.unpack_from(data, 0)
        if magic != SEGMENT_MAGIC or version != SEGMENT_VERSION:
            # Not ours to delete; set aside so it neither blocks nor counts against the budget.
            bad = path.with_name(path.name + ".bad")
            path.rename(bad)
            log.warning(
                "spool %s: %s is not a version-%d spool segment; moved to %s",
                self.directory,
                path.name,
                SEGMENT_VERSION,
                bad.name,
            )
            return None
        seg = Segment(number, path, SEG_HEAD.size)
        expect = SEG_HEAD.size
        for rec in scan_records(data, SEG_HEAD.size):
            self._recovered += rec.start - expect
            seg.add(rec.stream, rec.seq)
            expect = seg.size = rec.end
        if seg.size < len(data):
            self._recovered += len(data) - seg.size
            with open(path, "r+b") as f:  # truncate the torn tail so appends stay framed
                f.truncate(seg.size)
                os.fsync(f.fileno())
            log.warning(
                "spool %s: %s had a torn or corrupt tail of %d bytes; truncated",
                self.directory,
                path.name,
                len(data) - seg.size,
            )
        return seg

    # -- appending --------------------------------------------------------------------------

    def append(self, stream: str, seq: int, payload: bytes) -> bool:
        """Store one encoded batch; True when it is on disk (crash-safe), False when it could
        not be spooled (disk full / write error / larger than the budget): publish it anyway."""
        sb = stream.encode() if isinstance(stream, str) else b""
        if not sb or len(sb) > MAX_STREAM_BYTES:
            raise ValueError(
                f"spool stream must be 1-{MAX_STREAM_BYTES} UTF-8 bytes, got {stream!r}"
            )
        if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq < 2**63:
            raise ValueError(f"spool seq must be a non-negative 64-bit integer, got {seq!r}")
        with self._lock:
            self._check_open()
            now = self._clock()
            if self._paused_until is not None and now < self._paused_until:
                self._not_spooled()
                return False
            rec = encode_record(stream, seq, self._wall_ns(), bytes(payload))
            if len(rec) + SEG_HEAD.size > self.max_bytes:
                log.warning(
                    "spool %s: a %d-byte batch is larger than the whole spool; not spooled",
                    self.directory,
                    len(rec),
                )
                self._unspooled += 1
                return False
            self._make_room(len(rec), now)
            try:
                seg = self._active
                if seg is None or (seg.records and seg.size + len(rec) > self.segment_bytes):
                    seg = self._roll()
                self._write_record(seg, rec)
            except OSError as e:
                self._write_failed(e, now)
                self._not_spooled()
                return False
            seg.add(stream, seq)
            if self._paused_until is not None:
                self._resumed()
            if self._fsync_ns is not None and now - self._last_sync >= self._fsync_ns:
                self._sync_locked(now)
            return True

    def _not_spooled(self) -> None:
        self._unspooled += 1
        self._unspooled_in_pause += 1

    def _roll(self) -> Segment:
        """Close the active segment (fsynced) and start the next one."""
        if self._active is not None:
            self._close_active(sync=True)
        number = self._segments[-1].number + 1 if self._segments else 1
        path = self.directory / segment_name(number)
        fd = self._files.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND)
        head = SEG_HEAD.pack(SEGMENT_MAGIC, SEGMENT_VERSION, 0, number)
        try:
            self._write_all(fd, head)
        except OSError:
            self._files.close(fd)
            path.unlink(missing_ok=True)
            raise
        seg = Segment(number, path, len(head), fd=fd)
        self._segments.append(seg)
        self._active = seg
        self._bytes += seg.size
        fsync_dir(self.directory)  # the new name must survive a power cut too
        return seg

    def _write_all(self, fd: int, data: bytes) -> None:
        write_all(self._files, fd, data)

    def _write_record(self, seg: Segment, rec: bytes) -> None:
        assert seg.fd is not None
        start = seg.size
        try:
            self._write_all(seg.fd, rec)
        except OSError:
            # Roll back the partial record so the segment stays a clean run of records.
            try:
                self._files.ftruncate(seg.fd, start)
            except OSError:
                log.exception(
                    "spool %s: cannot cut a partial record from %s; it will be "
                    "trimmed when the spool is next opened",
                    self.directory,
                    seg.path.name,
                )
                self._close_active(sync=False)
            raise
        seg.size += len(rec)
        self._bytes += len(rec)

    def _write_failed(self, e: OSError, now: int) -> None:
        full = e.errno in FULL_ERRNOS
        self._last_error = f"{os.strerror(e.errno) if e.errno else e}"
        if self._paused_until is None:
            if full:
                log.error(
                    "spool %s: disk full; batches are published but not spooled until "
                    "space returns (retrying every %.0f s)",
                    self.directory,
                    self._retry_ns / 1e9,
                )
            else:
                log.error(
                    "spool %s: write failed (%s); batches are published but not spooled "
                    "(retrying every %.0f s)",
                    self.directory,
                    self._last_error,
                    self._retry_ns / 1e9,
                )
        self._disk_full = self._disk_full or full
        self._paused_until = now + self._retry_ns

    def _resumed(self) -> None:
        log.warning(
            "spool %s: writing again; %d batches were not spooled meanwhile",
            self.directory,
            self._unspooled_in_pause,
        )
        self._paused_until = None
        self._disk_full = False
        self._unspooled_in_pause = 0

    def _make_room(self, need: int, now: int) -> None:
        """Drop the oldest segments until ``need`` more bytes (maybe in a new segment) fit."""
        dropped = 0
        while self._segments and self._bytes + need + SEG_HEAD.size > self.max_bytes:
            seg = self._segments[0]
            if seg is self._active:
                self._close_active(sync=False)
            dropped += seg.unacked(self._acked)
            self._delete_segment(seg)
        if dropped:
            self._dropped += dropped
            self._dropped_since_warning += dropped
            if now >= self._next_drop_warning:
                log.warning(
                    "spool %s: full at %d bytes; dropped the %d oldest unacknowledged "
                    "batches (%d in total since start)",
                    self.directory,
                    self.max_bytes,
                    self._dropped_since_warning,
                    self._dropped,
                )
                self._dropped_since_warning = 0
                self._next_drop_warning = now + int(DROP_WARNING_INTERVAL_S * 1e9)

    def _close_active(self, *, sync: bool) -> None:
        seg = self._active
        if seg is None or seg.fd is None:
            return
        try:
            if sync:
                self._files.fsync(seg.fd)
        finally:
            self._files.close(seg.fd)
            seg.fd = None
            self._active = None

    def _delete_segment(self, seg: Segment) -> None:
        if seg is self._active:
            self._close_active(sync=False)
        seg.path.unlink(missing_ok=True)
        self._segments.remove(seg)
        self._bytes -= seg.size

    # -- acknowledgements -------------------------------------------------------------------

    def ack(self, stream: str, upto_seq: int) -> None:
        """Everything of ``stream`` with seq <= ``upto_seq`` is handled and may be forgotten."""
        if not isinstance(upto_seq, int) or isinstance(upto_seq, bool):
            raise TypeError(f"spool ack seq must be an integer, got {upto_seq!r}")
        with self._lock:
            self._check_open()
            if upto_seq <= self._acked.get(stream, -1):
                return
            self._acked[stream] = upto_seq
            self._acks_dirty = True
            for seg in [s for s in self._segments if stream in s.runs and s is not self._active]:
                if not seg.unacked_streams(self._acked):
                    self._delete_segment(seg)
            now = self._clock()
            if now - self._last_ack_write >= self._ack_ns:
                self._write_acks(now)

    def acked(self) -> dict[str, int]:
        with self._lock:
            return dict(self._acked)

    def lowest_pending(self, stream: str) -> int | None:
        """The lowest unacknowledged seq of ``stream`` still on disk, or None (the publisher's
        floor: nothing below it can be re-sent from the spool)."""
        with self._lock:
            a = self._acked.get(stream, -1)
            for seg in self._segments:
                for first, last in seg.runs.get(stream, ()):
                    if last > a:
                        return max(first, a + 1)
            return None

    def pending_streams(self) -> dict[str, tuple[int, int]]:
        """Streams with unacknowledged records on disk: stream -> (lowest, highest) such seq."""
        with self._lock:
            out: dict[str, tuple[int, int]] = {}
            for seg in self._segments:
                for stream, rs in seg.runs.items():
                    a = self._acked.get(stream, -1)
                    for first, last in rs:
                        if last > a:
                            lo, hi = max(first, a + 1), last
                            if stream in out:
                                lo, hi = min(lo, out[stream][0]), max(hi, out[stream][1])
                            out[stream] = (lo, hi)
            return out

    def _delete_acked_segments(self) -> None:
        for seg in [s for s in self._segments if s is not self._active]:
            if not seg.unacked_streams(self._acked):
                self._delete_segment(seg)

    def _write_acks(self, now: int) -> None:
        """Rewrite acks.json atomically (temp, fsync, rename, fsync dir), keeping only streams
        that still have records on disk."""
        live = set().union(*(s.runs for s in self._segments)) if self._segments else set()
        self._acked = {s: q for s, q in self._acked.items() if s in live}
        data = json.dumps(
            {"version": 1, "acked": self._acked}, separators=(",", ":"), sort_keys=True
        ).encode()
        self._last_ack_write = now
        try:
            write_atomic(self.directory / ACK_FILE, data, files=self._files)
        except OSError as e:
            # The previous acks.json is intact; stale acks only cost re-sends.
            self._last_error = os.strerror(e.errno) if e.errno else str(e)
            log.warning(
                "spool %s: cannot save %s (%s); will retry",
                self.directory,
                ACK_FILE,
                self._last_error,
            )
            return
        self._acks_dirty = False

    # -- reading back -----------------------------------------------------------------------

    def pending(self) -> Iterator[tuple[str, int, bytes]]:
        """Unacknowledged records on disk as (stream, seq, payload), oldest first.

        Sees what was appended before the call; segments acknowledged or dropped meanwhile
        are skipped. Reads one segment into memory at a time."""
        with self._lock:
            self._check_open()
            segs = [(s.path, s.size) for s in self._segments]
        for path, size in segs:
            try:
                with open(path, "rb") as f:
                    data = f.read(size)
            except FileNotFoundError:
                continue
            with self._lock:
                acked = dict(self._acked)
            for rec in scan_records(data, SEG_HEAD.size):
                if rec.seq > acked.get(rec.stream, -1):
                    yield rec.stream, rec.seq, data[rec.payload_start : rec.end]

    # -- housekeeping -----------------------------------------------------------------------

    def sync(self) -> None:
        """fsync the active segment and save acknowledgements now (call it from a timer when
        appends are rare; it blocks appends for the duration of the fsync)."""
        with self._lock:
            self._check_open()
            self._sync_locked(self._clock(), force_acks=True)

    def _sync_locked(self, now: int, *, force_acks: bool = False) -> None:
        self._last_sync = now
        if self._active is not None and self._active.fd is not None:
            try:
                self._files.fsync(self._active.fd)
            except OSError as e:
                # After a failed fsync the kernel may have dropped the dirty pages: start a
                # fresh segment rather than trust this one's unsynced tail any further.
                self._write_failed(e, now)
                self._close_active(sync=False)
        if self._acks_dirty and (force_acks or now - self._last_ack_write >= self._ack_ns):
            self._write_acks(now)

    def stats(self) -> SpoolStats:
        with self._lock:
            unacked = {s for seg in self._segments for s in seg.unacked_streams(self._acked)}
            return SpoolStats(
                directory=str(self.directory),
                bytes=self._bytes,
                segments=len(self._segments),
                records=sum(seg.unacked(self._acked) for seg in self._segments),
                streams=len(unacked),
                dropped_oldest=self._dropped,
                unspooled=self._unspooled,
                disk_full=self._disk_full,
                writing=self._paused_until is None,
                last_error=self._last_error,
                recovered_bytes=self._recovered,
                max_bytes=self.max_bytes,
            )

    def _check_open(self) -> None:
        if self._closed:
            raise SpoolError(f"spool {self.directory} is closed")

    def close(self) -> None:
        """fsync, save acks, delete fully acknowledged segments, release the directory."""
        with self._lock:
            if self._closed:
                return
            now = self._clock()
            try:
                self._sync_locked(now, force_acks=True)
                self._close_active(sync=False)
                self._delete_acked_segments()
                if self._acks_dirty:
                    self._write_acks(now)
            finally:
                self._closed = True
                os.close(self._lock_fd)

    def __enter__(self) -> Spool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
