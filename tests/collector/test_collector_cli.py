"""The `collector` command line in real processes over loopback Zenoh, including the end-to-end
capture with two real `sensor-agent` processes replaying the bundled trajectory."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest
import yaml

from bgt_core.formats.mbd import iter_rows
from collector.client import CollectorClient
from collector.errors import CollectorError
from collector_helpers import FakeAgent, expected_lines, make_batch, wait_for

COLLECTOR = [sys.executable, "-m", "collector.cli"]
SENSOR_AGENT = Path(sys.executable).with_name("sensor-agent")


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([*COLLECTOR, *args], capture_output=True, text=True, timeout=timeout)


def reachable(endpoint: str) -> bool:
    try:
        with CollectorClient(endpoint, connect_timeout_s=0.5) as c:
            c.status()
    except CollectorError:
        return False
    return True


@pytest.fixture
def serve(tmp_path, endpoint):
    """`collector serve` in its own process; yields its data dir; SIGTERM at the end must exit 0."""
    data = tmp_path / "data"
    proc = subprocess.Popen(
        [*COLLECTOR, "serve", "--data-dir", str(data), "--listen", endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(
            lambda: proc.poll() is not None or reachable(endpoint), 30, "collector serve to answer"
        )
        assert proc.poll() is None, proc.stderr.read()
        yield data
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err


def rows_by_sensor(paths) -> dict[str, list[tuple]]:
    out: dict[str, list[tuple]] = defaultdict(list)
    for p in paths:
        for r in iter_rows(p):
            out[r.sensor].append((r.t_ns, r.sensor, r.beacon, r.rssi))
    return dict(out)


@pytest.mark.slow
@pytest.mark.skipif(not SENSOR_AGENT.exists(), reason="sensor-agent is not installed")
def test_two_replaying_agents_end_to_end(serve, endpoint, dataset_dir) -> None:
    files = sorted((dataset_dir / "trk" / "straight_01").glob("*.mbd"))
    assert len(files) == 12
    started = cli("start", "--name", "e2e", "--connect", endpoint)
    assert started.returncode == 0, started.stderr
    run_id = started.stdout.strip()
    agents = [
        subprocess.Popen(
            [
                str(SENSOR_AGENT),
                "run",
                "--agent-id",
                f"pi-{i}",
                "--site",
                "default",
                "--connect",
                endpoint,
                "--replay-speed",
                "0",
                "--replay-keep-time",
                *[a for f in half for a in ("--replay", str(f))],
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i, half in enumerate((files[:6], files[6:]))
    ]
    for a in agents:
        _out, err = a.communicate(timeout=120)
        assert a.returncode == 0, err  # 0 = every batch was acknowledged by the collector
    stopped = cli("stop", "--connect", endpoint)
    assert stopped.returncode == 0, stopped.stderr
    run_dir = Path(stopped.stdout.strip())
    assert run_dir == (serve / run_id).resolve()

    want = rows_by_sensor(files)
    got = rows_by_sensor(sorted((run_dir / "rssi").glob("*/*.mbd")))
    assert sorted(got) == sorted(want)
    assert len(got) == 12
    for sensor, rows in want.items():
        assert sorted(got[sensor]) == sorted(rows), sensor
        assert len(got[sensor]) == len(rows)
    doc = yaml.safe_load((run_dir / "run.yaml").read_text())
    assert doc["readings"] == sum(len(r) for r in want.values())
    assert sorted(doc["agents"]) == ["pi-0", "pi-1"]
    assert sum(len(a["sensors"]) for a in doc["agents"].values()) == 12
    assert doc["missing_batches"] == 0


def test_cli_start_status_stop_runs(serve, endpoint) -> None:
    agent = FakeAgent(endpoint)
    try:
        agent.declare_token()
        run_id = cli("start", "--name", "cli", "--connect", endpoint).stdout.strip()
        assert run_id.endswith("Z-cli")
        batches = [make_batch(i) for i in range(3)]
        for b in batches:
            agent.put(b)
        wait_for(lambda: agent.acked(batches[0].sensor) == 2, what="acks")
        st = cli("status", "--json", "--connect", endpoint)
        assert st.returncode == 0, st.stderr
        doc = json.loads(st.stdout)
        assert doc["run"]["run_id"] == run_id
        sensor = doc["agents"]["pi-01"]["sensors"][batches[0].sensor]
        assert doc["agents"]["pi-01"]["alive"] is True
        assert sensor["readings"] == 15
        table = cli("status", "--connect", endpoint)
        assert batches[0].sensor in table.stdout
        assert "pi-01" in table.stdout
        live = cli("live", "--connect", endpoint, "--duration", "0.6", "--interval", "0.2")
        assert live.returncode == 0
        assert batches[0].sensor in live.stdout
        stop = cli("stop", "--connect", endpoint)
        assert stop.returncode == 0
        run_dir = Path(stop.stdout.strip())
        assert (
            run_dir / "rssi" / "pi-01" / f"{batches[0].sensor}.mbd"
        ).read_text().splitlines() == expected_lines(batches)
        runs = json.loads(cli("runs", "--json", "--connect", endpoint).stdout)
        assert [(r["run_id"], r["name"], r["readings"]) for r in runs] == [(run_id, "cli", 15)]
        assert "cli" in cli("runs", "--connect", endpoint).stdout
        again = cli("stop", "--connect", endpoint)
        assert again.returncode == 1
        assert again.stderr.strip() == "stop: no run is active"
    finally:
        agent.close()


@pytest.mark.parametrize("command", [["start"], ["stop"], ["status"], ["runs"], ["live"]])
def test_unreachable_is_one_line_and_exit_1(endpoint, command) -> None:
    r = cli(*command, "--connect", endpoint)
    assert r.returncode == 1
    assert (
        r.stderr.strip() == f"no collector answered at {endpoint} (is `collector serve` running?)"
    )


def test_serve_rejects_bad_config(tmp_path) -> None:
    cfg = tmp_path / "collector.yaml"
    cfg.write_text("batch_ms: 5\n")
    r = cli("serve", "--config", str(cfg))
    assert r.returncode == 1
    assert r.stderr.strip().startswith("collector.yaml: unknown key 'batch_ms'")
    assert "Traceback" not in r.stderr


def test_record_in_the_foreground(tmp_path, endpoint) -> None:
    proc = subprocess.Popen(
        [
            *COLLECTOR,
            "record",
            "--name",
            "fg",
            "--duration",
            "30",
            "--data-dir",
            str(tmp_path),
            "--listen",
            endpoint,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: reachable(endpoint), 30, "record to come up")
        agent = FakeAgent(endpoint)
        try:
            b = make_batch(0)
            agent.put(b)
            wait_for(lambda: agent.acked(b.sensor) == 0, what="ack")
        finally:
            agent.close()
        proc.send_signal(signal.SIGINT)  # Ctrl-C ends the recording early, cleanly
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    (run,) = list(tmp_path.glob("*-fg"))
    assert (run / "rssi" / "pi-01" / f"{b.sensor}.mbd").read_text().splitlines() == expected_lines(
        [b]
    )
    assert yaml.safe_load((run / "run.yaml").read_text())["readings"] == 5
    assert "5 readings in" in out


def test_sigterm_finalises_an_active_run(tmp_path, endpoint) -> None:
    proc = subprocess.Popen(
        [*COLLECTOR, "serve", "--data-dir", str(tmp_path), "--listen", endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: reachable(endpoint), 30, "serve to come up")
        assert cli("start", "--name", "term", "--connect", endpoint).returncode == 0
        time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    (run,) = list(tmp_path.glob("*-term"))
    doc = yaml.safe_load((run / "run.yaml").read_text())
    assert doc["stopped_by"] == "shutdown"
    assert doc["stop"] is not None


def test_serve_on_a_busy_port_is_one_line(tmp_path) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = cli("serve", "--listen", f"tcp/127.0.0.1:{port}", "--data-dir", str(tmp_path))
    assert r.returncode == 1
    assert r.stderr.count("\n") == 1
    assert r.stderr.startswith(f"cannot open the Zenoh router on tcp/127.0.0.1:{port}: ")
    assert "Address already in use" in r.stderr


def test_export_merges_per_agent_files_into_the_published_layout(tmp_path) -> None:
    run = tmp_path / "run"
    mac, other = "b827eb4521b4", "b827eb4521b5"
    (run / "rssi" / "pi-01").mkdir(parents=True)
    (run / "rssi" / "pi-02").mkdir()
    (run / "rssi" / "pi-01" / f"{mac}.mbd").write_text(
        f"1700000000.000000003,{mac},e78f135624ce,-50\n1700000000.200000000,{mac},e78f135624ce,-52\n"
    )
    (run / "rssi" / "pi-02" / f"{mac}.mbd").write_text(f"1700000000.1,{mac},e78f135624ce,-60\n")
    (run / "rssi" / "pi-02" / f"{other}.mbd").write_text(f"1700000001.0,{other},e78f135624ce,-70\n")
    r = cli("export", str(run), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    assert "4 readings of 2 sensor(s)" in r.stdout
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [f"{mac}.mbd", f"{other}.mbd"]
    assert (tmp_path / "out" / f"{mac}.mbd").read_text().splitlines() == [
        f"1700000000.000000003,{mac},e78f135624ce,-50",
        f"1700000000.1,{mac},e78f135624ce,-60",
        f"1700000000.200000000,{mac},e78f135624ce,-52",
    ]
    bad = cli("export", str(tmp_path / "nowhere"))
    assert bad.returncode == 1
    assert bad.stderr.strip().endswith("not a run directory (no rssi/ folder)")
    assert len(bad.stderr.strip().splitlines()) == 1


WAIT_THEN_SIGINT_FROM_A_THREAD = """
import signal, sys, threading, time
from collector.cli import _wait_for_signal

