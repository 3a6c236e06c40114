"""The playbook against booted Debian hosts (deploy/testbed/bgt_testbed.py): one collector and two
agents under systemd-nspawn on a private network, `ansible-playbook site.yml` over SSH, then
what a lab would check on the fleet, a capture across an agent reboot, re-runs, wrong
inventories and an upgrade.

The hosts boot once for the whole module (the fixture); the tests run in file order and share
them. Where the machine cannot boot containers the module is skipped with one line naming what
is missing. Figures (build, playbook wall times, capture counts, security scores) are printed
with -s.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

import polling
from bgt_core import wire
from bgt_core.formats.mbd import format_row
from testbed_loader import load_testbed

REPO = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

tb = load_testbed()
COLLECTOR = tb.host("bgt-collector")
AGENTS = [h for h in tb.HOSTS if h.role == "agent"]
STATE_DIR = Path("/var/lib/ble-groundtruth")


@dataclass
class Fleet:
    state: Path
    inventory: Path
    first: tb.PlaybookResult
    figures: dict[str, float] = field(default_factory=dict)
    run_dir: Path | None = None  # the capture's run, on the collector (host path)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    why = tb.missing_capability()
    if why:
        pytest.skip(f"cannot boot containers here: {why}")
    state = tmp_path_factory.mktemp("testbed")
    tb.use_state(state)
    try:
        t0 = time.monotonic()
        _path, took, built = tb.build_rootfs()
        figures = {"rootfs_s": took if built else time.monotonic() - t0, "rootfs_cold": built}
        figures.update(tb.up())
        first = tb.deploy([])
        figures["playbook_first_s"] = first.seconds
        yield Fleet(state, state / "inventory.yml", first, figures)
    finally:
        tb.down()
        # The hosts' upper directories hold three venvs; do not keep them in pytest's tmp.
        shutil.rmtree(state / "hosts", ignore_errors=True)


def on(h, *argv: str, check: bool = True, timeout: float = 120) -> str:
    return tb.ssh(h, list(argv), check=check, timeout=timeout).stdout


def show(h, unit: str, *props: str) -> dict[str, str]:
    out = on(h, "systemctl", "show", unit, "-p", ",".join(props))
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def unit_of(h) -> str:
    return "collector.service" if h.role == "collector" else "sensor-agent.service"


def cli(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """The collector CLI from the control address, with the site PKI the playbook made."""
    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": str(REPO)}
    cmd = tb.in_control_ns([sys.executable, "-c", "from collector.cli import main; main()", *argv])
    return subprocess.run(
        cmd, text=True, capture_output=True, timeout=timeout, check=False, env=env
    )


def operator_args(fleet: Fleet) -> list[str]:
    pki = fleet.state / "pki"
    return [
        "--connect", f"tls/{COLLECTOR.address}:7447", "--site", "testbed",
        "--root-ca", str(pki / "ca.crt"), "--cert", str(pki / "operator.crt"),
        "--key", str(pki / "operator.key"),
    ]  # fmt: skip


def wait_for(pred, timeout: float, what: str, step: float = 1.0):
    """tests/support/polling.wait_for, one poll a second by default (each poll may be an ssh)."""
    return polling.wait_for(pred, timeout, what, step=step)


def start_unit(h, unit: str, timeout: float = 90) -> None:
    """Start a unit and wait until it is active (a failed first start is retried by systemd
    after RestartSec); on timeout the error carries the unit's journal."""
    on(h, "systemctl", "start", "--no-block", unit)
    try:
        wait_for(
            lambda: show(h, unit, "ActiveState")["ActiveState"] == "active",
            timeout,
            f"{unit} on {h.name} to be active",
        )
    except AssertionError as e:
        log = on(h, "journalctl", "-u", unit, "-n", "40", "--no-pager", check=False)
        raise AssertionError(f"{e}\n{log}") from None


def failed_run(r) -> str:
    """A failed playbook run's message: the output's tail and, per host, its unit's journal
    (the test bed, and with it the journals, is gone once the session ends)."""
    parts = [r.output[-4000:]]
    for h in tb.HOSTS:
        unit = unit_of(h)
        log = on(h, "journalctl", "-u", unit, "-n", "40", "--no-pager", check=False)
        parts.append(f"--- {unit} on {h.name} ---\n{log}")
    return "\n".join(parts)


