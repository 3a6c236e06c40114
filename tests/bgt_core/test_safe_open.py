"""Files that never end (issue 35): every reader opens through bgt_core.safe_open, which takes
only regular files, decides a FIFO without blocking, and holds each kind to a size limit."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from bgt_core.safe_open import FileRefused, iter_raw_lines, open_regular, read_limited


def test_regular_files_and_links_to_them_open(tmp_path: Path) -> None:
    p = tmp_path / "a.mbd"
    p.write_bytes(b"x\ny\n")
    link = tmp_path / "link.mbd"
    link.symlink_to(p)
    for path in (p, link):
        with open_regular(path, "readings") as f:
            assert list(iter_raw_lines(f, path)) == [(1, b"x\n"), (2, b"y\n")]


@pytest.mark.parametrize("target", ["/dev/zero", "fifo", "link-to-zero", "folder"])
def test_what_never_ends_is_refused_at_once(tmp_path: Path, target: str) -> None:
    if target == "fifo":
        path = tmp_path / "run.yaml"
        os.mkfifo(path)  # nobody writes: opening it for reading blocks unless done without
    elif target == "link-to-zero":
        path = tmp_path / "markers.dat"
        path.symlink_to("/dev/zero")
    elif target == "folder":
        path = tmp_path
    else:
        path = Path(target)
    t = time.monotonic()
    with pytest.raises(FileRefused) as err:
        open_regular(path, "marker map")
    assert time.monotonic() - t < 2.0
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: is a ")
    assert message.endswith("not a regular file; a marker map must be one")


def test_size_limits(tmp_path: Path) -> None:
    p = tmp_path / "big.yaml"
    p.write_bytes(b"a" * 2048)
    with pytest.raises(FileRefused, match=r"big.yaml: 2048 bytes, over the 1024 bytes a yaml may"):
        open_regular(p, "yaml", max_bytes=1024)
    with open_regular(p, "yaml", max_bytes=4096) as f:
        assert len(read_limited(f, p, "yaml", 4096)) == 2048
    with open_regular(p, "yaml") as f, pytest.raises(FileRefused, match="larger than"):
        read_limited(f, p, "yaml", 1000)  # the file grew past its limit while read


def test_a_file_without_newlines_is_not_held_whole(tmp_path: Path) -> None:
    p = tmp_path / "one-line.mbd"
    p.write_bytes(b"1" * 200_000)
    with (
        open_regular(p, "readings") as f,
        pytest.raises(FileRefused, match=r"one-line.mbd:1: a line longer than 65536 bytes"),
    ):
        list(iter_raw_lines(f, p))
