"""Fixtures for the deployment tests: one site PKI (CA + certificates) made per session."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest

from deploy import pki
from deploy_helpers import AGENTS


@pytest.fixture(scope="session")
def pki_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA plus certificates for the collector (with loopback SANs), the operator, a1 and a2."""
    d = tmp_path_factory.mktemp("pki")
    now = dt.datetime.now(dt.UTC)
    pki.issue(d, "collector", ["collector", "localhost", "127.0.0.1"], now)
    for cn in ("operator", *AGENTS):
        pki.issue(d, cn, [cn], now)
    return d
