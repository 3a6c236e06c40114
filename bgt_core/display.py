"""Text from outside (run names, agent ids, file contents quoted in errors) made safe to show.

Standard library only. A terminal runs the escape codes in a string it prints, and a name of
100 kB fills a table; `shown` turns every character that is not printable into a visible escape
and cuts long text, so what is stored as given is shown as text.
"""

from __future__ import annotations


def shown(text: object, limit: int | None = 80) -> str:
    """``text`` with each non-printable character as ``\\xNN`` / ``\\uNNNN`` and, past ``limit``
    characters, cut with an ellipsis (None: never cut)."""
    s = str(text)
    if limit is not None and len(s) > limit:
        s = s[: max(limit - 1, 0)] + "…"
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in s)
