"""Owns the site's PKI: one CA, and one certificate per node whose CN is the node's identity.

Zenoh's ACL matches clients by certificate common name, so the CN of an agent certificate
*is* its agent id; the collector certificate also carries the names agents dial it by (SANs).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

log = logging.getLogger(__name__)

CA_NAME = "ble-groundtruth site CA"
CA_DAYS = 3650
LEAF_DAYS = 825


class PkiError(RuntimeError):
    """A PKI directory that cannot be used (unreadable, mismatched, or half-written)."""


@dataclass(frozen=True, slots=True)
class Issued:
    """Where one node's files are: the CA certificate, its certificate and key (PEM)."""

    name: str
    root_ca: Path
    cert: Path
    key: Path


def _write(path: Path, data: bytes, private: bool) -> None:
    # Write-then-rename so an interrupted run never leaves a truncated key behind.
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    # PKCS#8 unencrypted: the key must load unattended when the service starts.
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _load(pki_dir: Path, stem: str) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = pki_dir / f"{stem}.crt", pki_dir / f"{stem}.key"
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError) as e:
        raise PkiError(f"{cert_path}: cannot load certificate/key: {e}") from e
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise PkiError(f"{key_path}: expected an EC private key")
    return cert, key


def ensure_ca(
    pki_dir: Path, now: dt.datetime
) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """Load the site CA from ``pki_dir`` or create it; an existing CA is never replaced."""
    pki_dir.mkdir(parents=True, exist_ok=True)
    if (pki_dir / "ca.crt").exists() or (pki_dir / "ca.key").exists():
        return _load(pki_dir, "ca")
    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, CA_NAME)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(pki_dir / "ca.key", _key_pem(key), private=True)
    _write(pki_dir / "ca.crt", cert.public_bytes(serialization.Encoding.PEM), private=False)
    log.info("created site CA in %s", pki_dir)
    return cert, key


def _san_entries(names: Iterable[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for n in dict.fromkeys(names):  # keep order, drop duplicates
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            out.append(x509.DNSName(n))
    return out


def _matches(
    cert: x509.Certificate, ca: x509.Certificate, cn: str, sans: list[str], now: dt.datetime
) -> bool:
    """True if an existing leaf still fits: same CN and SANs, signed by this CA, not near expiry."""
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    got_cn = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    try:
        ext = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        got_sans = {str(v) for v in ext.get_values_for_type(x509.DNSName)}
        got_sans |= {str(v) for v in ext.get_values_for_type(x509.IPAddress)}
    except x509.ExtensionNotFound:
        got_sans = set()
    want_sans = {str(g.value) for g in _san_entries(sans)}
    fresh = cert.not_valid_after_utc - now > dt.timedelta(days=30)
    return got_cn == [cn] and got_sans == want_sans and fresh


def issue(pki_dir: Path, cn: str, sans: Iterable[str], now: dt.datetime) -> Issued:
    """Make sure ``<cn>.crt``/``<cn>.key`` exist, fit, and are signed by the site CA.

    Idempotent: an existing certificate that still fits is kept (so re-running the playbook
    does not rotate every key); a mismatching one is reissued.
    """
    ca_cert, ca_key = ensure_ca(pki_dir, now)
    sans = list(sans) or [cn]
    crt_path, key_path = pki_dir / f"{cn}.crt", pki_dir / f"{cn}.key"
    if crt_path.exists() and key_path.exists():
        cert, _ = _load(pki_dir, cn)
        if _matches(cert, ca_cert, cn, sans, now):
            return Issued(cn, pki_dir / "ca.crt", crt_path, key_path)
        log.warning("reissuing %s: name, SANs, issuer or expiry changed", crt_path)
    key = _new_key()
    ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(min(now + dt.timedelta(days=LEAF_DAYS), ca_cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=True,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        # Every node is both: agents dial the collector (client) and the collector listens (server).
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(_san_entries(sans)), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    _write(key_path, _key_pem(key), private=True)
    _write(crt_path, cert.public_bytes(serialization.Encoding.PEM), private=False)
    log.info("issued certificate CN=%s SANs=%s", cn, ",".join(sans))
    return Issued(cn, pki_dir / "ca.crt", crt_path, key_path)


def common_name(cert_path: Path) -> str:
    """The CN of a PEM certificate (what the collector's ACL will see)."""
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except (OSError, ValueError) as e:
        raise PkiError(f"{cert_path}: not a PEM certificate: {e}") from e
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise PkiError(f"{cert_path}: certificate has no common name")
    return str(names[0].value)
