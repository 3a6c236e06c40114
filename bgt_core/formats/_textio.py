"""Small text-file helpers shared by the format readers and writers."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from bgt_core.atomic import write_atomic
from bgt_core.safe_open import LIMITS, FileRefused, iter_raw_lines, open_regular, read_limited


def write_text_atomic(path: Path, text: str) -> None:
    """Write to a temporary sibling, fsync, then rename: readers never see half a file, and a
    failure leaves whatever was there before untouched (see ``bgt_core.atomic``)."""
    write_atomic(path, text)


# --- reading: every problem becomes the caller's one-line error type ----------------------------

# Deepest nesting of brackets accepted in a JSON or Python-literal value of our formats (the
# deepest real one is 4: an .hst Fingerprints object); deeper input is refused before parsing,
# so it can never end in a RecursionError.
MAX_NESTING = 16
_BRACKETS = re.compile(r"[\[\]{}()]")
_STRINGS = re.compile(r"\"(?:[^\"\\]|\\.)*\"|'(?:[^'\\]|\\.)*'")


def not_utf8(
    data: bytes, e: UnicodeDecodeError, source: str, first_line: int = 1, offset: int = 0
) -> str:
    """The message for undecodable bytes: ``<file>:<line>: not UTF-8 text (byte 0xff at offset N)``."""
    line = first_line + data.count(b"\n", 0, e.start)
    return (
        f"{source}:{line}: not UTF-8 text (byte {data[e.start]:#04x} at offset {offset + e.start})"
    )


def read_text(path: str | Path, error: type[Exception], what: str = "") -> str:
    """A file's UTF-8 text; ``error`` (one line naming the file) when it cannot be read, is not
    a regular file or is over its kind's size limit (``what``, see bgt_core.safe_open; a site
    file's by default), or holds bytes that are not UTF-8 (then the line and byte offset of the
    first one are named)."""
    path = Path(path)
    label = f"{what} " if what else ""
    kind = what if what in LIMITS else "site file"
    try:
        with open_regular(path, kind) as f:
            data = read_limited(f, path, kind)
    except FileRefused as e:  # names the file itself
        raise error(str(e)) from None
    except OSError as e:
        raise error(f"cannot read {label}{path}: {e.strerror or e}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(not_utf8(data, e, str(path))) from None


def iter_lines(
    path: str | Path, error: type[Exception], kind: str = "readings"
) -> Iterator[tuple[int, str]]:
    """``(line number, text)`` of each line, newline kept, decoded one line at a time (a large
    file is never held whole, nor a line longer than bgt_core.safe_open.MAX_LINE); ``error``
    for undecodable bytes, an unreadable file, one that is not a regular file or is over the
    size limit of its ``kind``."""
    path = Path(path)
    offset = 0
    try:
        with open_regular(path, kind) as f:
            for lineno, raw in iter_raw_lines(f, path):
                try:
                    yield lineno, raw.decode("utf-8")
                except UnicodeDecodeError as e:
                    raise error(not_utf8(raw, e, str(path), lineno, offset)) from None
                offset += len(raw)
    except FileRefused as e:  # names the file itself
        raise error(str(e)) from None
    except OSError as e:
        raise error(f"cannot read {path}: {e.strerror or e}") from None


def check_nesting(text: str, max_depth: int = MAX_NESTING) -> None:
    """ValueError if brackets in ``text`` (outside string literals) nest deeper than ``max_depth``."""
    if sum(text.count(c) for c in "[{(") <= max_depth:
        return  # cannot be deeper than the number of opening brackets
    depth = 0
    for m in _BRACKETS.finditer(_STRINGS.sub('""', text)):
        if m.group() in "[{(":
            depth += 1
            if depth > max_depth:
                raise ValueError(f"nested deeper than {max_depth} levels")
        else:
            depth -= 1


def json_loads(text: str, max_depth: int = MAX_NESTING) -> Any:
    """``json.loads`` refusing deep nesting up front; any failure is a ValueError."""
    check_nesting(text, max_depth)
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"nested deeper than {max_depth} levels") from None


def finite(value: object, what: str) -> float:
    """A real number (not a bool, not a string) as a finite float; ValueError naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number, not {value!r:.40}")  # noqa: TRY004 - readers catch ValueError
    try:
        out = float(value)
    except OverflowError:
        out = math.inf
    if not math.isfinite(out):
        raise ValueError(f"{what} must be finite, not {value!r:.40}")
    return out
