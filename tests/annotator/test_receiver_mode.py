"""Both directions (issue 36), end to end through the CLI on one rendered walk: beacon mode and
receiver mode with automatic sync label their readings alike; a phone's CSV log with its own
clock is imported and synchronised by the cover event; `annotator score` takes the receiver
antenna as the truth; fingerprints and radio maps come out per fixed beacon."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from annotator.io.trajectory import read_trajectory
from annotator.render.rssi import RECEIVER_ANTENNA, RECEIVER_MAC
from annotator_cli import invoke
from bgt_core.formats.grd import read_grd
from bgt_core.formats.hst import read_hst
from bgt_core.formats.mbd import iter_rows

pytestmark = pytest.mark.slow

T0 = 1_700_000_000.0
PHONE_OFFSET_S = 3.7  # the phone's clock runs this far ahead of the videos' stated starts
RENDER = ["--duration", "16", "--cover", "1.0:1.5", "--cover", "12.5:1.5", "--rssi-rate", "10"]


def auto_sync(experiment: Path, **changes: str) -> Path:
    """A copy of a rendered experiment.yaml that is not told when the videos started exactly."""
    text = experiment.read_text().replace("  mode: manual", "  mode: auto")
    for old, new in changes.items():
        text = text.replace(old, new)
    out = experiment.with_name(f"auto_{len(changes)}.yaml")
    out.write_text(text)
    return out


def label_errors(results: Path, truth_csv: Path, antenna: np.ndarray, shift_s: float = 0.0):
    """3-D error of every labelled reading against the true path of ``antenna`` (bundle frame)
    at the reading's own time, ``shift_s`` taken off first (a phone clock running ahead)."""
    labels = pd.read_parquet(results / "annotated.parquet")
    truth = read_trajectory(truth_csv).at_point(antenna)
    pos, _, ok = truth.interpolate(labels["t_ns"].to_numpy() / 1e9 - shift_s)
    assert ok.mean() > 0.99
    return np.linalg.norm(labels[["x", "y", "z"]].to_numpy() - pos, axis=1)[ok], labels


