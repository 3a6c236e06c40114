"""Help text of the typer CLIs.

Docstrings are wrapped to the source's line length; typer's rich help keeps those line breaks in
every paragraph after the first, so a terminal of another width shows ragged lines. ``flow``
joins the lines of each paragraph (a list item, a line starting with ``-``, ``*`` or ``1.``, keeps
its own line) and ``flow_command_help`` applies it to every command of an app.

Typer prints help through rich markup, which takes ``[default: x]`` or ``[[x, y], ...]`` for tags
and drops them. ``flow_command_help`` therefore also gives every command a class that escapes its
help texts, so each prints every character it was written with, and that shows boolean flags
without a ``<bool>`` value column (they take no value). Help texts are plain text: never markup.

Standard library only at import; typer and rich are imported when a CLI is put together.
"""

from __future__ import annotations

import inspect
import re
from typing import Any

_ITEM = re.compile(r"^\s*(?:[-*]|\d+[.)])\s")


def flow(text: str) -> str:
    """``text`` with the lines of each paragraph joined, list items on their own lines."""
    out = []
    for para in inspect.cleandoc(text).split("\n\n"):
        lines: list[str] = []
        for line in para.splitlines():
            if lines and not _ITEM.match(line):
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.rstrip())
        out.append("\n".join(lines))
    return "\n\n".join(out)


def flow_command_help(app: Any) -> None:
    """Flow the help of every command of a ``typer.Typer`` (and of its sub-apps): the explicit
    ``help=`` if given, else the callback's docstring; each command without a class of its own
    gets the classes of :func:`plain_help_classes` (help printed as written)."""
    from typer.core import TyperCommand, TyperGroup

    command_cls, group_cls = plain_help_classes()
    own = getattr(app.info.cls, "value", app.info.cls)  # typer wraps its default in a placeholder
    if own in (None, TyperGroup):
        app.info.cls = group_cls
    for info in app.registered_commands:
        doc = info.help if info.help is not None else inspect.getdoc(info.callback)
        if doc:
            info.help = flow(doc)
        if info.cls in (None, TyperCommand):
            info.cls = command_cls
    for group in app.registered_groups:
        if group.typer_instance is not None:
            flow_command_help(group.typer_instance)


_PLAIN_HELP: dict[str, Any] = {}


def _escape_help(params: list[Any]) -> None:
    """Escape each parameter's help for rich markup."""
    from rich.markup import escape

    for param in params:
        text = getattr(param, "help", None)
        if text:
            param.help = escape(text)


def plain_help_classes() -> tuple[Any, Any]:
    """``typer.core.TyperCommand`` and ``TyperGroup`` subclasses whose help texts (the
    command's and every parameter's) are escaped for rich markup, and whose flags (``--help``
    included) show no value type."""
    if _PLAIN_HELP:
        return _PLAIN_HELP["command"], _PLAIN_HELP["group"]
    from rich.markup import escape
    from typer.core import TyperCommand, TyperGroup

    class _Plain:
        help: str | None
        short_help: str | None
        params: list[Any]

        def _escape_own_help(self) -> None:
            if self.help:
                self.help = escape(self.help)
            if self.short_help:
                self.short_help = escape(self.short_help)
            _escape_help(self.params)

        def get_params(self, ctx: Any) -> list[Any]:
            params: list[Any] = super().get_params(ctx)  # type: ignore[misc]
            for param in params:  # --help and the completion flags are added late
                if getattr(param, "is_flag", False) and param.metavar is None:
                    param.metavar = ""
            return params

    class PlainHelpCommand(_Plain, TyperCommand):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._escape_own_help()

    class PlainHelpGroup(_Plain, TyperGroup):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._escape_own_help()

    _PLAIN_HELP.update(command=PlainHelpCommand, group=PlainHelpGroup)
    return PlainHelpCommand, PlainHelpGroup