def kill() -> None:  # the kernel may hand SIGINT to any thread: here, deliberately, not the main one
    time.sleep(0.3)
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)

threading.Thread(target=kill).start()
t0 = time.monotonic()
_wait_for_signal(float(sys.argv[1]) if len(sys.argv) > 1 else None)
print(round(time.monotonic() - t0, 2))
"""


@pytest.mark.parametrize("seconds", [None, 30.0])
def test_serve_wakes_on_a_signal_delivered_to_another_thread(seconds) -> None:
    """`collector serve` parks its main thread until SIGINT/SIGTERM. A signal the kernel delivers
    to another thread (one of Zenoh's, say) only sets a flag the main thread reads when it runs
    Python code; an untimed wait never did, so the collector ignored SIGINT (it hung about once
    in 12 flood-test runs). The wait must end soon after the signal, long before `seconds`."""
    args = [] if seconds is None else [str(seconds)]
    r = subprocess.run(
        [sys.executable, "-c", WAIT_THEN_SIGINT_FROM_A_THREAD, *args],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert r.returncode == 0, r.stderr
    assert float(r.stdout) < 10, r.stdout  # 0.3 s plus at most one short wait; generous bound


def test_serve_with_web_runs_the_console_and_stops_it(tmp_path, endpoint) -> None:
    """`collector serve --web ADDR`: the console comes up beside the collector, shows its fleet
    from the collector's own endpoint, and ends with it on SIGTERM."""
    pytest.importorskip("starlette")
    import urllib.request

    from loopback import free_port

    port = free_port()
    proc = subprocess.Popen(
        [*COLLECTOR, "serve", "--data-dir", str(tmp_path), "--listen", endpoint,
         "--web", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip

    def page() -> str:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
                return r.read().decode()
        except OSError:
            return ""

    try:
        wait_for(lambda: "operator console" in page(), 60, "the console beside the collector")
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/snapshot.js", timeout=5) as r:
            assert b"BGT_INITIAL" in r.read()
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0
    assert page() == ""  # the console went with it


def test_serve_web_needs_a_tcp_endpoint() -> None:
    from collector.web.launch import console_endpoint

    assert console_endpoint(["tcp/0.0.0.0:7447"]) == "tcp/127.0.0.1:7447"
    assert console_endpoint(["tls/10.0.0.1:7448", "tcp/127.0.0.1:7447"]) == "tcp/127.0.0.1:7447"
    with pytest.raises(CollectorError, match="needs a tcp/ endpoint"):
        console_endpoint(["tls/10.0.0.1:7448"])
