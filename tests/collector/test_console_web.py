"""`collector web`, the operator's console (issue 33): the snapshot the page shows, the HTTP API
against a real collector on loopback, and the page itself in a real headless browser (Debian's
chromium): the fleet appears, a hostile run name is shown as text, a cross-site start is refused."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("starlette")
uvicorn = pytest.importorskip("uvicorn")

from bgt_core.control_messages import CollectorStatus  # noqa: E402
from collector.client import CollectorClient  # noqa: E402
from collector.config import CollectorConfig  # noqa: E402
from collector.service import Collector  # noqa: E402
from collector.web.plan import PlanError, load_plan  # noqa: E402
from collector.web.server import Console, build_app  # noqa: E402
from collector.web.snapshot import ConsoleHistory, build_snapshot  # noqa: E402
from collector_helpers import (  # noqa: E402
    FakeAgent,
    expected_lines,
    make_batch,
    run_yaml_doc,
    with_floor,
)
from loopback import free_port  # noqa: E402
from polling import wait_for  # noqa: E402

A, B, QUIET = "b827eb4521b4", "000000000101", "000000000201"  # QUIET stops after 0.5 s
HOSTILE = '<img src=x onerror="document.title=1">'


def status(age_b: float | None) -> CollectorStatus:
    sensor = {"rate_hz": 9.5, "last_seen_age_s": 0.2, "last_rssi": -61, "readings": 95}
    return CollectorStatus.from_dict(
        {
            "run": None,
            "agents": {
                "pi-1": {
                    "alive": True,
                    "sensors": {
                        A: {**sensor, "beacons": {"e78f135624ce": 9.5}},
                        B: {**sensor, "last_seen_age_s": age_b, "beacons": {}},
                    },
                }
            },
            "shared_sensors": {A: ["pi-1", "pi-2"]},
        }
    )


def test_the_snapshot_flags_silent_sensors_and_keeps_their_quiet_time() -> None:
    history = ConsoleHistory()
    snap = build_snapshot(status(0.5), history, now=1000.0, silent_s=10)
    sensors = {s["mac"]: s for s in snap["agents"][0]["sensors"]}
    assert not sensors[B]["silent"]
    assert snap["beacons"] == ["e78f135624ce"]
    assert snap["points"] == {f"pi-1/{A}": -61, f"pi-1/{B}": -61}
    assert any("published by several agents" in a for a in snap["alerts"])
    snap = build_snapshot(status(25.0), history, now=1020.0, silent_s=10)
    quiet = {s["mac"]: s for s in snap["agents"][0]["sensors"]}[B]
    assert quiet["silent"]
    assert quiet["quiet_since"] == pytest.approx(995.0)
    assert snap["points"][f"pi-1/{B}"] is None
    # the time it went quiet stays as it was first seen, however long it stays quiet
    snap = build_snapshot(status(45.0), history, now=1040.0, silent_s=10)
    assert {s["mac"]: s for s in snap["agents"][0]["sensors"]}[B]["quiet_since"] == 995.0
    assert [p[1] for p in history.points[f"pi-1/{B}"]] == [-61, None, None]


@pytest.fixture
def fleet(tmp_path: Path, endpoint: str) -> Iterator[tuple[Collector, str]]:
    """A collector on loopback, an agent sending two sensors' batches, and the console on HTTP."""
    c = Collector(
        CollectorConfig(data_dir=tmp_path / "data", listen=(endpoint,), fsync_interval_s=0.1),
        drain_timeout_s=2.0,
    ).open()
    agent = FakeAgent(endpoint, agent="pi-1")
    agent.declare_token()
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.is_set():
            for sensor in (A, B, QUIET) if seq < 5 else (A, B):
                agent.put(with_floor(make_batch(seq, agent="pi-1", sensor=sensor), 0))
            seq += 1
            time.sleep(0.1)

    pub = threading.Thread(target=publish, daemon=True)
    pub.start()
    client = CollectorClient(endpoint, "default").__enter__()
    console = Console(client, poll_s=0.3, token="t0k3n", plan=load_plan("tetam"), silent_s=2.0)
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(build_app(console), host="127.0.0.1", port=port, log_level="warning")
    )
    serve = threading.Thread(target=server.run, daemon=True)
    serve.start()
    base = f"http://127.0.0.1:{port}/"
    wait_for(lambda: server.started, 20, "the console to listen")
    wait_for(lambda: console.latest is not None and console.latest.get("agents"), 20, "a snapshot")
    try:
        yield c, base, console
    finally:
        server.should_exit = True
        serve.join(10)
        stop.set()
        pub.join(5)
        client.__exit__(None, None, None)
        agent.close()
        c.close()


