"""Shared by the command modules: turning the project's errors into one-line exits."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    Progress,
    ProgressColumn,
    TaskID,
    TextColumn,
    TimeRemainingColumn,
)

from annotator.errors import AnnotatorError
from bgt_core.formats.devices import SiteConfigError
from bgt_core.formats.hst import HstError
from bgt_core.formats.markers import MarkerMapError
from bgt_core.formats.mbd import MbdError
from bgt_core.formats.occ import GridFormatError
from bgt_core.safe_yaml import YamlError

console = Console(stderr=True, emoji=False)
# The errors that mean "bad input": each carries one line naming the file and the field or line.
KNOWN_ERRORS = (
    AnnotatorError,
    MarkerMapError,
    MbdError,
    SiteConfigError,
    HstError,
    GridFormatError,
    YamlError,
    FileNotFoundError,
)
# A message is cut to this many characters: a bad value quoted in it must not flood the terminal.
MAX_MESSAGE = 400


def one_line(message: str) -> str:
    """Whitespace (newlines included) collapsed and the length capped: one terminal line's worth."""
    text = " ".join(message.split())
    return text if len(text) <= MAX_MESSAGE else text[: MAX_MESSAGE - 1] + "…"


@contextmanager
def one_line_errors() -> Iterator[None]:
    """Known errors -> red one-line message and exit 1; anything else keeps its traceback."""
    try:
        yield
    except KNOWN_ERRORS as e:
        # escape: messages quote formats like "[x, y]" that rich would eat as markup;
        # soft_wrap: one line however narrow the terminal.
        console.print(
            f"[red]error:[/red] {escape(one_line(str(e)))}", highlight=False, soft_wrap=True
        )
        raise typer.Exit(1) from None


class LazyProgress:
    """A rich Progress that appears only when the first task is added, so an input error found
    before any work starts is printed alone, not after an empty or half-drawn progress display.
    A transient one (erased when done) is not shown at all off a terminal, where it could only
    leave a stray blank line before the result or the error."""

    def __init__(self, *columns: Any, **kwargs: Any) -> None:
        kwargs = {"console": console, **kwargs}
        if kwargs.get("transient") and not kwargs["console"].is_terminal:
            kwargs["disable"] = True
        self._columns, self._kwargs = columns, kwargs
        self._bar: Progress | None = None

    def __enter__(self) -> LazyProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.stop()

    def add_task(self, description: str, **kwargs: Any) -> TaskID:
        if self._bar is None:
            self._bar = Progress(*self._columns, **self._kwargs)
            self._bar.start()
        return self._bar.add_task(description, **kwargs)

    def update(self, task: TaskID, **kwargs: Any) -> None:
        if self._bar is not None:
            self._bar.update(task, **kwargs)

    def advance(self, task: TaskID, advance: float = 1) -> None:
        if self._bar is not None:
            self._bar.advance(task, advance)


def stage_columns(width: int = 12) -> tuple[ProgressColumn, ...]:
    """Columns of the per-stage bars: name, bar, done/total, time left."""
    return (
        TextColumn(f"{{task.description:>{width}}}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeRemainingColumn(),
    )


def stage_progress(bar: Progress | LazyProgress) -> Callable[[str, int, int], None]:
    """The ``(name, done, total)`` callback long stages report to: one bar per name on ``bar``."""
    tasks: dict[str, TaskID] = {}

    def progress(name: str, done: int, total: int) -> None:
        if name not in tasks:
            tasks[name] = bar.add_task(name, total=total)
        bar.update(tasks[name], completed=done, total=total)

    return progress


def default_jobs() -> int:
    """Worker processes when --jobs is not given: one per core (the pool serves every stage)."""
    return max(os.cpu_count() or 1, 1)


# What to change in the capture when one part of sigma_m holds most of its variance.
_SIGMA_HINTS = {
    "sigma_params_m": "most of it is how well the map, rig and lenses are known: survey more "
    "markers along the walk{jig} (docs/field-guide.md)",
    "sigma_smoother_m": "most of it is frame noise: few or far markers in view; add markers "
    "along the walk",
    "sigma_blur_m": "most of it is motion blur: a shorter exposure or a slower walk",
}
_UNREFINED_HINT = (
    "most of it is how well the map, rig and lenses are known, as the experiment states: "
    "self-calibration (--refine all) measures them from the video"
)


def print_sigma_budget(
    console: Console, quality: dict[str, Any], *, refined: bool, jig: bool
) -> None:
    """One line on how good the trajectory says it is (sigma_m and its parts), and a hint when
    one part holds more than half of its variance (``refined``: a self-calibration ran; ``jig``:
    the walk started on a jig)."""
    from annotator.core.uncertainty import SIGMA_PARTS, sigma_budget

    budget = sigma_budget(quality)
    if budget is None:
        return
    parts = sorted(budget.parts_m.items(), key=lambda kv: -kv[1])
    console.print(
        f"sigma_m (per axis): median {1000 * budget.median_m:.1f} mm, p95 "
        f"{1000 * budget.p95_m:.1f} mm; its parts' medians: "
        + ", ".join(f"{SIGMA_PARTS[c]} {1000 * v:.1f}" for c, v in parts)
        + " mm",
        highlight=False,
        soft_wrap=True,
    )
    top = budget.largest
    if top in _SIGMA_HINTS and budget.parts_m[top] ** 2 > 0.5 * budget.median_m**2:
        hint = _SIGMA_HINTS[top] if refined or top != "sigma_params_m" else _UNREFINED_HINT
        hint = hint.format(jig="" if jig else ", or start it on a jig")
        console.print(f"  {hint}", highlight=False, soft_wrap=True)
