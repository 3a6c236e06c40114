"""Fixtures shared by every test folder: free loopback ports and the bundled dataset subset."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
DATASET = TESTS / "data" / "dataset"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoint() -> str:
    """A fresh loopback Zenoh endpoint, e.g. 'tcp/127.0.0.1:40123'."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def dataset_dir() -> Path:
    """The CC0 dataset subset shipped in tests/data/dataset (see its README)."""
    return DATASET