def test_first_playbook_run_succeeds(fleet: Fleet) -> None:
    r = fleet.first
    assert r.returncode == 0, failed_run(r)
    for h in tb.HOSTS:
        assert r.recap[h.name]["failed"] == 0, r.output[-4000:]
        assert r.recap[h.name]["unreachable"] == 0, r.output[-4000:]
        assert r.recap[h.name]["changed"] > 0, "a first run must install something"
    print(f"\nFIGURES boot: {fleet.figures}")


def test_units_are_active(fleet: Fleet) -> None:
    for h in tb.HOSTS:
        st = show(h, unit_of(h), "ActiveState", "SubState", "Type", "NRestarts")
        assert st["ActiveState"] == "active", (h.name, st, on(h, "journalctl", "-n", "30"))
        assert st["Type"] == "notify"
        assert st["NRestarts"] == "0", (h.name, st)


def test_watchdog_is_fed(fleet: Fleet) -> None:
    """WatchdogSec=30 and the services ping every 15 s: systemd's watchdog timestamp moves."""
    first = {h.name: show(h, unit_of(h), "WatchdogTimestampMonotonic", "WatchdogUSec")
             for h in tb.HOSTS}  # fmt: skip
    for h in tb.HOSTS:
        assert first[h.name]["WatchdogUSec"] == "30s"

        def moved(h=h) -> bool:
            now = show(h, unit_of(h), "WatchdogTimestampMonotonic")["WatchdogTimestampMonotonic"]
            return int(now) > int(first[h.name]["WatchdogTimestampMonotonic"])

        wait_for(moved, 45, f"a watchdog ping from {unit_of(h)} on {h.name}")


def test_installed_units_score_at_most_2(fleet: Fleet) -> None:
    scores = {}
    for h in tb.HOSTS:
        out = on(h, "systemd-analyze", "security", "--no-pager", unit_of(h))
        m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", out)
        assert m, out[-1500:]
        scores[f"{h.name}:{unit_of(h)}"] = float(m[1])
    print(f"\nFIGURES security: {scores}")
    assert all(s <= 2.0 for s in scores.values()), scores


def test_chrony_on_agents_follows_the_collector(fleet: Fleet) -> None:
    for h in AGENTS:

        def synced(h=h) -> bool:
            out = on(h, "chronyc", "-n", "sources")
            return any(
                line.startswith("^*") and COLLECTOR.address in line for line in out.splitlines()
            )

        wait_for(synced, 120, f"{h.name}'s chrony selecting {COLLECTOR.address}", step=2)
        tracking = on(h, "chronyc", "-n", "tracking")
        assert f"({COLLECTOR.address})" in tracking.splitlines()[0], tracking
        # The agents have no other source: the default pools are gone.
        assert len([x for x in on(h, "chronyc", "-n", "sources").splitlines() if x[:1] == "^"]) == 1


def test_fleet_status_lists_both_agents_with_clock_offsets(fleet: Fleet) -> None:
    # Each agent's chrony reference must be the collector (by name or address); agents re-read
    # chrony once a minute, so one started before chrony synced shows it within ~60 s.
    ref = "".join(f"{int(x):02X}" for x in COLLECTOR.address.split("."))
    ref_re = rf"{ref} \((bgt-collector|{re.escape(COLLECTOR.address)})\)"
    last = {"out": ""}

    def listed() -> bool:
        res = cli("fleet", "status", "--inventory", str(fleet.inventory))
        last["out"] = res.stdout + res.stderr
        rows = [line for line in res.stdout.splitlines() if re.search(r"\bagent[12]\b", line)]
        return (
            res.returncode == 0
            and len(rows) == 2
            and all(re.search(r"\byes\b.*[+-]\d+\.\d+ ms", r) for r in rows)
            and all(re.search(ref_re, r) for r in rows)
        )

    try:
        wait_for(listed, 100, "both agents alive, with offsets and chrony on the collector", 5)
    except AssertionError as e:
        raise AssertionError(f"{e}\n{last['out']}") from None


# --- capture through the deployed fleet --------------------------------------------------------


