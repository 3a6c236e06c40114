"""Shared by the command modules: turning the project's errors into one-line exits."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.markup import escape

from annotator.errors import AnnotatorError
from ble_groundtruth.formats.devices import SiteConfigError
from ble_groundtruth.formats.markers import MarkerMapError
from ble_groundtruth.formats.mbd import MbdError

console = Console(stderr=True)
KNOWN_ERRORS = (AnnotatorError, MarkerMapError, MbdError, SiteConfigError, FileNotFoundError)


@contextmanager
def one_line_errors() -> Iterator[None]:
    """Known errors -> red one-line message and exit 1; anything else keeps its traceback."""
    try:
        yield
    except KNOWN_ERRORS as e:
        # escape: messages quote formats like "[x, y]" that rich would eat as markup;
        # soft_wrap: one line however narrow the terminal.
        console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)
        raise typer.Exit(1) from None


def default_jobs() -> int:
    """Worker processes when --jobs is not given: one per core (the pool serves every stage)."""
    return max(os.cpu_count() or 1, 1)
