"""Pure parts of the collector: decoding, row formatting, dedupe/ack watermarks, rejects, run ids,
run directories and config files."""

from __future__ import annotations

import random
import struct

import pytest
import yaml

from bgt_core import wire
from bgt_core.formats.mbd import format_row, iter_rows
from bgt_core.messages import Ack
from collector.config import CollectorConfig, load_config
from collector.errors import CollectorError, ConfigError
from collector.ingest import RejectCounter, StreamTracker, decode, reject_reason
from collector.readings import as_tuples, beacons, count_beacons, format_rows, from_tuples
from collector.store import RunWriter, clean_name, list_runs, make_run_id
from collector_helpers import make_batch
from full_disk import SwitchableDisk

# -- decode ------------------------------------------------------------------------------------


def test_decode_matches_wire_decoder() -> None:
    b = make_batch(3, n=20)
    got = decode(wire.to_wire(b))
    assert (got.agent_id, got.boot_id, got.sensor, got.seq) == (b.agent_id, b.boot_id, b.sensor, 3)
    assert [(t, m.hex(), r) for t, _mono, m, r in as_tuples(got.rows)] == [
        (r.t_ns, r.beacon, r.rssi) for r in b.readings
    ]


def test_decode_with_extras_takes_the_full_path() -> None:
    ib = wire.IBeacon("f7826da64fa24e988024bc5b71e0893e", 1, 2, -59)
    b = wire.Batch(
        "pi-01",
        "0123456789abcdef",
        "b827eb4521b4",
        0,
        (wire.Reading(1_700_000_000 * 10**9, "e78f135624ce", -50, 5, ibeacon=ib),),
    )
    got = decode(wire.to_wire(b))
    assert as_tuples(got.rows) == [(1_700_000_000 * 10**9, 5, bytes.fromhex("e78f135624ce"), -50)]


def _corrupt(data: bytes, off: int, fmt: str, value) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, off, value)
    return bytes(out)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda d: b"NOPE" + d[4:],
        lambda d: _corrupt(d, 4, "<H", 9),
        lambda d: d[:-1],
        lambda d: d + b"x",
        lambda d: d.replace(b'"seq":0', b'"seq":-1'),
        lambda d: d.replace(b"b827eb4521b4", b"b827eb4521bz"),
    ],
)
def test_decode_raises_exactly_what_wire_raises(mutate) -> None:
    bad = mutate(wire.to_wire(make_batch(0, n=2)))
    with pytest.raises(wire.WireError) as expected:
        wire.from_wire(bad)
    with pytest.raises(wire.WireError) as got:
        decode(bad)
    assert type(got.value) is type(expected.value)
    assert str(got.value) == str(expected.value)


@pytest.mark.parametrize(
    ("mutate", "why"),
    [
        (lambda d: _corrupt(d, len(d) - 1, "<b", 100), "reading 1: RSSI 100 dBm out of range"),
        (
            lambda d: _corrupt(d, len(d) - 23, "<q", 42),
            "reading 1: timestamp 42 ns is not a plausible",
        ),
        (lambda d: _corrupt(d, len(d) - 15, "<q", -1), "reading 1: negative monotonic time"),
    ],
)
def test_decode_skips_an_implausible_reading_and_keeps_the_rest(mutate, why) -> None:
    b = make_batch(0, n=2)
    bad = mutate(wire.to_wire(b))
    with pytest.raises(wire.InvalidField, match=why):
        wire.from_wire(bad)  # the strict decoder still refuses the batch
    got = decode(bad)
    assert (got.seq, got.skipped) == (0, 1)
    assert got.skip_reason.startswith(why)
    r = b.readings[0]
    assert as_tuples(got.rows) == [(r.t_ns, r.mono_ns, bytes.fromhex(r.beacon), r.rssi)]


def test_reject_reasons() -> None:
    assert reject_reason(wire.BadMagic("x")) == "bad_magic"
    assert reject_reason(wire.Truncated("x")) == "truncated"
    assert reject_reason(wire.InvalidField("x")) == "invalid_field"
    assert reject_reason(wire.WireError("x")) == "malformed"


def test_format_rows_is_format_row_in_bulk() -> None:
    b = make_batch(0, n=30)
    rows = decode(wire.to_wire(b)).rows
    assert format_rows(b.sensor, rows) == "".join(
        format_row(r.t_ns, b.sensor, r.beacon, r.rssi) for r in b.readings
    )
    # ...including times with leading zeros in the fraction and whole seconds.
    rows = from_tuples(
        [
            (1_600_000_000_000_000_007, 0, b"\x01" * 6, -5),
            (1_600_000_001_000_000_000, 0, b"\xff" * 6, 0),
        ]
    )
    assert format_rows("aabbccddeeff", rows) == (
        "1600000000.000000007,aabbccddeeff,010101010101,-5\n"
        "1600000001.000000000,aabbccddeeff,ffffffffffff,0\n"
    )


