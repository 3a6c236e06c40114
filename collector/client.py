"""Talking to a running collector: a short-lived client-mode Zenoh session and one query per
control command, with a timeout and a one-line error when nobody answers."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from bgt_core import wire
from bgt_core.control_messages import Reply, StartReply, StartRequest, StopReply
from bgt_core.zenoh_config import DEFAULT_ENDPOINT, SessionSpec, TlsFiles, build_config
from collector.errors import CommandFailed, Unreachable

if TYPE_CHECKING:
    import zenoh

# How long each command may take once the collector has the request (stop drains first).
TIMEOUTS = {"start": 15.0, "stop": 60.0, "status": 10.0, "runs": 10.0}


class CollectorClient:
    def __init__(
        self,
        connect: str = DEFAULT_ENDPOINT,
        site: str = "default",
        connect_timeout_s: float = 3.0,
        tls: TlsFiles | None = None,
    ) -> None:
        self.connect = connect
        self.site = site
        self.tls = tls  # the operator's certificate when the collector listens on tls/...
        self._timeout_ms = int(connect_timeout_s * 1000)
        self._session: zenoh.Session | None = None

    def __enter__(self) -> CollectorClient:
        import zenoh

        spec = SessionSpec(
            mode="client",
            connect=[self.connect],
            tls=self.tls,
            extra={"connect/timeout_ms": self._timeout_ms},
        )
        try:
            self._session = zenoh.open(build_config(spec))
        except zenoh.ZError:
            raise Unreachable(self._unreachable()) from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    def _unreachable(self) -> str:
        return f"no collector answered at {self.connect} (is `collector serve` running?)"

    def _no_reply(self, command: str) -> str:
        # The session opened, so a router is there: either it is not our collector, or its ACL
        # drops this query (a certificate the collector does not let drive runs).
        return (
            f"no reply to {command} from {self.connect} — the collector is not running there, "
            "or it is not allowed for this certificate?"
        )

    def call(self, command: str, request: dict[str, Any] | None = None) -> dict[str, Any]:
        """Send one control request; returns the reply without its "ok" field."""
        key = wire.collector_control_key(self.site, command)
        payload = json.dumps(request or {}).encode()
        if self._session is None:
            raise Unreachable("not connected: use the client in a `with` block")
        replies = self._session.get(key, payload=payload, timeout=TIMEOUTS[command])
        for reply in replies:
            if reply.ok is None:
                why = "no reason given" if reply.err is None else reply.err.payload.to_string()
                raise CommandFailed(f"{command}: {why}")
            msg = Reply.from_dict(
                wire.from_json(reply.ok.payload.to_bytes(), f"{command} reply"), command
            )
            if not msg.ok:
                raise CommandFailed(f"{command}: {msg.error or 'failed without a reason'}")
            return msg.body
        raise Unreachable(self._no_reply(command))

    def start(
        self,
        name: str | None = None,
        *,
        max_offset_ms: float | None = None,
        strict: bool = False,
        notes: str | None = None,
    ) -> dict[str, Any]:
        return self.call("start", StartRequest(name, max_offset_ms, strict, notes).to_dict())

    def stop(self) -> dict[str, Any]:
        return self.call("stop")

    def start_typed(
        self,
        name: str | None = None,
        *,
        max_offset_ms: float | None = None,
        strict: bool = False,
        notes: str | None = None,
    ) -> StartReply:
        """``start``, its reply checked and typed."""
        return StartReply.from_dict(
            self.start(name, max_offset_ms=max_offset_ms, strict=strict, notes=notes)
        )

    def stop_typed(self) -> StopReply:
        """``stop``, its reply checked and typed."""
        return StopReply.from_dict(self.stop())

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def runs(self) -> list[dict[str, Any]]:
        runs: list[dict[str, Any]] = self.call("runs")["runs"]
        return runs
