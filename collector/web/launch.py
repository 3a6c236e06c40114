"""`collector serve --web ADDR`: the console as a child process of the collector, connected to the
collector's own loopback endpoint; it ends with the collector. Starlette is imported only by the
child, so the collector starts without the web extra until --web is asked for."""

from __future__ import annotations

import subprocess
import sys

from collector.errors import CollectorError


def console_endpoint(listen: list[str]) -> str:
    """The endpoint the console connects to: the collector's first plain-TCP one, on loopback
    when it listens on every address."""
    for ep in listen:
        proto, _, addr = ep.partition("/")
        if proto != "tcp":
            continue
        host, _, port = addr.rpartition(":")
        if host in ("0.0.0.0", "[::]", "::"):
            host = "127.0.0.1"
        return f"tcp/{host}:{port}"
    raise CollectorError(
        "serve --web needs a tcp/ endpoint to reach the collector; with TLS only, run "
        "`collector web` with the operator's certificate"
    )


def spawn_console(listen: list[str], web: str, site: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable, "-m", "collector.cli", "web", "--connect", console_endpoint(listen),
            "--listen", web, "--site", site,
        ]
    )  # fmt: skip
