"""`.hst` fingerprint histograms: bin edges, the site's devices and one normalised RSSI histogram
per (reference position, sensor, beacon). Standard library only; see docs/formats.md."""

from __future__ import annotations

import ast
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats._textio import check_nesting, read_text, write_text_atomic
from bgt_core.formats.devices import (
    Devices,
    SiteConfigError,
    devices_from_obj,
    devices_to_obj,
)
from bgt_core.wire import WireError, normalize_mac

Position = tuple[float, float, float]
# position -> sensor MAC -> beacon MAC -> histogram (len(bins) - 1 probabilities)
FingerprintTable = dict[Position, dict[str, dict[str, tuple[float, ...]]]]

DEFAULT_BINS: tuple[float, ...] = tuple(float(v) for v in range(-100, -19))


class HstError(ValueError):
    """A malformed .hst file; the message names the file and line."""


@dataclass(frozen=True, slots=True)
class FingerprintHistograms:
    bins: tuple[float, ...]  # bin edges in dBm; each histogram has len(bins) - 1 entries
    devices: Devices
    fingerprints: FingerprintTable


def check_edges(obj: object) -> tuple[float, ...]:
    """Bin edges as floats; ValueError unless at least two, finite and strictly increasing."""
    if not isinstance(obj, list | tuple) or len(obj) < 2:
        raise ValueError("expected a list of at least two bin edges")
    edges = tuple(float(v) for v in obj)
    if not all(math.isfinite(v) for v in edges) or any(
        b <= a for a, b in zip(edges, edges[1:], strict=False)
    ):
        raise ValueError("bin edges must be finite and increase")
    return edges


def position_key(pos: Iterable[float]) -> str:
    """The published key spelling: ``str()`` of a tuple of floats, e.g. ``'(12.95, 16.8, 1.85)'``."""
    return str(tuple(float(v) for v in pos))


_NUM = r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*"
# '(x, y, z)' (or '[x, y, z]'): three plain numbers, one level of brackets and nothing else.
_POSITION_KEY = re.compile(rf"^\s*[(\[]{_NUM},{_NUM},{_NUM},?\s*[)\]]\s*$")


def parse_position_key(key: str) -> Position:
    m = _POSITION_KEY.match(key) if len(key) <= 200 else None
    if m is None:
        raise ValueError(f"position key {key[:60]!r} is not '(x, y, z)'")
    x, y, z = (float(v) for v in m.groups())
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"position key {key[:60]!r}: coordinates must be finite")
    return (x, y, z)


def _decode(value: str) -> object:
    # The published files are valid JSON (fast to parse); Python-literal spellings are accepted too.
    # Nesting is checked first: no input can reach a RecursionError.
    check_nesting(value)
    try:
        return json.loads(value)
    except ValueError:
        return ast.literal_eval(value.strip())


def _histogram(values: object, n: int, where: str) -> tuple[float, ...]:
    if not isinstance(values, list | tuple) or len(values) != n:
        got = len(values) if isinstance(values, list | tuple) else type(values).__name__
        raise ValueError(f"{where}: expected {n} probabilities, got {got}")
    out = tuple(float(v) for v in values)
    if not all(math.isfinite(v) and v >= 0.0 for v in out):
        raise ValueError(f"{where}: probabilities must be finite and non-negative")
    return out


def _fingerprints(obj: object, n: int) -> FingerprintTable:
    if not isinstance(obj, dict):
        raise TypeError("expected an object {'(x, y, z)': {sensor: {beacon: [...]}}}")
    table: FingerprintTable = {}
    for key, sensors in obj.items():
        pos = parse_position_key(str(key))
        if not isinstance(sensors, dict):
            raise TypeError(f"{key}: expected {{sensor: {{beacon: [...]}}}}")
        per_sensor: dict[str, dict[str, tuple[float, ...]]] = {}
        for sensor, beacons in sensors.items():
            if not isinstance(beacons, dict):
                raise TypeError(f"{key} {sensor}: expected {{beacon: [...]}}")
            smac = normalize_mac(sensor)
            per_sensor[smac] = {
                normalize_mac(b): _histogram(h, n, f"{key} {sensor} {b}")
                for b, h in beacons.items()
            }
        if pos in table:
            raise ValueError(f"position {key} listed twice")
        table[pos] = per_sensor
    return table


