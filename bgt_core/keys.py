"""Unknown keys in a YAML mapping: one message, with a close match where there is one.

Standard library only. Every config reader of the suite (experiment.yaml, rig.yaml, agent.yaml,
collector.yaml, ...) asks :func:`unknown_key` for each mapping it reads and raises its own error
type with the message, so a misspelt key is never silently ignored nor reported as something else.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def unknown_key(
    given: Iterable[object], allowed: Iterable[str], source: str, section: str = ""
) -> str | None:
    """None if every key of ``given`` is in ``allowed``; else the message for the first unknown
    one (sorted), e.g. ``exp.yaml: unknown key 'sync.mdoe' (did you mean 'mode'? allowed: mode,
    beacon, ...)``. ``source`` names the file, ``section`` the dotted path of a nested mapping
    ('' at the top level); keys are shown cut to 40 characters."""
    names = list(allowed)
    unknown = sorted({str(k) for k in given} - set(names))
    if not unknown:
        return None
    key = unknown[0]
    close = difflib.get_close_matches(key, names, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}? " if close else ""
    dotted = f"{section}.{key[:40]}" if section else key[:40]
    return f"{source}: unknown key {dotted!r} ({hint}allowed: {', '.join(names)})"