def post(url: str, body: dict, headers: dict[str, str]) -> tuple[int, dict]:
    req = urllib.request.Request(
        url, json.dumps(body).encode(), {"Content-Type": "application/json", **headers}
    )
    try:
        with urllib.request.urlopen(req, timeout=20) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_start_and_stop_need_the_pages_token_and_origin(fleet) -> None:
    c, base, _ = fleet
    assert post(base + "api/start", {"name": "x"}, {})[0] == 403  # no token
    code, reply = post(
        base + "api/start", {"name": "x"}, {"X-BGT-Token": "t0k3n", "Origin": "http://evil.example"}
    )
    assert code == 403
    assert "cross-origin" in reply["error"]
    code, reply = post(base + "api/start", {"name": "bad\x1bname"}, {"X-BGT-Token": "t0k3n"})
    assert code == 400
    assert "printable" in reply["error"]
    code, reply = post(
        base + "api/start", {"name": HOSTILE, "notes": "walk 3\nby Ana"}, {"X-BGT-Token": "t0k3n"}
    )
    assert code == 200, reply
    code, stopped = post(base + "api/stop", {}, {"X-BGT-Token": "t0k3n"})
    assert code == 200, stopped
    doc = run_yaml_doc(stopped["run_dir"])
    with urllib.request.urlopen(base + "plan.png", timeout=20) as r:
        assert r.read(8) == b"\x89PNG\r\n\x1a\n"
    assert doc["name"] == HOSTILE
    assert doc["notes"] == "walk 3\nby Ana"


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_the_page_in_a_real_browser(fleet) -> None:
    c, base, console = fleet
    code, _ = post(base + "api/start", {"name": HOSTILE}, {"X-BGT-Token": "t0k3n"})
    assert code == 200

    def quiet_in_snapshot() -> bool:
        snap = console.latest or {}
        rows = [s for a in snap.get("agents", []) for s in a["sensors"] if s["mac"] == QUIET]
        return bool(rows and rows[0]["silent"] and snap.get("run"))

    wait_for(quiet_in_snapshot, 20, "the quiet sensor silent, the run on")
    dom = subprocess.run(
        [
            CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--timeout=6000", "--dump-dom", base,
        ],
        capture_output=True, text=True, timeout=120,
    ).stdout  # fmt: skip
    # a screenshot beside the test's files, for a failure to be looked at
    shot = Path(tempfile.mkdtemp(prefix="console-")) / "console.png"
    subprocess.run(
        [
            CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--window-size=1100,1900", "--timeout=3000", f"--screenshot={shot}", base,
        ],
        capture_output=True, timeout=120,
    )  # fmt: skip
    print(f"console screenshot: {shot}")
    post(base + "api/stop", {}, {"X-BGT-Token": "t0k3n"})
    assert shot.stat().st_size > 20_000
    # the fleet table was filled from the server-sent events: both sensors, with rates
    fleet_table = dom[dom.index('<table id="fleet">') : dom.index('<table id="matrix">')]
    assert A in fleet_table
    assert B in fleet_table
    assert "pi-1" in fleet_table
    # the sensor x beacon matrix gives each pair's rate and last RSSI
    matrix = dom[dom.index('<table id="matrix">') : dom.index('<div id="chart">')]
    assert "/s, -" in matrix
    assert "dBm" in matrix
    # the sensor that went quiet is red, with the time it went quiet
    quiet_row = fleet_table[fleet_table.index(QUIET) - 200 : fleet_table.index(QUIET) + 400]
    assert 'class="silent"' in quiet_row
    assert "quiet since" in quiet_row
    # the hostile run name is text in the page, never markup
    assert "&lt;img src=x onerror=" in dom
    assert "<img src" not in dom
    assert "<title>ble-groundtruth console</title>" in dom  # its onerror never ran
    # the floor plan is shown (its box unhidden) once the snapshot carries it
    assert '<div id="plan-box">' in dom