def spool_records(spool: Path) -> list[tuple[str, bytes]]:
    """(stream, payload) of every whole record in a spool directory, by the documented format."""
    import struct
    import zlib

    head, rec, body = struct.Struct("<8sHHQ"), struct.Struct("<4sII"), struct.Struct("<qqB")
    out = []
    for seg in sorted(spool.glob("*.seg")):
        try:
            data = seg.read_bytes()
        except FileNotFoundError:
            continue  # deleted once acknowledged; an earlier poll read it
        off = head.size
        while data[:8] == b"BGTSPOOL" and off + rec.size <= len(data):
            magic, n, crc = rec.unpack_from(data, off)
            end = off + rec.size + n
            b = data[off + rec.size : end]
            if magic != b"BGTR" or end > len(data) or n < body.size:
                break
            if zlib.crc32(b, zlib.crc32(struct.pack("<I", n))) != crc:
                break
            slen = body.unpack_from(b, 0)[2]
            out.append((b[body.size : body.size + slen].decode(), b[body.size + slen :]))
            off = end
    return out


class SpoolWatch:
    """Polls each agent's spool (through the host's view of its file system) and keeps every
    record ever seen, so segments deleted after acknowledgement still count."""

    def __init__(self) -> None:
        self.seen: dict[str, dict[str, bytes]] = {h.agent_id: {} for h in AGENTS}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def poll(self) -> None:
        for h in AGENTS:
            for stream, payload in spool_records(tb.merged(h) / "var/lib/ble-groundtruth/spool"):
                self.seen[h.agent_id].setdefault(f"{stream}#{hash(payload)}", payload)

    def _loop(self) -> None:
        while not self._stop.wait(0.3):
            self.poll()

    def __enter__(self) -> SpoolWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.poll()

    def rows(self, agent_id: str) -> tuple[set[str], set[str]]:
        """The readings the agent spooled (as run-file rows) and its boot ids."""
        rows, boots = set(), set()
        for payload in self.seen[agent_id].values():
            b = wire.from_wire(payload)
            boots.add(b.boot_id)
            for r in b.readings:
                rows.add(format_row(r.t_ns, b.sensor, r.beacon, r.rssi).rstrip("\n"))
        return rows, boots


def run_rows(run_dir: Path) -> Counter[str]:
    """Every row of the run's RSSI files, wherever under rssi/ they are (rssi/<mac>.mbd or
    rssi/<agent>/<mac>.mbd)."""
    rows: Counter[str] = Counter()
    for f in sorted((run_dir / "rssi").rglob("*.mbd")):
        for line in f.read_text(encoding="utf-8").splitlines():
            if line.strip():
                rows[line.strip()] += 1
    return rows


def test_capture_across_an_agent_reboot_loses_and_repeats_nothing(fleet: Fleet) -> None:
    try:
        _capture_across_a_reboot(fleet)
    finally:  # back to normal for the next tests, pass or fail
        for h in AGENTS:
            start_unit(h, "sensor-agent.service")


