"""Site PKI: CN = identity, CA-signed, idempotent, reissued when the names change."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from cryptography import x509

from deploy import pki

NOW = dt.datetime(2026, 11, 22, 3, 0, tzinfo=dt.UTC)


def test_issue_signs_with_the_site_ca_and_sets_names(tmp_path: Path) -> None:
    got = pki.issue(tmp_path, "collector", ["collector", "192.168.50.10"], NOW)
    ca = x509.load_pem_x509_certificate(got.root_ca.read_bytes())
    cert = x509.load_pem_x509_certificate(got.cert.read_bytes())
    cert.verify_directly_issued_by(ca)
    assert pki.common_name(got.cert) == "collector"
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["collector"]
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["192.168.50.10"]
    assert got.key.stat().st_mode & 0o077 == 0  # private keys are owner-only
    assert (tmp_path / "ca.key").stat().st_mode & 0o077 == 0


def test_issue_is_idempotent_and_reissues_on_change(tmp_path: Path) -> None:
    first = pki.issue(tmp_path, "pi-01", ["pi-01"], NOW).cert.read_bytes()
    ca = (tmp_path / "ca.crt").read_bytes()
    assert (
        pki.issue(tmp_path, "pi-01", ["pi-01"], NOW + dt.timedelta(days=1)).cert.read_bytes()
        == first
    )
    changed = pki.issue(tmp_path, "pi-01", ["pi-01", "10.0.0.5"], NOW).cert.read_bytes()
    assert changed != first
    # Near expiry (< 30 days left) it is renewed; the CA itself is never replaced.
    late = NOW + dt.timedelta(days=pki.LEAF_DAYS - 10)
    assert pki.issue(tmp_path, "pi-01", ["pi-01", "10.0.0.5"], late).cert.read_bytes() != changed
    assert (tmp_path / "ca.crt").read_bytes() == ca


def test_certificate_from_another_ca_is_replaced(tmp_path: Path) -> None:
    pki.issue(tmp_path / "other", "pi-01", ["pi-01"], NOW)
    pki.ensure_ca(tmp_path / "site", NOW)
    for name in ("pi-01.crt", "pi-01.key"):
        (tmp_path / "site" / name).write_bytes((tmp_path / "other" / name).read_bytes())
    got = pki.issue(tmp_path / "site", "pi-01", ["pi-01"], NOW)
    ca = x509.load_pem_x509_certificate(got.root_ca.read_bytes())
    x509.load_pem_x509_certificate(got.cert.read_bytes()).verify_directly_issued_by(ca)
