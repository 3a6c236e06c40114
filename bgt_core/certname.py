"""The subject common name (CN) of a PEM certificate, read with the standard library only.

Zenoh's ACL identifies TLS clients by their certificate's CN, so an agent compares it with its
configured agent id at start-up. The agent does not depend on ``cryptography``; this walks just
enough DER to reach the subject (RFC 5280: Certificate -> TBSCertificate -> subject Name).
"""

from __future__ import annotations

import base64
import re
from pathlib import Path

_PEM_RE = re.compile(rb"-----BEGIN CERTIFICATE-----\s*(.+?)\s*-----END CERTIFICATE-----", re.S)
_CN_OID = bytes([0x06, 0x03, 0x55, 0x04, 0x03])  # OBJECT IDENTIFIER 2.5.4.3
_STRING_TAGS = {0x0C, 0x13, 0x14, 0x16, 0x1E}  # UTF8, Printable, Teletex, IA5, BMP strings


class CertificateError(ValueError):
    """Not a PEM certificate this reader understands."""


def _tlv(buf: bytes, off: int) -> tuple[int, int, int]:
    """(tag, start of content, end of content) of the DER element at ``off``."""
    if off + 2 > len(buf):
        raise CertificateError("truncated DER")
    tag, n = buf[off], buf[off + 1]
    off += 2
    if n & 0x80:
        k = n & 0x7F
        if not 1 <= k <= 4 or off + k > len(buf):
            raise CertificateError("bad DER length")
        n = int.from_bytes(buf[off : off + k], "big")
        off += k
    if off + n > len(buf):
        raise CertificateError("truncated DER")
    return tag, off, off + n


def _children(buf: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
    out = []
    while start < end:
        tag, s, e = _tlv(buf, start)
        out.append((tag, s, e))
        start = e
    return out


def subject_cn(der: bytes) -> str | None:
    """The first CN of the certificate's subject, or None if it has none."""
    _t, s, e = _tlv(der, 0)  # Certificate
    _t, s, e = _tlv(der, s)  # TBSCertificate
    fields = _children(der, s, e)
    if fields and fields[0][0] == 0xA0:  # [0] version
        fields = fields[1:]
    if len(fields) < 5:
        raise CertificateError("TBSCertificate too short")
    _t, s, e = fields[4]  # serial, signature, issuer, validity, subject
    for _set_tag, rs, re_ in _children(der, s, e):  # RelativeDistinguishedName (SET)
        for _seq_tag, as_, ae in _children(der, rs, re_):  # AttributeTypeAndValue
            parts = _children(der, as_, ae)
            if (
                len(parts) == 2
                and der[as_ : parts[0][2]] == _CN_OID
                and parts[1][0] in _STRING_TAGS
            ):
                raw = der[parts[1][1] : parts[1][2]]
                return raw.decode("utf-16-be" if parts[1][0] == 0x1E else "utf-8", errors="replace")
    return None


def certificate_cn(path: str | Path) -> str | None:
    """The CN of the first certificate in a PEM file; CertificateError or OSError otherwise."""
    m = _PEM_RE.search(Path(path).read_bytes())
    if m is None:
        raise CertificateError(f"{path}: no PEM certificate")
    try:
        der = base64.b64decode(b"".join(m.group(1).split()), validate=True)
    except ValueError as e:
        raise CertificateError(f"{path}: bad base64 in the certificate") from e
    return subject_cn(der)
