"""Turns the dataset-format errors of the fingerprint / radio-map commands into AnnotatorError,
so `_common.one_line_errors()` prints them as one red line."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from annotator.errors import AnnotatorError
from bgt_core.formats.hst import HstError
from bgt_core.formats.occ import GridFormatError


@contextmanager
def format_errors() -> Iterator[None]:
    try:
        yield
    except (HstError, GridFormatError) as e:
        raise AnnotatorError(str(e)) from None