def _capture_across_a_reboot(fleet: Fleet) -> None:
    rebooted = AGENTS[0]
    for h in AGENTS:  # a fresh spool: everything in it belongs to this capture
        on(h, "systemctl", "stop", "sensor-agent.service", timeout=90)
        on(h, "sh", "-c", "rm -rf /var/lib/ble-groundtruth/spool/*")
    res = cli("start", "--name", "testbed", *operator_args(fleet))
    assert res.returncode == 0, res.stdout + res.stderr
    run_id = res.stdout.strip().splitlines()[-1]
    t0 = time.monotonic()
    with SpoolWatch() as watch:
        for h in AGENTS:
            start_unit(h, "sensor-agent.service")
        time.sleep(max(0.0, 25 - (time.monotonic() - t0)))
        with contextlib.suppress(subprocess.TimeoutExpired):  # sshd may go before we return
            tb.ssh(rebooted, ["systemctl", "reboot", "--no-block"], check=False, timeout=30)
        wait_for(
            lambda: tb.ssh(rebooted, ["true"], check=False, timeout=30).returncode != 0,
            90,
            f"{rebooted.name} to go down",
            step=0.5,
        )
        tb.wait_ssh(rebooted, timeout=180)
        wait_for(
            lambda: (
                show(rebooted, "sensor-agent.service", "ActiveState")["ActiveState"] == "active"
            ),
            60,
            "the rebooted agent's service",
        )
        time.sleep(max(5.0, 60 - (time.monotonic() - t0)))
        for h in AGENTS:  # SIGINT: stop scanning, flush, wait for the collector's acks
            on(h, "systemctl", "stop", "sensor-agent.service", timeout=90)
    res = cli("stop", *operator_args(fleet))
    assert res.returncode == 0, res.stdout + res.stderr
    run_dir = tb.merged(COLLECTOR) / str(res.stdout.strip().splitlines()[-1]).lstrip("/")
    assert run_id in str(run_dir)
    fleet.run_dir = run_dir
    in_run = run_rows(run_dir)
    counts = {}
    for h in AGENTS:
        spooled, boots = watch.rows(h.agent_id)
        lost = len(spooled - in_run.keys())
        dup = sum(in_run[r] - 1 for r in spooled if in_run[r] > 1)
        counts[h.agent_id] = {"spooled": len(spooled), "lost": lost, "duplicated": dup,
                              "boots": len(boots)}  # fmt: skip
    print(f"\nFIGURES capture: {counts}, run rows {sum(in_run.values())}")
    for h in AGENTS:  # a start that systemd had to retry: show why, for the record
        if show(h, "sensor-agent.service", "NRestarts")["NRestarts"] != "0":
            print(on(h, "journalctl", "-u", "sensor-agent", "-n", "60", "--no-pager", check=False))
    assert counts[rebooted.agent_id]["boots"] >= 2, "the agent did not restart in the capture"
    for agent_id, c in counts.items():
        assert c["spooled"] > 300, (agent_id, c)
        assert c["lost"] == 0, (agent_id, c)
        assert c["duplicated"] == 0, (agent_id, c)
    # Nothing in the run that no spool held. The watch polls every 0.3 s, and the batch that an
    # agent flushes as it stops is spooled, sent, acknowledged and deleted faster than that; so
    # rows the watch never saw must be that tail: after the agent's last row the watch did see,
    # and no more than a few seconds of readings.
    for h in AGENTS:
        spooled = watch.rows(h.agent_id)[0]
        sensors = {row.split(",")[1] for row in spooled}
        unseen = {r for r in in_run if r.split(",")[1] in sensors} - spooled
        last_seen = max(float(row.split(",")[0]) for row in spooled)
        early = sorted(r for r in unseen if float(r.split(",")[0]) <= last_seen)
        assert not early, (h.agent_id, early[:5])
        assert len(unseen) <= 3 * len(spooled) / 60, (h.agent_id, sorted(unseen)[:5])
    all_sensors = {row.split(",")[1] for h in AGENTS for row in watch.rows(h.agent_id)[0]}
    assert {r.split(",")[1] for r in in_run} <= all_sensors


def test_second_run_changes_nothing(fleet: Fleet) -> None:
    r = tb.deploy([])
    fleet.figures["playbook_second_s"] = r.seconds
    print(f"\nFIGURES playbook first {fleet.first.seconds:.0f} s, second {r.seconds:.0f} s")
    assert r.returncode == 0, failed_run(r)
    for name, c in r.recap.items():
        assert c["failed"] == 0, (name, c, r.output[-4000:])
        assert c["changed"] == 0, (name, c, changed_tasks(r.output, name))


def changed_tasks(output: str, host: str) -> list[str]:
    """The playbook tasks that reported a change on ``host`` (for a failure message)."""
    task, out = "", []
    for line in output.splitlines():
        if line.startswith("TASK ["):
            task = line.split("]")[0].removeprefix("TASK [")
        elif line.startswith("changed: [") and f"[{host}]" in line:
            out.append(f"{task}: {line}")
    return out


# --- wrong inventories ---------------------------------------------------------------------


def _inventory_copy(fleet: Fleet, tmp_path: Path, extra: str = "") -> Path:
    shutil.copytree(fleet.state / "pki", tmp_path / "pki")
    shutil.copytree(fleet.state / "build", tmp_path / "build")
    text = fleet.inventory.read_text(encoding="utf-8")
    inv = tmp_path / "inventory.yml"
    inv.write_text(text.replace("    bgt_pki_dir: pki\n", "    bgt_pki_dir: pki\n" + extra))
    return inv