def test_format_rows_of_any_plausible_rows_is_format_row() -> None:
    """Rows of mixed widths (RSSI -128..127, seconds before and after 2001), one width only, one
    beacon, two, many, MACs ending in zero bytes: the array formatting is the row-by-row text,
    byte for byte, and the per-beacon counts are a loop's."""
    rng = random.Random(7)
    for k in range(200):
        n = rng.randrange(1, 60)
        fixed_rssi = rng.randrange(-99, -9) if k % 2 else None
        rows = [
            (
                rng.randrange(
                    wire.T_NS_MIN, wire.T_NS_MIN + 10**17 if k % 5 == 0 else wire.T_NS_MAX
                ),
                rng.randrange(0, 2**62),
                bytes(rng.randrange(256) for _ in range(5)) + bytes(1)
                if k % 3
                else bytes.fromhex(rng.choice(["e78f135624ce", "e78f13562400"])),
                rng.randrange(wire.RSSI_MIN, wire.RSSI_MAX + 1)
                if fixed_rssi is None
                else fixed_rssi,
            )
            for _ in range(n)
        ]
        want = "".join(format_row(t, "aabbccddeeff", m.hex(), r) for t, _mono, m, r in rows)
        arr = from_tuples(rows)
        assert format_rows("aabbccddeeff", arr) == want
        assert format_rows("aabbccddeeff", arr, beacons(arr)) == want
        assert as_tuples(from_tuples(rows)) == rows
        counts: dict[bytes, list[int]] = {}
        for _t, _mono, m, r in rows:
            c = counts.setdefault(m, [0, 0])
            c[0], c[1] = c[0] + 1, c[1] + r
        assert count_beacons(arr) == count_beacons(arr, beacons(arr)) == counts
    with pytest.raises(ValueError, match="outside the wire"):
        format_rows("aabbccddeeff", from_tuples([(10**16, 0, bytes(6), -50)]))


# -- dedupe, gaps, watermarks --------------------------------------------------------------------

S = ("pi-01", "0123456789abcdef", "b827eb4521b4")


def test_tracker_dedupes_and_keeps_contiguous_watermark() -> None:
    t = StreamTracker()
    assert [t.accept(S, q) for q in (0, 1, 1, 0, 3, 4, 3)] == [
        True,
        True,
        False,
        False,
        True,
        True,
        False,
    ]
    assert t.duplicates == 3
    st = t.streams[S]
    assert st.done_upto == 1
    assert st.gaps == 1
    assert t.missing(S) == 1
    assert t.open_gaps() == 1
    assert t.accept(S, 2)  # recovery fills the gap: watermark jumps over what was already there
    assert st.done_upto == 4
    assert t.missing(S) == 0
    assert t.ack_message("pi-01") == Ack(S[1], {})  # nothing durable yet
    assert t.mark_durable() == {"pi-01"}
    assert t.ack_message("pi-01") == Ack(S[1], {"b827eb4521b4": 4})
    assert t.mark_durable() == set()  # unchanged -> nobody to tell


def test_tracker_acks_only_the_latest_boot() -> None:
    t = StreamTracker()
    t.accept(S, 0)
    t.accept(("pi-01", "fedcba9876543210", S[2]), 0)
    t.accept(("pi-01", "fedcba9876543210", S[2]), 1)
    t.mark_durable()
    assert t.ack_message("pi-01") == Ack("fedcba9876543210", {S[2]: 1})
    assert t.ack_message("nobody") is None


def test_tracker_stream_first_seen_late() -> None:
    t = StreamTracker()
    assert t.accept(S, 5)
    assert t.streams[S].first_seq == 5
    assert t.streams[S].done_upto == 5
    t.mark_durable()
    assert t.ack_message("pi-01").streams == {S[2]: 5}
    assert t.accept(S, 4)  # from before the collector joined (e.g. history): written once
    assert not t.accept(S, 4)
    assert not t.accept(S, 5)
    assert t.duplicates == 2


def test_reject_counter_rate_limits_logging(caplog) -> None:
    now = [0.0]
    rc = RejectCounter(lambda: now[0], interval_s=10.0)
    for _ in range(5):
        rc.reject("bad_magic", "k", "bad magic")
    now[0] = 11.0
    rc.reject("bad_magic", "k", "bad magic")
    rc.reject("truncated", "k", "short")
    assert rc.snapshot() == {"bad_magic": 6, "truncated": 1}
    msgs = [r.getMessage() for r in caplog.records if r.name == "collector.ingest"]
    assert len(msgs) == 3
    assert "[4 more like it not logged]" in msgs[1]


