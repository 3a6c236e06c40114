"""Fixtures shared by every test folder: free loopback ports and the bundled dataset subset."""

from __future__ import annotations

from pathlib import Path

import pytest

from loopback import free_port

TESTS = Path(__file__).resolve().parent
DATASET = TESTS / "data" / "dataset"


@pytest.fixture
def endpoint() -> str:
    """A fresh loopback Zenoh endpoint, e.g. 'tcp/127.0.0.1:40123'."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def dataset_dir() -> Path:
    """The CC0 dataset subset shipped in tests/data/dataset (see its README)."""
    return DATASET
