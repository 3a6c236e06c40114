"""Help text of the typer CLIs.

Docstrings are wrapped to the source's line length; typer's rich help keeps those line breaks in
every paragraph after the first, so a terminal of another width shows ragged lines. ``flow``
joins the lines of each paragraph (a list item, a line starting with ``-``, ``*`` or ``1.``, keeps
its own line) and ``flow_command_help`` applies it to every command of an app.
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
    ``help=`` if given, else the callback's docstring."""
    for info in app.registered_commands:
        doc = info.help if info.help is not None else inspect.getdoc(info.callback)
        if doc:
            info.help = flow(doc)
    for group in app.registered_groups:
        if group.typer_instance is not None:
            flow_command_help(group.typer_instance)
