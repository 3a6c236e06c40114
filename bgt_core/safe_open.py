"""Opening a file someone else named: only a regular file, never one that does not end.

Standard library only. Every reader of the suite (the annotator's marker maps, RSSI files and
YAML, the collector's run files and export, the agent's replay) opens through
:func:`open_regular`. A path may lead anywhere: ``/dev/zero`` never ends, a FIFO blocks the
reader until someone writes, a socket cannot be read. Symbolic links are followed and their
target must be a regular file too. The FIFO case is decided without blocking: the file is
opened non-blocking and checked with ``fstat`` before anything is read. Each kind of file has a
size limit, refused with one line naming the file and the limit.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

MiB = 1 << 20
GiB = 1 << 30

# Size limits per kind of file: far above any real one, far below what exhausts a machine.
LIMITS = {
    "yaml": 16 * MiB,  # a config, experiment, run.yaml, marker map in YAML
    "marker map": 16 * MiB,
    "site file": 64 * MiB,  # .dev, .par, .occ, .grd, .hst
    "readings": 8 * GiB,  # one .mbd file of a run (a sensor over many hours)
    "trajectory": 1 * GiB,
}
# The longest line a text reader accepts: a file without newlines is not read whole.
MAX_LINE = 64 * 1024

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


class FileRefused(OSError):
    """A path that is not a regular file, or a file over its limit. An OSError, so readers that
    report 'cannot read PATH: ...' already report it; ``str()`` is the whole one-line message."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


def _size(n: int) -> str:
    return f"{n / GiB:g} GiB" if n >= GiB else f"{n / MiB:g} MiB" if n >= MiB else f"{n} bytes"


def open_regular(path: str | Path, kind: str = "file", max_bytes: int | None = None) -> BinaryIO:
    """``path`` opened for binary reading if it is (or links to) a regular file of at most
    ``max_bytes`` (default: ``LIMITS[kind]``, none for an unknown kind); FileRefused otherwise,
    and OSError as ``open`` raises it for a missing or unreadable file."""
    path = Path(path)
    limit = LIMITS.get(kind) if max_bytes is None else max_bytes
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(path, flags)
    try:
        _check(os.fstat(fd), path, kind, limit)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _check(st: os.stat_result, path: Path, kind: str, limit: int | None) -> None:
    """FileRefused unless ``st`` is a regular file within ``limit`` bytes."""
    if not stat.S_ISREG(st.st_mode):
        what = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
        raise FileRefused(f"{path}: is {what}, not a regular file; a {kind} must be one")
    if limit is not None and st.st_size > limit:
        raise FileRefused(f"{path}: {_size(st.st_size)}, over the {_size(limit)} a {kind} may have")


def read_limited(f: BinaryIO, path: str | Path, kind: str, max_bytes: int | None = None) -> bytes:
    """All of an opened file, refused (FileRefused) if it grew past its limit while read."""
    limit = LIMITS.get(kind) if max_bytes is None else max_bytes
    data = f.read() if limit is None else f.read(limit + 1)
    if limit is not None and len(data) > limit:
        raise FileRefused(f"{path}: larger than the {_size(limit)} a {kind} may have")
    return data


def iter_raw_lines(
    f: BinaryIO, path: str | Path, max_line: int = MAX_LINE
) -> Iterator[tuple[int, bytes]]:
    """``(line number, bytes)`` of each line of an opened file, newline kept; FileRefused for a
    line longer than ``max_line`` bytes (a file with no newlines is never held whole)."""
    lineno = 0
    while True:
        raw = f.readline(max_line + 1)
        if not raw:
            return
        lineno += 1
        if len(raw) > max_line and not raw.endswith(b"\n"):
            raise FileRefused(f"{path}:{lineno}: a line longer than {max_line} bytes")
        yield lineno, raw
