"""The checks every file the annotator reads shares (experiment.yaml, rig.yaml, CAMPAIGN.yaml):
a mapping, its allowed keys, a number in a range, a MAC, a name. Each problem is one ConfigError
line that names the file and the dotted key."""

from __future__ import annotations

import math
import re
from typing import Any

from annotator.errors import ConfigError
from bgt_core.keys import unknown_key

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")  # a folder name on any file system


def mapping(obj: Any, where: str) -> dict[str, Any]:
    """``obj`` as a mapping with text keys; ``where`` names it (``file: section``)."""
    if not isinstance(obj, dict):
        raise ConfigError(f"{where} must be a mapping")
    return {str(k): v for k, v in obj.items()}


def known_keys(
    obj: dict[Any, Any], allowed: tuple[str, ...], source: str, section: str = ""
) -> None:
    """ConfigError naming the first key of ``obj`` not in ``allowed`` (with a close match)."""
    message = unknown_key(obj, allowed, source, section)
    if message is not None:
        raise ConfigError(message)


def number(value: Any, where: str, lo: float, hi: float, expected: str = "") -> float:
    """A number in [lo, hi], as float. Strings are read as numbers too: the safe loader reads
    every scalar as text, and YAML 1.1 reads 1.5e9 (no sign in the exponent) as a string.
    Booleans, NaN and infinities are refused."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ConfigError(f"{where}: must be a number, not {value!r:.40}")
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    except ValueError:
        raise ConfigError(f"{where}: must be a number, not {value!r:.40}") from None
    if not (math.isfinite(x) and lo <= x <= hi):
        expected = expected or f"a finite number in {lo:g}..{hi:g}"
        raise ConfigError(f"{where}: must be {expected}, not {value!r:.40}")
    return x


def mac(value: Any, where: str) -> str:
    """A MAC address, normalised to 12 lower-case hex digits."""
    from bgt_core.wire import WireError, normalize_mac

    if isinstance(value, int | float) and not isinstance(value, bool):
        # 020000000001 unquoted is a number to YAML (octal, even): its digits are lost.
        raise ConfigError(f"{where}: {value!r:.40} was read as a number; quote the MAC ('...')")
    try:
        return normalize_mac(value)
    except WireError:
        raise ConfigError(f"{where}: not a MAC address: {value!r:.40}") from None


def name(value: Any, where: str) -> str:
    """A name that is also a folder name: letters, digits, '_', '-' and '.', at most 64."""
    text = value if isinstance(value, str) else ""
    if not NAME.match(text):
        raise ConfigError(
            f"{where}: {value!r:.40} is not a name: letters, digits, '_', '-' and '.', at most 64"
        )
    return text
