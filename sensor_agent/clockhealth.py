"""What the agent knows about its own clock: ``chronyc tracking`` parsed into numbers, for the
collector's four-timestamp clock exchange (the reply itself is built by the publisher)."""

from __future__ import annotations

import logging
import shutil
import subprocess
from typing import Any

log = logging.getLogger(__name__)

CHRONYC_TIMEOUT_S = 2.0


def _seconds(value: str) -> float | None:
    """'0.000012345 seconds fast of NTP time' -> 1.2345e-05 (slow -> negative); None if unparsable."""
    parts = value.split()
    try:
        x = float(parts[0])
    except (IndexError, ValueError):
        return None
    if "slow" in parts:
        x = -x
    return x


def parse_chronyc_tracking(text: str) -> dict[str, Any]:
    """The fields of ``chronyc tracking`` output the collector stores, as numbers.

    ``system_time_offset_s`` is the system clock minus NTP time (positive = fast), as chrony
    reports it; fields missing from the text are None.
    """
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields[key.strip().lower()] = value.strip()
    out: dict[str, Any] = {
        "ref_id": None,
        "stratum": None,
        "system_time_offset_s": None,
        "last_offset_s": None,
        "rms_offset_s": None,
        "frequency_ppm": None,
        "root_delay_s": None,
        "root_dispersion_s": None,
        "leap_status": None,
    }
    if "reference id" in fields:
        out["ref_id"] = fields["reference id"]
    if "stratum" in fields:
        try:
            out["stratum"] = int(fields["stratum"])
        except ValueError:
            pass
    for name, key in (
        ("system_time_offset_s", "system time"),
        ("last_offset_s", "last offset"),
        ("rms_offset_s", "rms offset"),
        ("root_delay_s", "root delay"),
        ("root_dispersion_s", "root dispersion"),
    ):
        if key in fields:
            out[name] = _seconds(fields[key])
    if "frequency" in fields:
        out["frequency_ppm"] = _seconds(fields["frequency"])  # same 'N unit slow|fast' shape
    if "leap status" in fields:
        out["leap_status"] = fields["leap status"]
    return out


def read_chrony() -> dict[str, Any] | None:
    """``chronyc tracking`` parsed, or None when chrony is not installed or does not answer.

    Blocking (runs a subprocess): call it from a worker thread."""
    exe = shutil.which("chronyc")
    if exe is None:
        return None
    try:
        r = subprocess.run(
            [exe, "tracking"],
            capture_output=True,
            text=True,
            timeout=CHRONYC_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        log.debug("chronyc tracking failed: %s", e)
        return None
    if r.returncode != 0:
        log.debug("chronyc tracking exited %d: %s", r.returncode, r.stderr.strip())
        return None
    return parse_chronyc_tracking(r.stdout)
