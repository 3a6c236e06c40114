"""Durable whole-file replacement, the one way this project rewrites a file in place.

``write_atomic`` writes a temporary sibling, fsyncs it, renames it over the target and fsyncs the
directory: after a crash or power cut a reader finds either the old file or the new one, never
half of either, and a failed write leaves the old file as it was. Standard library only.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


class FileOps:
    """The few file operations the durable writers use; tests subclass it to inject faults
    (a full disk)."""

    def open(self, path: Path, flags: int, mode: int = 0o644) -> int:
        return os.open(path, flags, mode)

    def write(self, fd: int, data: bytes | memoryview) -> int:
        return os.write(fd, data)

    def fsync(self, fd: int) -> None:
        os.fsync(fd)

    def ftruncate(self, fd: int, length: int) -> None:
        os.ftruncate(fd, length)

    def close(self, fd: int) -> None:
        os.close(fd)


OS_FILES = FileOps()


def fsync_dir(path: Path) -> None:
    """Make the directory entries of ``path`` (a new or renamed file in it) durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_all(files: FileOps, fd: int, data: bytes | memoryview) -> None:
    """Write every byte (a write that makes no progress counts as a full disk)."""
    view = memoryview(data)
    while view:
        n = files.write(fd, view)
        if n <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = view[n:]


def temp_path(path: Path) -> Path:
    """The temporary sibling ``write_atomic`` uses for ``path`` (left over only by a crash)."""
    return path.with_name(path.name + ".tmp")


def write_atomic(path: Path, data: bytes | str, *, files: FileOps = OS_FILES) -> None:
    """Replace ``path`` with ``data`` (str is written as UTF-8): temp file, fsync, rename,
    directory fsync. On failure the temp file is removed and the old file is untouched."""
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    tmp = temp_path(path)
    try:
        fd = files.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        try:
            write_all(files, fd, raw)
            files.fsync(fd)
        finally:
            files.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a half-written temp file must not eat the space we lack
        raise
    fsync_dir(path.parent)