# -- run ids and run directories ---------------------------------------------------------------------


def test_run_ids_sort_and_are_safe() -> None:
    t = 1_795_318_500 * 10**9  # 2026-11-22T03:35:00Z
    assert make_run_id(t, "hall walk #2") == "20261122T033500Z-hall-walk-2"
    assert make_run_id(t, None) == "20261122T033500Z-run"
    assert make_run_id(t, "../../etc") == "20261122T033500Z-etc"
    assert clean_name("...") == "run"
    assert make_run_id(t, "b") > make_run_id(t - 10**9, "z")


def test_run_writer_files_and_yaml(tmp_path) -> None:
    w = RunWriter(tmp_path, "20261122T033500Z-x", "x", 1_795_318_500 * 10**9, {"site": "default"})
    b = make_batch(0, n=4)
    rows = decode(wire.to_wire(b)).rows
    w.append("pi-01", b.sensor, format_rows(b.sensor, rows), len(rows))
    w.close()
    w.write_yaml(stop_ns=1_795_318_560 * 10**9, agents={"pi-01": {}}, summary={"gaps": 0})
    got = [
        (r.t_ns, r.sensor, r.beacon, r.rssi)
        for r in iter_rows(w.dir / "rssi" / "pi-01" / f"{b.sensor}.mbd")
    ]
    assert got == [(r.t_ns, b.sensor, r.beacon, r.rssi) for r in b.readings]
    doc = yaml.safe_load((w.dir / "run.yaml").read_text())
    assert doc["start"] == "2026-11-22T03:35:00.000Z"
    assert doc["stop"] == "2026-11-22T03:36:00.000Z"
    assert doc["readings"] == 4
    assert doc["site"] == "default"
    assert doc["version"] == 1
    assert doc["gaps"] == 0
    assert list_runs(tmp_path) == [
        {
            "run_id": "20261122T033500Z-x",
            "name": "x",
            "start": "2026-11-22T03:35:00.000Z",
            "stop": "2026-11-22T03:36:00.000Z",
            "readings": 4,
        }
    ]
    with pytest.raises(CollectorError, match="already exists"):
        RunWriter(tmp_path, "20261122T033500Z-x", "x", 0, {})


# -- config ----------------------------------------------------------------------------------------


def _write(tmp_path, text: str):
    p = tmp_path / "collector.yaml"
    p.write_text(text)
    return p


def test_config_defaults_and_relative_paths(tmp_path) -> None:
    (tmp_path / "acl.json5").write_text("{enabled: false}")
    cfg = load_config(
        _write(tmp_path, "site: lab\ndata_dir: runs\nacl: acl.json5\nfsync_interval_s: 2\n")
    )
    assert cfg.site == "lab"
    assert cfg.data_dir == tmp_path / "runs"
    assert cfg.acl == tmp_path / "acl.json5"
    assert cfg.listen == ("tcp/127.0.0.1:7447",)
    assert cfg.fsync_interval_s == 2.0
    assert load_config(_write(tmp_path, "")).data_dir == tmp_path / "data"


