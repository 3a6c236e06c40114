"""Full disks for the tests, at the two fault-injection seams the suite has: a plain ``os.write``
replacement (the collector's store) and a ``FileOps`` (the agent's spool). Both behave like the
kernel: a short write first, then ENOSPC."""

from __future__ import annotations

import errno
import os

from bgt_core.atomic import FileOps


class SwitchableDisk:
    """``os.write`` with a switch: while ``full``, a write gets ``partial`` bytes in, then the
    next one fails with ENOSPC."""

    def __init__(self, partial: int = 3) -> None:
        self.full = False
        self.partial = partial

    def __call__(self, fd: int, data: bytes) -> int:
        if self.full:
            if len(data) > self.partial:
                return os.write(fd, data[: self.partial])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)


class QuotaFiles(FileOps):
    """A filesystem with ``free`` bytes left: short writes, then ENOSPC; truncating frees space."""

    def __init__(self, free: int) -> None:
        self.free = free
        self.writes = 0

    def write(self, fd: int, data: bytes | memoryview) -> int:
        self.writes += 1
        if self.free <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), self.free)
        self.free -= n
        return os.write(fd, data[:n])

    def ftruncate(self, fd: int, length: int) -> None:
        self.free += os.fstat(fd).st_size - length
        os.ftruncate(fd, length)