@pytest.fixture(scope="module")
def renders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same walk (same seed: the same videos) once with the bundle's beacon heard by the
    site's sensors, once with beacons at the sensors' places heard by a receiver on the bundle."""
    base = tmp_path_factory.mktemp("both_directions")
    out = {"beacon": base / "beacon", "receiver": base / "receiver"}
    invoke("simulate", "--out", str(out["beacon"]), *RENDER, "--jobs", "2")
    invoke("simulate", "--out", str(out["receiver"]), *RENDER, "--jobs", "2", "--receiver")
    return out


def sync_errors_ms(results: Path, shift_s: float = 0.0) -> list[float]:
    report = json.loads((results / "report.json").read_text())
    true = {"front": T0, "back": T0 + 0.41}
    return [
        (cam["video_start"] - shift_s - true[name]) * 1e3
        for name, cam in report["sync"]["cameras"].items()
    ]


def test_receiver_mode_labels_like_beacon_mode(renders: dict[str, Path]) -> None:
    rb, rr = renders["beacon"] / "results", renders["receiver"] / "results"
    invoke("run", str(auto_sync(renders["beacon"] / "experiment.yaml")), "--out", str(rb))
    out = invoke("run", str(auto_sync(renders["receiver"] / "experiment.yaml")), "--out", str(rr))
    assert f"receiver {RECEIVER_MAC} (12 beacons heard)" in out
    err_b, _ = label_errors(rb, renders["beacon"] / "truth.csv", np.zeros(3))
    antenna = np.asarray(RECEIVER_ANTENNA)
    err_r, labels = label_errors(rr, renders["receiver"] / "truth.csv", antenna)
    medians = {"beacon": np.median(err_b) * 100, "receiver": np.median(err_r) * 100}
    p95 = {"beacon": np.percentile(err_b, 95) * 100, "receiver": np.percentile(err_r, 95) * 100}
    print(f"label error median {medians} cm, p95 {p95} cm")  # both, as the issue asks
    assert medians["receiver"] < 1.0
    assert p95["receiver"] < 3.0
    assert medians["receiver"] <= medians["beacon"] + 0.3
    assert max(abs(e) for e in sync_errors_ms(rr)) < 20.0
    # labelled at the receiver's antenna, not at the bundle's origin (11 cm away)
    err_origin, _ = label_errors(rr, renders["receiver"] / "truth.csv", np.zeros(3))
    assert np.median(err_origin) > 0.08
    # one file per beacon heard, the merged file, and the same quality columns
    names = sorted(p.name for p in (rr / "annotated").glob("*.mbd"))
    beacons = sorted(set(labels["beacon"]))
    assert len(beacons) == 12
    assert names == sorted([*(f"{b}.mbd" for b in beacons), "all_sensors.mbd"])
    for b in beacons[:3]:
        rows = list(iter_rows(rr / "annotated" / f"{b}.mbd"))
        assert {r.beacon for r in rows} == {b}
        assert {r.sensor for r in rows} == {RECEIVER_MAC}
    assert {"pos_sigma", "markers_used", "gap_s"} <= set(labels.columns)
    report = json.loads((rr / "report.json").read_text())
    assert report["mode"] == "receiver"
    assert report["receiver"] == RECEIVER_MAC
    assert report["labelled_point_bundle_m"] == list(RECEIVER_ANTENNA)
    assert len(report["per_beacon"]) == 12

    # `annotator score`: estimates exactly on the receiver's true path score ~0 against the run
    truth = read_trajectory(renders["receiver"] / "truth.csv").at_point(antenna)
    t = np.arange(T0 + 3.0, T0 + 11.0, 0.5)
    pos, _, _ = truth.interpolate(t)
    est = renders["receiver"] / "estimates.csv"
    est.write_text(
        "t,x,y,z\n"
        + "".join(f"{a:.3f},{p[0]},{p[1]},{p[2]}\n" for a, p in zip(t, pos, strict=True))
    )
    invoke("score", str(est), "--truth", str(rr), "--out", str(rr / "score"), "--no-plots")
    score = json.loads((rr / "score" / "score.json").read_text())
    assert score["error_2d_m"]["median"] < 0.01  # the bundle origin would be 5 cm off

    # fingerprints and a radio map of each fixed beacon as the moving receiver heard it
    hst = rr / "receiver.hst"
    invoke(
        "fingerprints",
        "--from-annotated",
        str(rr / "annotated"),
        "--cell",
        "1.0",
        "--out",
        str(hst),
    )
    h = read_hst(hst)
    heard = {b for per_sensor in h.fingerprints.values() for s in per_sensor.values() for b in s}
    assert heard == set(beacons)
    assert {s for per_sensor in h.fingerprints.values() for s in per_sensor} == {RECEIVER_MAC}
    invoke("radiomap", str(hst), "--cell", "1.0", "--out", str(rr / "radiomap"))
    grd = read_grd(rr / "radiomap" / f"receiver_{RECEIVER_MAC}_1.0.grd")
    assert {b for cell in grd.cells.values() for b in cell} == set(beacons)
    assert (rr / "radiomap" / f"receiver_{RECEIVER_MAC}_1.0_beacons.png").stat().st_size > 10_000


def test_a_phone_log_with_its_own_clock(renders: dict[str, Path]) -> None:
    """The receiver's readings as a phone app would log them: its clock 3.7 s ahead, times half
    in Unix seconds and half in ISO 8601 with a +01:00 offset, colon MACs, extra columns."""
    render = renders["receiver"]
    source = render / "run" / "rssi" / "simulated" / f"{RECEIVER_MAC}.mbd"
    zone = dt.timezone(dt.timedelta(hours=1))
    lines = ["timestamp,device name,mac,rssi,tx power"]
    for i, row in enumerate(iter_rows(source)):
        t_ns = row.t_ns + round(PHONE_OFFSET_S * 1e9)
        when = (
            f"{t_ns // 10**9}.{t_ns % 10**9:09d}"
            if i % 2
            else dt.datetime.fromtimestamp(t_ns // 1000 / 1e6, zone).isoformat()
        )
        mac = ":".join(row.beacon[k : k + 2] for k in range(0, 12, 2)).upper()
        lines.append(f'{when},"tag, {i}",{mac},{row.rssi},-59')
    log = render / "phone.csv"
    log.write_text("\n".join(lines) + "\n")
    invoke(
        "import-log", str(log), "--columns", "timestamp,mac,rssi", "--sensor",
        "02:00:00:00:00:01", "--out", str(render / "phone_rssi"),
    )  # fmt: skip
    exp = auto_sync(
        render / "experiment.yaml",
        **{
            "rssi: run": "rssi: phone_rssi",
            f"receiver: '{RECEIVER_MAC}'": "receiver: '020000000001'",
        },
    )
    results = render / "phone_results"
    invoke("run", str(exp), "--out", str(results))
    errors = sync_errors_ms(results, PHONE_OFFSET_S)
    print(f"phone log: video starts found {errors} ms off after the {PHONE_OFFSET_S} s offset")
    assert max(abs(e) for e in errors) < 20.0
    err, labels = label_errors(
        results, render / "truth.csv", np.asarray(RECEIVER_ANTENNA), PHONE_OFFSET_S
    )
    assert set(labels["sensor"]) == {"020000000001"}
    assert np.median(err) < 0.01