def test_config_overrides() -> None:
    cfg = CollectorConfig().with_overrides(listen=["tcp/127.0.0.1:9000"], site="x")
    assert cfg.listen == ("tcp/127.0.0.1:9000",)
    assert cfg.site == "x"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("colour: red\n", "collector.yaml: unknown key 'colour'"),
        ("fsync_interval_s: soon\n", "collector.yaml: fsync_interval_s must be a number"),
        ("insecure: 1\n", "collector.yaml: insecure must be true or false"),
        (
            "listen: [7447]\n",
            "collector.yaml: listen entry must be a string like tcp/192.168.1.10:7447",
        ),
        (
            "listen: [tcp/192.168.1.10:7447]\n",
            "tcp/192.168.1.10:7447 is unencrypted beyond this machine",
        ),
        ("tls: {root_ca: ca.pem}\n", "tls must be null or a mapping with root_ca, cert and key"),
        ("tls: {root_ca: a, cert: b, key: c}\n", "tls.root_ca file not found"),
        ("acl: missing.json5\n", "acl file not found"),
        ("site: 'a b'\n", "site must be 1-64 characters"),
        ("- 1\n", "expected a mapping"),
        ("site: [unclosed\n", "not valid YAML"),
    ],
)
def test_config_errors_name_the_field(tmp_path, text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")) as e:
        load_config(_write(tmp_path, text))
    assert "\n" not in str(e.value)


def test_config_insecure_allows_lan_listen(tmp_path) -> None:
    cfg = load_config(_write(tmp_path, "listen: [tcp/0.0.0.0:7447]\ninsecure: true\n"))
    assert cfg.listen == ("tcp/0.0.0.0:7447",)


def test_failed_write_keeps_rows_for_the_retry(tmp_path) -> None:
    disk = SwitchableDisk(partial=7)
    w = RunWriter(tmp_path, "r", "r", 1_795_318_500 * 10**9, {}, write=disk)
    b = make_batch(0, n=3)
    rows = decode(wire.to_wire(b)).rows
    w.append("pi-01", b.sensor, format_rows(b.sensor, rows[:1]), 1)
    w.flush()
    path = w.dir / "rssi" / "pi-01" / f"{b.sensor}.mbd"
    good = path.read_bytes()
    w.append("pi-01", b.sensor, format_rows(b.sensor, rows[1:2]), 1)
    disk.full = True
    with pytest.raises(OSError, match="No space"):
        w.flush()
    assert path.read_bytes() == good  # the partial write was rolled back to the last whole line
    assert w.appenders[("pi-01", b.sensor)].size == len(good)
    w.append("pi-01", b.sensor, format_rows(b.sensor, rows[2:]), 1)
    assert w.buffered > 0
    disk.full = False  # space again
    w.close()
    assert path.read_text().splitlines() == [
        format_row(r.t_ns, b.sensor, r.beacon, r.rssi).strip() for r in b.readings
    ]


def test_insecure_flag_allows_lan_listen() -> None:
    with pytest.raises(ConfigError, match="--insecure"):
        CollectorConfig().with_overrides(listen=["tcp/0.0.0.0:7447"])
    cfg = CollectorConfig().with_overrides(listen=["tcp/0.0.0.0:7447"], insecure=True)
    assert cfg.insecure


# -- live view ---------------------------------------------------------------------------------------


def test_sparkline_maps_rssi_to_bar_heights() -> None:
    from collector.live import sparkline

    assert sparkline([-120, -100, -65, -30, 0]) == "▁▁▅██"
    assert sparkline([]) == ""
    assert sparkline([-65, None, float("nan"), "x", 42]) == "▅   █"  # never fails the view


def test_live_table_shows_every_sensor_and_the_run() -> None:
    from rich.console import Console

    from collector.live import render

    status = {
        "run": {"run_id": "20261122T033500Z-x", "readings": 12},
        "agents": {
            "pi-01": {
                "alive": True,
                "sensors": {
                    "b827eb4521b4": {
                        "rate_hz": 9.5,
                        "last_rssi": -61,
                        "last_seen_age_s": 0.25,
                        "readings": 12,
                        "recent_rssi": [-90, -30],
                    }
                },
            },
            "pi-02": {"alive": False, "sensors": {}},
        },
        "rejected_payloads": {"bad_magic": 3},
        "duplicates_dropped": 1,
    }
    console = Console(width=120, record=True)
    console.print(render(status))
    text = console.export_text()
    assert "run 20261122T033500Z-x: 12 readings written" in text
    row = next(line for line in text.splitlines() if "b827eb4521b4" in line)
    assert row.split()[:7] == ["pi-01", "b827eb4521b4", "yes", "9.5", "-61", "0.2s", "12"]
    assert "▂█" in row  # -90 dBm is one step above the -100 floor
    assert "pi-02" in text
    assert "rejected payloads: 3  bad readings skipped: 0  duplicates dropped: 1" in text


def test_live_view_reports_bad_readings_refused_and_shared_streams() -> None:
    from rich.console import Console

    from collector.live import render

    status = {
        "run": None,
        "agents": {},
        "duplicates_dropped": 0,
        "rejected_payloads": {"bad_reading": 2, "truncated": 1},
        "streams": {"total": 1300, "shown": 200, "admitted": 1100, "open_files": 128},
        "refused_streams": {"batches": 100, "streams": 100, "by_agent": {"pi-bad": 100}},
        "shared_sensors": {"b827eb4521b4": ["pi-01", "pi-02"]},
    }
    console = Console(width=160, record=True)
    console.print(render(status))
    text = console.export_text()
    assert "rejected payloads: 1  bad readings skipped: 2" in text
    assert "1100 more streams not shown (1300 in all)" in text
    assert "100 batches of 100 streams refused over the stream limits: pi-bad (100)" in text
    assert "sensor b827eb4521b4 is published by several agents: pi-01, pi-02" in text
