"""Detection recall against the truth on clean and degraded frames (issue 29): the share of the
markers wholly in view that the tracker's detector finds, above floors measured with
bench/detection_recall.py (a drop below them is a regression)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))

from detection_recall import SIZES, conditions, measure  # noqa: E402

# Measured on 60 frames (bench/detection_recall.py); the test renders fewer, so a margin.
FLOORS = {"clean-540": 0.75, "real-540": 0.30}


@pytest.mark.parametrize("name", sorted(FLOORS))
def test_recall_above_its_floor(name: str) -> None:
    r = measure(conditions()[name], frames=12)
    assert len(r.expected) >= 40
    assert r.share() >= FLOORS[name]
    assert r.share(*SIZES[-1]) > 0.95  # markers over 40 px are found whatever the imaging
