"""annotator.core.scoring and `annotator score`: errors at each estimate's own time against known truth."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from annotator.core.scoring import Truth, interpolate_truth, score, summarize
from annotator.core.trajectory import Trajectory
from annotator.io.scoring import read_estimates, read_truth, write_estimates
from annotator.io.trajectory import write_trajectory

DATA = Path(__file__).resolve().parents[2] / "data" / "dataset"
TRACK = DATA / "trk" / "straight_01_all_sensors.mbd"


def annotator_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "annotator"
    return (
        [str(exe)]
        if exe.is_file()
        else [sys.executable, "-c", "from annotator.cli import main; main()"]
    )


def walk(t: np.ndarray) -> np.ndarray:
    """A beacon walking +x at 1 m/s and +y at 0.5 m/s, at 1.5 m height."""
    return np.column_stack([1.0 * t, 0.5 * t, np.full_like(t, 1.5)])


def test_summary_figures_on_known_errors() -> None:
    e = np.arange(1.0, 101.0)  # 1..100 m
    s = summarize(np.append(e, np.nan))
    assert s.n == 100
    assert s.mean == pytest.approx(50.5)
    assert s.median == s.ce50 == pytest.approx(50.5)
    assert s.ce75 == pytest.approx(75.25)
    assert s.ce95 == pytest.approx(95.05)
    assert s.max == 100.0
    assert s.rmse == pytest.approx(np.sqrt(np.mean(e**2)))
    assert summarize(np.array([np.nan])).as_dict()["median"] is None


def test_truth_is_interpolated_at_each_estimate_time_never_extrapolated() -> None:
    tt = np.arange(0.0, 10.01, 0.5)
    truth = Truth.from_samples(tt, walk(tt))
    q = np.array([-0.1, 0.0, 0.25, 3.3, 10.0, 10.2])
    pos, _ = interpolate_truth(truth, q)
    np.testing.assert_allclose(pos[1:5], walk(q[1:5]), atol=1e-12)
    assert np.isnan(pos[[0, 5]]).all()


def test_truth_gaps_are_not_bridged() -> None:
    tt = np.array([0.0, 0.5, 1.0, 4.0, 4.5, 5.0, 5.5, 6.0])
    p = walk(tt)
    p[6] = np.nan  # a missing pose at 5.5 s
    truth = Truth(tt, p)
    pos, _ = interpolate_truth(truth, np.array([0.75, 2.0, 4.25, 5.25, 5.75, 6.0]), max_gap_s=1.0)
    ok = np.isfinite(pos).all(axis=1)
    # 2.0 lies in a 3 s pause; 5.25 and 5.75 next to the NaN row; 6.0 is a valid sample itself
    assert ok.tolist() == [True, False, True, False, False, True]


def test_offset_estimates_give_exact_2d_and_3d_errors() -> None:
    tt = np.arange(0.0, 20.0, 0.1)
    truth = Truth.from_samples(tt, walk(tt))
    t = np.arange(1.0, 19.0, 0.37)
    est = walk(t) + [0.3, 0.4, 1.2]
    s = score(t, est, truth)
    np.testing.assert_allclose(s.error_2d, 0.5, atol=1e-9)
    np.testing.assert_allclose(s.error_3d, 1.3, atol=1e-9)
    rep = s.report()
    assert rep["error_2d_m"]["ce95"] == pytest.approx(0.5)
    assert rep["error_3d_m"]["rmse"] == pytest.approx(1.3)
    assert rep["coverage"]["scored"] == len(t)


def test_coverage_counts_estimates_outside_the_truth() -> None:
    tt = np.arange(0.0, 10.0, 0.1)
    truth = Truth.from_samples(tt, walk(tt))
    t = np.arange(-5.0, 5.0, 0.5)  # the first half before the truth starts
    s = score(t, walk(t), truth)
    c = s.coverage
    assert c["estimates"] == 20
    assert c["scored"] == 10
    assert c["not_scored"] == 10
    # truth samples 0.0 .. 5.5 s have an estimate within 1 s (the last at 4.5 s): 56 of 100
    assert c["truth_covered_fraction"] == pytest.approx(0.56)


def test_latency_is_the_shift_that_removes_a_lag() -> None:
    tt = np.arange(0.0, 60.0, 0.05)
    truth = Truth.from_samples(
        tt, np.column_stack([3 * np.sin(tt / 3), 2 * np.cos(tt / 4), tt * 0])
    )
    t = np.arange(5.0, 55.0, 0.2)
    lagged = np.column_stack([3 * np.sin((t - 0.4) / 3), 2 * np.cos((t - 0.4) / 4), t * 0])
    s = score(t, lagged, truth, latency_max_s=2.0, latency_step_s=0.05)
    assert s.latency.shift_s == pytest.approx(0.4, abs=1e-9)
    assert s.latency.ce50_at_shift < 1e-9 < s.latency.ce50_at_zero


def test_truth_sigma_comes_from_an_annotated_run(tmp_path: Path) -> None:
    tt = np.arange(100.0, 110.0, 0.1)
    sigma = np.full(len(tt), 0.012)
    rot = np.tile(np.eye(3), (len(tt), 1, 1))
    write_trajectory(tmp_path / "trajectory.csv", Trajectory(tt, walk(tt), rot, {"sigma_m": sigma}))
    truth = read_truth(tmp_path)
    t = np.arange(101.0, 109.0, 0.5)
    rep = score(t, walk(t) + [0.1, 0, 0], truth).report()
    assert rep["truth_sigma_m"]["n"] == len(t)
    assert rep["truth_sigma_m"]["median"] == pytest.approx(0.012)
    assert rep["error_2d_m"]["median"] == pytest.approx(0.1, abs=1e-6)


def test_published_track_truth_has_one_sample_per_timestamp() -> None:
    truth = read_truth(TRACK)
    assert np.all(np.diff(truth.t) > 0)
    assert truth.sigma is None
    raw = np.loadtxt(TRACK, delimiter=",", usecols=(0, 4, 5, 6))
    assert len(truth.t) == len(np.unique(raw[:, 0]))
    # the truth at a row's own timestamp is that row's position
    pos, _ = interpolate_truth(truth, raw[:5, 0])
    np.testing.assert_allclose(pos, raw[:5, 1:], atol=1e-9)


def test_score_cli_writes_json_blocks_and_plots(tmp_path: Path) -> None:
    truth = read_truth(TRACK)
    t = truth.t[::7]
    pos, _ = interpolate_truth(truth, t)
    write_estimates(tmp_path / "est.csv", t, pos + [0.6, 0.8, 0.0])
    est = read_estimates(tmp_path / "est.csv")
    assert est.has_z
    assert len(est.t) == len(t)
    res = subprocess.run(
        [
            *annotator_cmd(),
            "score",
            str(tmp_path / "est.csv"),
            "--truth",
            str(TRACK),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert res.returncode == 0, res.stderr
    body = json.loads((tmp_path / "out" / "score.json").read_text(encoding="utf-8"))
    for block in ("error_2d_m", "error_3d_m"):
        assert set(body[block]) == {"mean", "median", "rmse", "ce50", "ce75", "ce95", "max", "n"}
    assert body["error_2d_m"]["ce75"] == pytest.approx(1.0, abs=2e-4)  # 4-decimal CSV rounding
    assert body["error_3d_m"]["n"] == len(t)
    for png in ("error_cdf.png", "error_over_time.png", "estimates_on_floor_plan.png"):
        assert (tmp_path / "out" / png).stat().st_size > 10_000


def test_score_cli_bad_estimates_is_one_line_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("time,x,y\n1,2,3\n", encoding="utf-8")
    res = subprocess.run(
        [
            *annotator_cmd(),
            "score",
            str(bad),
            "--truth",
            str(TRACK),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert res.returncode == 1
    assert "header lacks column(s) t" in res.stderr
    assert "Traceback" not in res.stderr
    assert not (tmp_path / "out").exists()
    bad.write_text("t,x,y\n1,2,3\n2,oops,3\n", encoding="utf-8")
    res = subprocess.run(
        [
            *annotator_cmd(),
            "score",
            str(bad),
            "--truth",
            str(TRACK),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert res.returncode == 1
    assert f"{bad}:3:" in res.stderr
    # estimates from another day: nothing to score, said in one line
    bad.write_text("t,x,y\n1,2,3\n2,2,3\n", encoding="utf-8")
    res = subprocess.run(
        [
            *annotator_cmd(),
            "score",
            str(bad),
            "--truth",
            str(TRACK),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert res.returncode == 1
    assert "no estimate falls inside" in res.stderr


def test_score_cli_latency_is_opt_in_and_finds_a_lag(tmp_path: Path) -> None:
    truth = read_truth(TRACK)
    t = truth.t[100:-100:5]
    lagged, _ = interpolate_truth(truth, t - 0.5)  # a localizer half a second late
    write_estimates(tmp_path / "est.csv", t, lagged[:, :2])
    for extra, out in (([], "plain"), (["--latency", "2"], "lat")):
        res = subprocess.run(
            [
                *annotator_cmd(),
                "score",
                str(tmp_path / "est.csv"),
                "--truth",
                str(TRACK),
                "--out",
                str(tmp_path / out),
                "--no-plots",
                *extra,
            ],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert res.returncode == 0, res.stderr
    assert (
        json.loads((tmp_path / "plain" / "score.json").read_text(encoding="utf-8"))["latency"]
        is None
    )
    lat = json.loads((tmp_path / "lat" / "score.json").read_text(encoding="utf-8"))["latency"]
    assert lat["shift_s"] == pytest.approx(0.5)
    assert lat["ce50_2d_at_shift_m"] < 1e-3 < lat["ce50_2d_at_zero_m"]