def test_unknown_host_stops_the_playbook_naming_it(fleet: Fleet, tmp_path: Path) -> None:
    inv = _inventory_copy(fleet, tmp_path)
    text = inv.read_text(encoding="utf-8")
    ghost = (
        "        bgt-ghost:\n          ansible_host: ghost.invalid\n"
        "          agent_id: ghost\n          adapters: []\n"
    )
    inv.write_text(text.replace("      hosts:\n        bgt-agent1:", "      hosts:\n" + ghost
                                + "        bgt-agent1:"))  # fmt: skip
    r = tb.deploy([], inventory=inv)
    assert r.returncode != 0
    failed = [x for x in r.output.splitlines() if "bgt-ghost" in x and "UNREACHABLE" in x]
    assert failed, r.output[-3000:]
    assert "ghost.invalid" in failed[0], r.output[-3000:]
    # The probe stops everything before any host is touched.
    touched = {h: c for h, c in r.recap.items() if c.get("changed")}
    assert not touched, (touched, r.output[-3000:])
    assert "PLAY [Collector]" not in r.output, r.output[-3000:]


def test_missing_certificate_stops_the_playbook_naming_it(fleet: Fleet, tmp_path: Path) -> None:
    inv = _inventory_copy(fleet, tmp_path, extra="    bgt_issue_certs: false\n")
    (tmp_path / "pki" / "agent2.crt").unlink()
    r = tb.deploy([], inventory=inv)
    assert r.returncode != 0
    assert re.search(r"agent2\.crt \(for bgt-agent2\) is missing", r.output), r.output[-3000:]
    touched = {h: c for h, c in r.recap.items() if c.get("changed") and h != "localhost"}
    assert not touched, (touched, r.output[-3000:])
    assert "PLAY [Collector]" not in r.output, r.output[-3000:]


# --- upgrade -------------------------------------------------------------------------------


def test_upgrade_with_a_newer_wheel_keeps_spool_and_runs(fleet: Fleet, tmp_path: Path) -> None:
    assert fleet.run_dir is not None, "needs the capture test's run"
    src = tmp_path / "src-next"
    skip = shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "pki")
    for part in ("sensor_agent", "collector", "annotator", "bgt_core", "deploy", "systemd"):
        shutil.copytree(REPO / part, src / part, ignore=skip)
    shutil.copy(REPO / "README.md", src / "README.md")
    py = (REPO / "pyproject.toml").read_text(encoding="utf-8")
    old = re.search(r'^version = "([^"]+)"', py, re.M)[1]
    new = old + ".post1"
    (src / "pyproject.toml").write_text(py.replace(f'version = "{old}"', f'version = "{new}"'))
    runs_before = {p: p.read_bytes() for p in fleet.run_dir.rglob("*") if p.is_file()}
    spool = "/var/lib/ble-groundtruth/spool"
    before = {h.name: show(h, unit_of(h), "InvocationID")["InvocationID"] for h in tb.HOSTS}
    r = tb.deploy(["-e", f"bgt_src_dir={src}"])
    assert r.returncode == 0, failed_run(r)
    for h in tb.HOSTS:
        shown = on(
            h, "/opt/ble-groundtruth/venv/bin/python", "-m", "pip", "show", "ble-groundtruth"
        )
        assert f"Version: {new}" in shown, (h.name, shown)
        st = show(h, unit_of(h), "InvocationID", "ActiveState")
        assert st["ActiveState"] == "active", h.name
        assert st["InvocationID"] != before[h.name], f"{unit_of(h)} on {h.name} not restarted"
        wheels = on(h, "ls", "/opt/ble-groundtruth/wheelhouse").split()
        assert [w for w in wheels if w.startswith("ble_groundtruth-")] == [
            f"ble_groundtruth-{new}-py3-none-any.whl"
        ]
    for h in AGENTS:
        assert tb.ssh(h, ["test", "-f", f"{spool}/acks.json"], check=False).returncode == 0
    after = {p: p.read_bytes() for p in fleet.run_dir.rglob("*") if p.is_file()}
    assert after == runs_before, "the upgrade changed the recorded run"
