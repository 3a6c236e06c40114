"""Mutual TLS + the generated ACL on real zenoh sessions over loopback.

A router plays the collector (mTLS listener, ACL from ``build_acl``); clients connect as
agents a1/a2 (their own certificates), as the operator CLI, and without a certificate.
What a1 may or may not do is judged by what the router-side subscriber/queryable receives.
"""

from __future__ import annotations

import datetime as dt
import json
import threading
from pathlib import Path

import pytest
import zenoh
from zenoh import ext

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config, load_acl
from deploy import pki
from deploy.acl import build_acl
from deploy_helpers import ADMINS, AGENTS, free_port, wait_until

SITE = "default"
MAC1, MAC2 = "aabbccddee01", "aabbccddee02"


def tls_for(pki_dir: Path, cn: str) -> TlsFiles:
    return TlsFiles(str(pki_dir / "ca.crt"), str(pki_dir / f"{cn}.crt"), str(pki_dir / f"{cn}.key"))


class Router:
    """The collector's side: records every data sample and every control query it receives."""

    def __init__(self, pki_dir: Path, tmp_path: Path) -> None:
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        acl_file = tmp_path / "acl.json5"
        acl_file.write_text(json.dumps(build_acl(SITE, list(AGENTS), list(ADMINS)), indent=2))
        spec = SessionSpec(
            mode="router",
            listen=[self.endpoint],
            tls=tls_for(pki_dir, "collector"),
            acl=load_acl(acl_file),
        )
        self.session = zenoh.open(build_config(spec))
        self.lock = threading.Lock()
        self.data: list[tuple[str, bytes]] = []
        self.control: list[str] = []
        self._sub = self.session.declare_subscriber(wire.data_selector(SITE), self._on_data)
        self._qs = [
            self.session.declare_queryable(wire.collector_control_key(SITE, cmd), self._on_control)
            for cmd in ("start", "stop")
        ]

    def _on_data(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.data.append((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_control(self, query: zenoh.Query) -> None:
        with self.lock:
            self.control.append(str(query.key_expr))
        query.reply(query.key_expr, wire.to_json({"ok": True, "run_id": "r"}))

    def received(self) -> list[tuple[str, bytes]]:
        with self.lock:
            return list(self.data)

    def client(self, pki_dir: Path, cn: str | None) -> zenoh.Session:
        tls = tls_for(pki_dir, cn) if cn else None
        return zenoh.open(
            build_config(SessionSpec(mode="client", connect=[self.endpoint], tls=tls))
        )


@pytest.fixture
def router(pki_dir: Path, tmp_path: Path):
    r = Router(pki_dir, tmp_path)
    yield r
    r.session.close()


@pytest.fixture
def agents(router: Router, pki_dir: Path):
    sessions = {a: router.client(pki_dir, a) for a in AGENTS}
    yield sessions
    for s in sessions.values():
        s.close()


def put_until_seen(router: Router, session: zenoh.Session, key: str, payload: bytes) -> None:
    """Publish a legitimate sample, re-sending until the router has it (declarations are async)."""

    def seen() -> bool:
        session.put(key, payload)
        return (key, payload) in router.received()

    assert wait_until(seen, step=0.2), f"router never received {key}"


def test_client_without_certificate_is_refused(router: Router, pki_dir: Path) -> None:
    # No TLS settings at all, then trusting the CA but presenting no certificate.
    with pytest.raises(zenoh.ZError):
        router.client(pki_dir, None)
    conf = build_config(SessionSpec(mode="client", connect=[router.endpoint]))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki_dir / "ca.crt")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(conf)


def test_client_with_certificate_of_another_ca_is_refused(
    router: Router, pki_dir: Path, tmp_path: Path
) -> None:
    rogue = tmp_path / "rogue"
    pki.issue(rogue, "a1", ["a1"], dt.datetime.now(dt.UTC))  # right CN, wrong CA
    tls = TlsFiles(str(pki_dir / "ca.crt"), str(rogue / "a1.crt"), str(rogue / "a1.key"))
    with pytest.raises(zenoh.ZError):
        zenoh.open(build_config(SessionSpec(mode="client", connect=[router.endpoint], tls=tls)))


def test_agent_cannot_publish_as_another(router: Router, agents: dict[str, zenoh.Session]) -> None:
    a1, a2 = agents["a1"], agents["a2"]
    own1, own2 = wire.data_key(SITE, "a1", MAC1), wire.data_key(SITE, "a2", MAC2)
    put_until_seen(router, a1, own1, b"a1-first")
    put_until_seen(router, a2, own2, b"a2-first")
    # a1 tries to write into a2's stream, into a made-up agent's, and outside the data tree.
    for i in range(20):
        a1.put(own2, f"spoof-{i}".encode())
        a1.put(wire.data_key(SITE, "a3", MAC1), b"spoof-a3")
        a1.put(f"ble/{SITE}/ack/a2", b"spoof-ack")
    # Legitimate data keeps flowing meanwhile and after.
    put_until_seen(router, a1, own1, b"a1-after")
    put_until_seen(router, a2, own2, b"a2-after")
    got = router.received()
    assert not [p for _, p in got if p.startswith(b"spoof")]
    assert {k for k, _ in got} == {own1, own2}
    assert all(p.startswith(b"a2-") for k, p in got if k == own2)


def test_agent_cannot_start_or_stop_a_run(
    router: Router, agents: dict[str, zenoh.Session], pki_dir: Path
) -> None:
    a1 = agents["a1"]
    own1 = wire.data_key(SITE, "a1", MAC1)
    put_until_seen(router, a1, own1, b"before")
    for cmd in ("start", "stop"):
        replies = list(a1.get(wire.collector_control_key(SITE, cmd), timeout=2.0))
        assert [r for r in replies if r.ok is not None] == []
    assert router.control == []
    # The operator certificate may; that proves the queryables were there to be denied.
    op = router.client(pki_dir, "operator")
    try:
        replies = list(op.get(wire.collector_control_key(SITE, "start"), timeout=5.0))
        assert [wire.from_json(r.ok.payload.to_bytes())["ok"] for r in replies if r.ok] == [True]
        assert router.control == [wire.collector_control_key(SITE, "start")]
    finally:
        op.close()
    put_until_seen(router, a1, own1, b"after")


def test_agent_cannot_answer_for_another(
    router: Router, agents: dict[str, zenoh.Session], pki_dir: Path
) -> None:
    a1, a2 = agents["a1"], agents["a2"]

    def status_of(key_agent: str, claims: str):
        # Replies carry a concrete key, as a real agent's do (a query's key may be a wildcard).
        key = wire.agent_status_key(SITE, key_agent)
        return lambda q: q.reply(key, wire.to_json({"agent_id": claims}))

    # a1 declares a status queryable and a liveliness token in a2's name, besides its own.
    q_fake = a1.declare_queryable(wire.agent_status_key(SITE, "a2"), status_of("a2", "a1-as-a2"))
    q1 = a1.declare_queryable(wire.agent_status_key(SITE, "a1"), status_of("a1", "a1"))
    q2 = a2.declare_queryable(wire.agent_status_key(SITE, "a2"), status_of("a2", "a2"))
    t_fake = a1.liveliness().declare_token(wire.agent_token_key(SITE, "a2"))
    t1 = a1.liveliness().declare_token(wire.agent_token_key(SITE, "a1"))
    op = router.client(pki_dir, "operator")
    try:

        def answers() -> list[str]:
            replies = op.get(wire.agent_status_selector(SITE), timeout=2.0)
            return sorted(
                wire.from_json(r.ok.payload.to_bytes())["agent_id"] for r in replies if r.ok
            )

        assert wait_until(lambda: answers() == ["a1", "a2"], step=0.2), answers()

        def tokens() -> list[str]:
            replies = op.liveliness().get(wire.agent_token_selector(SITE), timeout=2.0)
            return sorted(str(r.ok.key_expr) for r in replies if r.ok)

        assert wait_until(lambda: tokens() == [wire.agent_token_key(SITE, "a1")], step=0.2), (
            tokens()
        )
    finally:
        op.close()
        for obj in (q_fake, q1, q2, t_fake, t1):
            obj.undeclare()


def test_acks_reach_only_their_agent(router: Router, agents: dict[str, zenoh.Session]) -> None:
    got: dict[str, list[bytes]] = {"a1": [], "a2": []}
    # a1 also tries to listen to a2's acks.
    subs = [
        agents["a1"].declare_subscriber(
            wire.ack_key(SITE, "a1"), lambda s: got["a1"].append(s.payload.to_bytes())
        ),
        agents["a1"].declare_subscriber(
            wire.ack_key(SITE, "a2"), lambda s: got["a1"].append(s.payload.to_bytes())
        ),
        agents["a2"].declare_subscriber(
            wire.ack_key(SITE, "a2"), lambda s: got["a2"].append(s.payload.to_bytes())
        ),
    ]

    def ack(agent: str) -> bytes:
        return wire.to_json({"boot": "0123456789abcdef", "streams": {MAC1: 1}, "for": agent})

    assert wait_until(
        lambda: router.session.put(wire.ack_key(SITE, "a1"), ack("a1")) or bool(got["a1"]), step=0.2
    )
    assert wait_until(
        lambda: router.session.put(wire.ack_key(SITE, "a2"), ack("a2")) or bool(got["a2"]), step=0.2
    )
    router.session.put(wire.ack_key(SITE, "a2"), ack("a2"))
    assert wait_until(lambda: len(got["a2"]) >= 2)
    assert set(got["a1"]) == {ack("a1")}
    assert set(got["a2"]) == {ack("a2")}
    for s in subs:
        s.undeclare()


def test_advanced_publisher_history_passes_the_acl(
    router: Router, agents: dict[str, zenoh.Session]
) -> None:
    """The ``@adv`` keys: a late advanced subscriber on the router recovers a1's cached samples."""
    key = wire.data_key(SITE, "a1", MAC1)
    pub = ext.declare_advanced_publisher(
        agents["a1"],
        key,
        cache=ext.CacheConfig(max_samples=100),
        sample_miss_detection=ext.MissDetectionConfig(heartbeat=0.2),
        publisher_detection=True,
    )
    for i in range(5):
        pub.put(f"cached-{i}".encode())
    got: list[bytes] = []
    sub = ext.declare_advanced_subscriber(
        router.session,
        wire.data_selector(SITE),
        lambda s: got.append(s.payload.to_bytes()),
        history=ext.HistoryConfig(detect_late_publishers=True),
        recovery=ext.RecoveryConfig(heartbeat=True),
        subscriber_detection=True,
    )
    try:
        want = [f"cached-{i}".encode() for i in range(5)]
        assert wait_until(lambda: got[:5] == want), got
        pub.put(b"live")
        assert wait_until(lambda: got[-1:] == [b"live"]), got
    finally:
        sub.undeclare()
        pub.undeclare()
