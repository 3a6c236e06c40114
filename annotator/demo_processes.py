"""The demo's child processes: the collector and the simulated agents it starts as console
scripts, their logs, stopping them cleanly, and the short CLI commands (start, stop) it runs."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from annotator.errors import DemoError

log = logging.getLogger(__name__)

# How long to wait for a child process to do its part; generous, the machine may be shared.
STARTUP_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def console_script(name: str, module: str) -> list[str]:
    """The installed console script next to this interpreter, else `python -m module`."""
    exe = Path(sys.executable).parent / name
    if exe.is_file() and os.access(exe, os.X_OK):
        return [str(exe)]
    return [sys.executable, "-m", module]


def log_tail(path: Path, n: int = 400) -> str:
    """Last non-empty line of a log file, for an error message."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1][-n:] if lines else ""


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    log_file: IO[bytes]


@dataclass
class Children:
    """Long-running child processes; all are stopped (SIGINT, then SIGKILL) when the block ends,
    whatever ends it, Ctrl-C included."""

    log_dir: Path
    children: list[Child] = field(default_factory=list)

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()

    def spawn(self, name: str, argv: list[str]) -> Child:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        f = log_path.open("wb")
        # Own process group: a Ctrl-C at the terminal reaches only the demo, which then stops the
        # children in order (agents first, so the collector drains what they sent).
        proc = subprocess.Popen(
            argv,
            stdout=f,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        child = Child(name, proc, log_path, f)
        self.children.append(child)
        log.debug("started %s (pid %d): %s", name, proc.pid, " ".join(argv))
        return child

    def check_alive(self) -> None:
        for c in self.children:
            rc = c.proc.poll()
            if rc is not None:
                raise DemoError(
                    f"{c.name} exited early with code {rc}: {log_tail(c.log_path)} (log: {c.log_path})"
                )

    def stop(self, child: Child, timeout: float = STOP_TIMEOUT_S) -> int | None:
        if child.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                child.proc.send_signal(signal.SIGINT)
            try:
                child.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s; killing it", child.name, timeout)
                child.proc.kill()
                child.proc.wait()
        child.log_file.close()
        if child in self.children:
            self.children.remove(child)
        return child.proc.returncode

    def stop_all(self) -> None:
        for c in list(reversed(self.children)):  # agents (started last) first, the collector last
            self.stop(c)


def run_cli(argv: list[str], what: str, timeout: float = STARTUP_TIMEOUT_S) -> str:
    """Run a short CLI command; its stdout, or DemoError with its last error line."""
    try:
        res = subprocess.run(
            argv,
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise DemoError(f"{what}: no answer within {timeout:.0f} s") from None
    if res.returncode != 0:
        lines = [ln for ln in (res.stderr + res.stdout).splitlines() if ln.strip()]
        raise DemoError(
            f"{what} failed: {lines[-1].strip() if lines else f'exit code {res.returncode}'}"
        )
    return res.stdout.strip()
