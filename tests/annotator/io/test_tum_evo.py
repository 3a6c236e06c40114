"""`annotator tum`: TUM export that evo reads, and evo_ape agreeing with `annotator score`."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.scoring import interpolate_truth
from annotator.core.trajectory import Trajectory
from annotator.io.scoring import read_truth, write_estimates
from annotator.io.trajectory import write_trajectory
from annotator.io.tum import read_poses

DATA = Path(__file__).resolve().parents[2] / "data" / "dataset"
TRACK = DATA / "trk" / "straight_01_all_sensors.mbd"
BIN = Path(sys.executable).parent


def annotator(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    exe = BIN / "annotator"
    cmd = (
        [str(exe)]
        if exe.is_file()
        else [sys.executable, "-c", "from annotator.cli import main; main()"]
    )
    res = subprocess.run(
        [*cmd, *args], capture_output=True, text=True, timeout=120, check=False, cwd=cwd
    )
    assert res.returncode == 0, res.stderr
    return res


def test_trajectory_export_keeps_pose_and_orientation(tmp_path: Path) -> None:
    t = np.array([10.0, 10.1, 10.2])
    rot = Rotation.from_euler("zyx", [[0.1, 0.2, 0.3], [0.5, 0.0, -0.2], [1.0, -0.3, 0.1]])
    pos = np.array([[1.0, 2.0, 1.5], [np.nan, np.nan, np.nan], [3.0, 4.0, 1.25]])
    mats = rot.as_matrix()
    mats[1] = np.nan  # a gap: not written
    write_trajectory(tmp_path / "trajectory.csv", Trajectory(t, pos, mats))
    annotator("tum", str(tmp_path), "--out", "x.tum", cwd=tmp_path)
    rows = np.loadtxt(tmp_path / "x.tum")
    assert rows.shape == (2, 8)
    np.testing.assert_allclose(rows[:, :4], [[10.0, 1.0, 2.0, 1.5], [10.2, 3.0, 4.0, 1.25]])
    got = Rotation.from_quat(rows[:, 4:])  # TUM: qx qy qz qw, scipy's scalar-last order
    assert (got.inv() * rot[[0, 2]]).magnitude().max() < 1e-9


def test_published_track_export_has_one_pose_per_timestamp() -> None:
    p = read_poses(TRACK)
    assert np.all(np.diff(p.t) > 0)
    # every orientation is a proper rotation (a unit quaternion once written)
    np.testing.assert_allclose(
        p.rotation @ p.rotation.transpose(0, 2, 1),
        np.broadcast_to(np.eye(3), p.rotation.shape),
        atol=1e-12,
    )


def _evo_stats(ref: Path, est: Path, tmp: Path, *extra: str) -> dict[str, float]:
    exe = BIN / "evo_ape"
    if not exe.is_file():
        pytest.skip("evo is not installed (pip install '.[dev]')")
    out = tmp / f"ape{len(list(tmp.glob('ape*.zip')))}.zip"
    # HOME: evo writes its settings file there on first use
    res = subprocess.run(
        [str(exe), "tum", str(ref), str(est), "--no_warnings", "--save_results", str(out), *extra],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "HOME": str(tmp), "MPLBACKEND": "Agg"},
    )
    assert res.returncode == 0, res.stdout + res.stderr
    with zipfile.ZipFile(out) as z:
        return json.loads(z.read("stats.json"))


def test_evo_ape_gives_the_same_figures_as_annotator_score(tmp_path: Path) -> None:
    pytest.importorskip("evo")
    truth = read_truth(TRACK)
    rng = np.random.default_rng(3)
    # estimates at their own times (between truth samples), some outside the truth's span
    t = np.sort(rng.uniform(truth.t[0] - 3, truth.t[-1] + 3, 300))
    ref, _ = interpolate_truth(truth, t)
    est = np.where(np.isfinite(ref), ref, [10.0, 8.0, 1.5]) + rng.normal(
        0, [0.8, 0.8, 0.3], (len(t), 3)
    )
    write_estimates(tmp_path / "est.csv", t, est)
    annotator(
        "score", "est.csv", "--truth", str(TRACK), "--out", "score", "--no-plots", cwd=tmp_path
    )
    body = json.loads((tmp_path / "score" / "score.json").read_text(encoding="utf-8"))
    assert 0 < body["error_3d_m"]["n"] < len(t)  # the estimates outside the truth are not scored

    annotator("tum", str(TRACK), "--at", "est.csv", "--out", "truth.tum", cwd=tmp_path)
    annotator("tum", "est.csv", "--out", "est.tum", cwd=tmp_path)
    annotator("tum", str(TRACK), "--at", "est.csv", "--flat", "--out", "truth2d.tum", cwd=tmp_path)
    annotator("tum", "est.csv", "--flat", "--out", "est2d.tum", cwd=tmp_path)
    # evo pairs poses by timestamp; the ones outside the truth have no partner and drop out
    for ref_file, est_file, block in (
        ("truth.tum", "est.tum", "error_3d_m"),
        ("truth2d.tum", "est2d.tum", "error_2d_m"),
    ):
        evo = _evo_stats(tmp_path / ref_file, tmp_path / est_file, tmp_path)
        ours = body[block]
        for ours_key, evo_key in (
            ("rmse", "rmse"),
            ("mean", "mean"),
            ("median", "median"),
            ("max", "max"),
        ):
            assert evo[evo_key] == pytest.approx(ours[ours_key], abs=1e-6), (block, ours_key)


def test_evo_ape_gives_the_same_figures_as_annotator_evaluate(tmp_path: Path) -> None:
    pytest.importorskip("evo")
    rng = np.random.default_rng(5)
    tt = np.arange(0.0, 30.0, 1 / 30) + 1.7e9
    tau = tt - tt[0]
    ref_pos = np.column_stack(
        [8 + 2 * np.sin(tau / 5), 6 + 2 * np.cos(tau / 5), 1.5 + 0.1 * np.sin(tau)]
    )
    rots = Rotation.from_euler("z", (tau / 5)[:, None]).as_matrix()
    write_trajectory(tmp_path / "truth.csv", Trajectory(tt, ref_pos, rots))
    # a tracker's output: its own frame times, a few cm off
    te = np.sort(rng.uniform(tt[0] + 0.5, tt[-1] - 0.5, 400))
    taue = te - tt[0]
    est = np.column_stack(
        [8 + 2 * np.sin(taue / 5), 6 + 2 * np.cos(taue / 5), 1.5 + 0.1 * np.sin(taue)]
    )
    est += rng.normal(0, 0.03, est.shape)
    write_trajectory(
        tmp_path / "est.csv",
        Trajectory(te, est, Rotation.from_euler("z", (taue / 5)[:, None]).as_matrix()),
    )
    annotator("evaluate", "est.csv", "--truth", "truth.csv", "--report", "ev.json", cwd=tmp_path)
    ours = json.loads((tmp_path / "ev.json").read_text(encoding="utf-8"))["position_error_m"]
    annotator("tum", "truth.csv", "--at", "est.csv", "--out", "truth.tum", cwd=tmp_path)
    annotator("tum", "est.csv", "--out", "est.tum", cwd=tmp_path)
    evo = _evo_stats(tmp_path / "truth.tum", tmp_path / "est.tum", tmp_path)
    for key in ("median", "mean", "max"):
        # trajectory.csv keeps 6 decimals of t: the truth is interpolated at the same rounded times
        assert evo[key] == pytest.approx(ours[key], abs=1e-6), key
