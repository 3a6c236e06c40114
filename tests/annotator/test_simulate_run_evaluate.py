"""A newcomer's path on a render of their own (issue 30): `annotator simulate` -> `annotator run`
-> `annotator evaluate`, end to end through the CLI. Before, `run` failed with "rssi: no .mbd
files" because simulate wrote no readings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.io.trajectory import read_trajectory

pytestmark = pytest.mark.slow


def test_simulate_then_run_then_evaluate(tmp_path: Path) -> None:
    out = tmp_path / "render"
    cli = CliRunner()
    res = cli.invoke(
        app,
        [
            "simulate",
            "--out",
            str(out),
            "--duration",
            "8",
            "--seed",
            "2",
            "--jobs",
            "2",
            "--cover",
            "1.0:1.0",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "run/ (" in res.output
    res = cli.invoke(app, ["run", str(out / "experiment.yaml"), "--out", str(out / "results")])
    assert res.exit_code == 0, res.output
    assert "readings inside the tracked span" in res.output
    res = cli.invoke(
        app,
        ["evaluate", str(out / "results" / "trajectory.csv"), "--truth", str(out / "truth.csv")],
    )
    assert res.exit_code == 0, res.output
    report = json.loads((out / "results" / "evaluation.json").read_text())
    assert report["position_error_m"]["median"] < 0.01

    # every labelled reading sits where the truth puts the bundle at the reading's own time
    labels = pd.read_parquet(out / "results" / "annotated.parquet")
    assert len(labels) > 100
    assert labels["sensor"].nunique() == 12
    truth = read_trajectory(out / "truth.csv")
    t = labels["t_ns"].to_numpy() / 1e9
    assert truth.t[0] <= t.min()
    assert t.max() <= truth.t[-1]
    true_xyz = np.column_stack([np.interp(t, truth.t, truth.position[:, k]) for k in range(3)])
    err = np.linalg.norm(labels[["x", "y", "z"]].to_numpy() - true_xyz, axis=1)
    assert np.median(err) < 0.01
    assert np.percentile(err, 95) < 0.03
    # the readings taken while the lenses were covered have no pose: none is labelled there
    rel = t - 1_700_000_000.0
    assert not ((rel > 1.2) & (rel < 1.8)).any()
