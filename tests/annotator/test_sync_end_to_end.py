"""`annotator run` end to end: a rendered experiment with a hands-cover event, RSSI simulated from
the same true trajectory, cameras starting at different times, ``sync.mode: auto``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from annotator.cli import app
from annotator.commands.run import write_run_outputs
from annotator.io.experiment import load_experiment
from annotator.io.report_records import REPORT_VERSION, read_report
from annotator.pipeline import RunSettings, run_experiment
from annotator.render import LoopTrajectory, render_experiment
from bgt_core.formats.devices import read_dev
from bgt_core.formats.mbd import iter_rows
from bgt_core.sites import site_dir

pytestmark = pytest.mark.slow

T0 = 1_700_000_000.0
DURATION = 6.5
START_OFFSET = 0.73  # the back camera starts this much after the front one
COVER = (0.5, 1.2)  # (start, duration) after T0, as the renderer takes it
RAMP = 0.15  # the renderer's hands take this long to close (and to open)
# The hands are over the beacon from the middle of the closing to the middle of the opening.
COVERED = (T0 + COVER[0] + RAMP / 2, T0 + COVER[0] + COVER[1] + RAMP / 2)
BEACON = "e78f135624ce"


def simulate_rssi(
    folder: Path,
    pose_at: LoopTrajectory,
    rng: np.random.Generator,
    *,
    t_span: tuple[float, float],
    covered: tuple[float, float] | None,
) -> int:
    """Per-sensor .mbd files of the bundle's beacon heard by the tetam sensors (log-distance path
    loss + noise); while ``covered`` the level drops 12 dB and most readings are lost."""
    folder.mkdir(parents=True, exist_ok=True)
    devices = read_dev(site_dir("tetam") / "tetam.dev")
    total = 0
    for mac, dev in devices.dongles.items():
        n = rng.poisson(8.0 * (t_span[1] - t_span[0]))
        t_ns = np.sort(rng.integers(int(t_span[0] * 1e9), int(t_span[1] * 1e9), n))
        pos, _ = pose_at(t_ns / 1e9)
        d = np.linalg.norm(pos - np.asarray(dev.position), axis=1)
        level = -50.0 - 20.0 * np.log10(np.maximum(d, 0.3)) + rng.normal(0.0, 3.0, n)
        keep = np.ones(n, dtype=bool)
        if covered is not None:
            inside = (t_ns >= covered[0] * 1e9) & (t_ns < covered[1] * 1e9)
            level[inside] -= 12.0
            keep = ~inside | (rng.random(n) < 0.3)
        rows = [
            f"{s // 10**9}.{s % 10**9:09d},{mac},{BEACON},{int(round(v))}\n"
            for s, v in zip(t_ns[keep].tolist(), level[keep], strict=True)
        ]
        (folder / f"{mac}.mbd").write_text("".join(rows), encoding="utf-8")
        total += len(rows)
    return total


def set_sync(experiment: Path, sync: dict) -> None:
    doc = yaml.safe_load(experiment.read_text(encoding="utf-8"))
    doc["sync"] = sync
    experiment.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("render")
    traj = LoopTrajectory(t0=T0)
    render_experiment(
        out, traj, (T0, T0 + DURATION), start_offset=START_OFFSET, covers=[COVER], seed=3, jobs=2
    )
    simulate_rssi(
        out / "rssi",
        traj,
        np.random.default_rng(0),
        t_span=(T0 - 2.0, T0 + DURATION + 2.0),
        covered=COVERED,
    )
    set_sync(out / "experiment.yaml", {"mode": "auto"})
    return out


def test_auto_sync_run_labels_readings_with_centimetre_error(
    rendered: Path, tmp_path: Path
) -> None:
    exp = load_experiment(rendered / "experiment.yaml")
    result = run_experiment(exp, RunSettings())
    write_run_outputs(tmp_path / "out", exp, result)
    truth_start = {"front": T0, "back": T0 + START_OFFSET}

    # Sync: each camera's start within a few ms, with an honest uncertainty.
    rep = read_report(tmp_path / "out" / "report.json")
    assert rep["version"] == REPORT_VERSION
    for name, true_start in truth_start.items():
        cam = rep["sync"]["cameras"][name]
        err = cam["video_start"] - true_start
        print(
            f"{name}: sync offset error {err * 1000:+.1f} ms (reported sigma "
            f"{cam['video_start_sigma_s'] * 1000:.1f} ms)"
        )
        assert abs(err) < 0.02
        assert 0 < cam["video_start_sigma_s"] < 0.05
        assert cam["method"].startswith("auto")
    # The back camera starts while the lens is covered; it is tied to the front one.
    assert rep["sync"]["cameras"]["back"]["method"] == "auto via front"
    assert rep["sync"]["mode"] == "auto"
    assert len(rep["sync"]["rssi_events"]) == 1
    # The self-calibration ran (default --refine all) and wrote its record and files.
    if result.refinement is not None:
        assert set(rep["refinement"]["cameras"]) == {"front", "back"}
        assert (tmp_path / "out" / rep["refinement"]["files"]["marker_positions"]).is_file()
    assert result.params is not None
    assert result.params.rig
    # The trajectory's sigma budget, as `annotator track` prints it.
    sig = result.trajectory.quality["sigma_m"]
    budget = rep["quality"]["trajectory_sigma_m"]
    assert budget["median"] == pytest.approx(np.nanmedian(sig))
    assert set(budget["parts_median"]) == {
        "sigma_params_m",
        "sigma_smoother_m",
        "sigma_blur_m",
        "sigma_unmodelled_m",
    }

    # Labels: every reading in the tracked span, position error against the truth at its own time.
    labels, table = result.labels, result.rssi
    lab = labels.labelled
    cov = rep["coverage"]["labelled_of_tracked_span"]
    print(f"labelled {lab.sum()} of {len(table)}; coverage of tracked span {cov:.3f}")
    assert cov >= 0.95
    # Readings under the hands are left out on purpose (the hands attenuate them), and reported.
    assert rep["counts"]["during_a_cover_event"] > 0
    truth_pos, truth_rot = LoopTrajectory(t0=T0)(table.t_ns[lab] / 1e9)
    err = np.linalg.norm(labels.positions[lab] - truth_pos, axis=1)
    print(
        f"position error: median {np.median(err) * 100:.2f} cm, p95 {np.percentile(err, 95) * 100:.2f} cm"
    )
    assert np.median(err) <= 0.02
    assert np.percentile(err, 95) <= 0.06
    ang = np.degrees((truth_rot.inv() * Rotation.from_matrix(labels.rotations[lab])).magnitude())
    print(f"rotation error: median {np.median(ang):.2f} deg")
    assert np.median(ang) < 2.0
    # Nothing outside the tracked span is labelled.
    span = rep["tracked_span"]
    t_lab = table.t_ns[lab] / 1e9
    assert t_lab.min() >= span["start"] - 1e-6
    assert t_lab.max() <= span["stop"] + 1e-6

    # Files: all_sensors.mbd has the labelled rows in time order; parquet the same rows.
    rows = list(iter_rows(tmp_path / "out" / "annotated" / "all_sensors.mbd"))
    assert len(rows) == int(lab.sum())
    assert [r.t_ns for r in rows] == sorted(r.t_ns for r in rows)
    assert len(list((tmp_path / "out" / "annotated").glob("*.mbd"))) == 13  # 12 sensors + all
    df = pd.read_parquet(tmp_path / "out" / "annotated.parquet")
    assert len(df) == len(rows)
    for name in ("trajectory.csv", "trajectory_map.png", "rssi_time.png", "rssi_on_trajectory.png"):
        assert (tmp_path / "out" / name).stat().st_size > 1000


def test_cli_manual_mode_and_missing_event(rendered: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    # Manual sync with the true starts: the CLI path, no plots.
    manual = tmp_path / "manual"
    manual.mkdir()
    for f in rendered.iterdir():
        if f.is_file():
            (manual / f.name).symlink_to(f)
    (manual / "rssi").symlink_to(rendered / "rssi")
    (manual / "experiment.yaml").unlink()
    (manual / "experiment.yaml").write_text((rendered / "experiment.yaml").read_text())
    set_sync(
        manual / "experiment.yaml",
        {"mode": "manual", "video_start": {"front": T0, "back": T0 + START_OFFSET}},
    )
    res = runner.invoke(
        app, ["run", str(manual / "experiment.yaml"), "--out", str(tmp_path / "o1"), "--no-plots"]
    )
    assert res.exit_code == 0, res.output
    rep = json.loads((tmp_path / "o1" / "report.json").read_text())
    assert rep["sync"]["cameras"]["back"]["video_start"] == pytest.approx(T0 + START_OFFSET)
    assert rep["sync"]["cameras"]["back"]["video_start_sigma_s"] is None
    # No event known in manual mode: nothing excluded; the cover shows up as a tracking gap.
    assert rep["counts"]["during_a_cover_event"] == 0
    assert rep["counts"]["inside_a_tracking_gap"] > 0
    assert rep["counts"]["labelled"] > 400
    assert rep["counts"]["labelled"] == len(
        list(iter_rows(tmp_path / "o1" / "annotated" / "all_sensors.mbd"))
    )
    assert not (tmp_path / "o1" / "rssi_time.png").exists()

    # Auto sync on RSSI without a drop: one red line naming the RSSI, exit 1, before any video work.
    flat = tmp_path / "flat"
    simulate_rssi(
        flat,
        LoopTrajectory(t0=T0),
        np.random.default_rng(1),
        t_span=(T0 - 2.0, T0 + DURATION + 2.0),
        covered=None,
    )
    doc = yaml.safe_load((manual / "experiment.yaml").read_text())
    doc["rssi"] = str(flat)
    doc["sync"] = {"mode": "auto"}
    (manual / "experiment.yaml").write_text(yaml.safe_dump(doc))
    res = runner.invoke(
        app, ["run", str(manual / "experiment.yaml"), "--out", str(tmp_path / "o2")]
    )
    assert res.exit_code == 1
    assert "no cover event found" in res.output
    assert f"RSSI of beacon {BEACON}" in res.output
    assert "Traceback" not in res.output