def test_floor_plans(tmp_path: Path) -> None:
    plan = load_plan("tetam")
    assert (plan.width, plan.height) == (640, 718)
    assert plan.sensors[A][2] == "sensor10"
    assert 0 < plan.sensors[A][0] < plan.width
    assert 0 < plan.sensors[A][1] < plan.height
    with pytest.raises(PlanError, match="neither a folder nor a built-in site"):
        load_plan("atlantis")
    (tmp_path / "x.dev").write_text("")
    with pytest.raises(PlanError, match="needs exactly one .dev, .par and .png"):
        load_plan(str(tmp_path))


def test_live_positions_follow_the_beacon_on_a_radio_map(tmp_path: Path) -> None:
    """--radiomap: the grid-HMM baseline, stepped once a second with the beacon's last RSSI at
    each sensor, puts it where the map says those RSSI values are heard."""
    pytest.importorskip("annotator.core.localize")
    import numpy as np

    from bgt_core.formats.grd import RadioMapGrid, write_grd
    from collector.web.position import LivePositions

    beacon = "e78f135624ce"
    where = {"000000000001": (0.0, 0.0), "000000000002": (9.0, 0.0), "000000000003": (0.0, 9.0)}
    edges = tuple(float(v) for v in range(-100, -29))
    centres = np.arange(-99.5, -30)

    def hist(d: float) -> tuple[float, ...]:
        mean = -45 - 20 * np.log10(max(d, 0.5))
        h = np.exp(-0.5 * ((centres - mean) / 3.0) ** 2)
        return tuple(float(v) for v in h / h.sum())

    for mac, (sx, sy) in where.items():
        cells = {
            (float(x), float(y)): {beacon: hist(np.hypot(x + 0.5 - sx, y + 0.5 - sy))}
            for x in range(10)
            for y in range(10)
        }
        write_grd(
            RadioMapGrid(mac, ((0.0, 0.0), (9.0, 9.0)), 1.0, edges, cells), tmp_path / f"{mac}.grd"
        )
    live = LivePositions(tmp_path)
    truth = (7.5, 1.5)  # near the second sensor

    def observed(t: float) -> CollectorStatus:
        sensors = {
            mac: {
                "rate_hz": 10.0,
                "last_seen_age_s": 0.1,
                "beacon_rssi": {
                    beacon: round(-45 - 20 * np.log10(np.hypot(truth[0] - sx, truth[1] - sy)))
                },
            }
            for mac, (sx, sy) in where.items()
        }
        return CollectorStatus.from_dict({"agents": {"pi-1": {"alive": True, "sensors": sensors}}})

    for t in range(5):
        est = live.update(observed(t))[beacon]
    assert np.hypot(est["x"] - truth[0], est["y"] - truth[1]) < 1.0
    assert est["sensors"] == 3
    assert 0 < est["sigma_m"] < 2.0
    with pytest.raises(ValueError, match="no cell for beacon"):
        LivePositions(tmp_path, ["aaaaaaaaaaaa"])


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_start_and_stop_by_clicking_in_a_real_browser(fleet, endpoint) -> None:
    """The operator's way: type a name and notes, click Start, wait, click Stop, in chromium
    driven over DevTools. The run is recorded under that name, and its folder holds exactly
    what a run holds."""
    from cdp import browser_page

    c, base, console = fleet
    with browser_page(base, free_port()) as page:
        wait_for(
            lambda: (
                page.evaluate("document.readyState") == "complete"
                and page.evaluate("document.querySelectorAll('#fleet tr').length") > 1
            ),
            30,
            "the page and its fleet table",
        )
        # an agent that leaves (its liveliness token gone) turns red in the agents table
        gone = FakeAgent(endpoint, agent="pi-2")
        gone.declare_token()
        gone.put(with_floor(make_batch(0, agent="pi-2", sensor="000000000301"), 0))
        row_class = (
            "Array.from(document.querySelectorAll('#agents tbody tr'))"
            ".filter((r) => r.cells[0].textContent === 'pi-2').map((r) => r.className).join()"
        )
        wait_for(lambda: page.evaluate(row_class) == "", 20, "pi-2 alive in the agents table")
        gone.close()
        wait_for(lambda: page.evaluate(row_class) == "silent", 20, "pi-2 red once it left")
        # the agent's row says when the collector last acknowledged its batches
        wait_for(
            lambda: (
                "s ago" in str(page.evaluate("document.querySelector('#agents tbody').textContent"))
            ),
            20,
            "the agent's last acknowledgement",
        )
        # the RSSI chart (the vendored uPlot) has a line per sensor, and the agent's readings
        # reach it within 2 s: its newest point is never older than that
        wait_for(lambda: page.evaluate("window.bgtChart ? 1 : 0") == 1, 20, "the chart")
        labels = page.evaluate("window.bgtChart.series.slice(1).map((s) => s.label)")
        assert any(str(label).startswith(f"pi-1/{A} ") for label in labels), labels
        ages = []
        for _ in range(5):
            ages.append(page.evaluate("Date.now() / 1000 - window.bgtChart.data[0].at(-1)"))
            time.sleep(0.5)
        assert max(ages) < 2.0, ages
        line = next(i for i, label in enumerate(labels) if str(label).startswith(f"pi-1/{A}")) + 1
        values = page.evaluate(f"window.bgtChart.data[{line}].filter((v) => v !== null)")
        assert isinstance(values, list)
        assert values, "no RSSI of the sensor on its line"
        assert all(-100 < v < -20 for v in values), values
        page.evaluate(
            "document.getElementById('run-name').value = 'clicked-walk';"
            "document.getElementById('run-notes').value = 'started from the page';"
            "document.getElementById('start').click()"
        )
        wait_for(
            lambda: str(page.evaluate("document.getElementById('reply').textContent")).startswith(
                "started"
            ),
            30,
            "the page to say the run started",
        )
        wait_for(lambda: bool((console.latest or {}).get("run")), 20, "the run in the snapshot")
        time.sleep(1.5)  # the agent's batches land in the run
        page.evaluate("document.getElementById('stop').click()")
        wait_for(
            lambda: str(page.evaluate("document.getElementById('reply').textContent")).startswith(
                "stopped"
            ),
            30,
            "the page to say the run stopped",
        )
        reply = str(page.evaluate("document.getElementById('reply').textContent"))
    run_dir = Path(reply.rsplit(" in ", 1)[1])
    doc = run_yaml_doc(run_dir)
    assert doc["name"] == "clicked-walk"
    assert doc["notes"] == "started from the page"
    # the run folder: run.yaml, the collector's state.json and one file per agent and sensor
    # that sent readings during the run (the quiet sensor had stopped before), nothing else
    files = sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file())
    assert files == sorted(
        ["run.yaml", "state.json", f"rssi/pi-1/{A}.mbd", f"rssi/pi-1/{B}.mbd"]
    ), files
    # each file holds exactly the readings the agent sent while the run was on: whole batches,
    # consecutive, each once, in order
    for sensor in (A, B):
        sent = expected_lines([make_batch(k, agent="pi-1", sensor=sensor) for k in range(3000)])
        lines = (run_dir / "rssi" / "pi-1" / f"{sensor}.mbd").read_text().splitlines()
        assert lines, sensor
        first = sent.index(lines[0])
        assert first % 5 == 0  # a batch's first reading
        assert len(lines) % 5 == 0  # whole batches only
        assert lines == sent[first : first + len(lines)], sensor