def parse_hst(text: str, source: str = "<hst>") -> FingerprintHistograms:
    fields: dict[str, tuple[int, object]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise HstError(f"{source}:{lineno}: expected 'Key:<literal>'")
        try:
            fields[key.strip()] = (lineno, _decode(value))
        except ValueError as e:
            if str(e).startswith("nested deeper"):
                raise HstError(f"{source}:{lineno}: {key.strip()[:40]}: {e}") from None
            raise HstError(
                f"{source}:{lineno}: {key.strip()[:40]} is not a valid literal"
            ) from None
        except (SyntaxError, MemoryError, RecursionError, TypeError):
            raise HstError(
                f"{source}:{lineno}: {key.strip()[:40]} is not a valid literal"
            ) from None
    for required in ("Bins", "Dongles", "Fingerprints"):
        if required not in fields:
            raise HstError(f"{source}: no '{required}:' line")
    lineno, bins_obj = fields["Bins"]
    try:
        bins = check_edges(bins_obj)
    except (TypeError, ValueError, OverflowError) as e:
        raise HstError(f"{source}:{lineno}: Bins: {e}") from None
    d_line, dongles = fields["Dongles"]
    b_line, beacons = fields.get("Beacons", (d_line, {}))
    try:  # each part checked on its own, so the message names its line
        devices = Devices(
            devices_from_obj(dongles, {}, f"{source}:{d_line}").dongles,
            devices_from_obj({}, beacons, f"{source}:{b_line}").beacons,
        )
    except SiteConfigError as e:
        raise HstError(str(e)) from None
    lineno, fp_obj = fields["Fingerprints"]
    try:
        table = _fingerprints(fp_obj, len(bins) - 1)
    except (ValueError, TypeError, WireError, OverflowError) as e:
        raise HstError(f"{source}:{lineno}: Fingerprints: {e}") from None
    return FingerprintHistograms(bins, devices, table)


def read_hst(path: str | Path) -> FingerprintHistograms:
    path = Path(path)
    return parse_hst(read_text(path, HstError), str(path))


def format_hst(h: FingerprintHistograms) -> str:
    """The published layout: JSON-spelled values, ``Fingerprints:{ `` opening, newline at the end."""
    dongles, beacons = devices_to_obj(h.devices)
    entries = []
    for pos, sensors in h.fingerprints.items():
        body = {
            s: {b: [float(v) for v in p] for b, p in beacons_.items()}
            for s, beacons_ in sensors.items()
        }
        entries.append(f"{json.dumps(position_key(pos))}: {json.dumps(body)}")
    return (
        f"Bins:{json.dumps([float(b) for b in h.bins])}\n"
        f"Dongles:{json.dumps(dongles)}\n"
        f"Beacons:{json.dumps(beacons)}\n"
        f"Fingerprints:{{ {', '.join(entries)}}}\n"
    )


def write_hst(h: FingerprintHistograms, path: str | Path) -> None:
    """Write atomically (temporary file + rename) so a failed run never leaves half a file."""
    write_text_atomic(Path(path), format_hst(h))


def histograms_from_mapping(
    bins: Iterable[float],
    devices: Devices,
    table: Mapping[Iterable[float], Mapping[str, Mapping[str, Iterable[float]]]],
) -> FingerprintHistograms:
    """Build the record from any nested mapping (numpy arrays welcome), converting to floats."""
    bins_t = tuple(float(b) for b in bins)
    out: FingerprintTable = {}
    for pos, sensors in table.items():
        key = tuple(float(v) for v in pos)
        if len(key) != 3:
            raise ValueError(f"position {pos!r} is not (x, y, z)")
        out[key] = {
            s: {
                b: _histogram([float(v) for v in p], len(bins_t) - 1, f"{key} {s} {b}")
                for b, p in beacons.items()
            }
            for s, beacons in sensors.items()
        }
    return FingerprintHistograms(bins_t, devices, out)
