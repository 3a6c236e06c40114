"""Baseline localizers (weighted kNN, grid HMM) on a synthetic radio map with a known answer, and
the whole baseline pipeline on the bundled published track."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from annotator.core.localize import RadioMapArrays, Readings, grid_hmm, knn
from annotator.io.localize import radiomap_arrays
from bgt_core.formats.grd import RadioMapGrid

DATA = Path(__file__).resolve().parents[2] / "data" / "dataset"
EDGES = np.arange(-100.0, -19.0)
SENSORS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])


def path_loss_map(cell: float = 1.0, n: int = 10) -> RadioMapArrays:
    """Cells of a 10 x 10 m room; each sensor's histogram a narrow bump around a log-distance
    path-loss RSSI, so every cell has its own signature."""
    g = (np.arange(n) + 0.5) * cell
    centres = np.array([(x, y) for y in g for x in g])
    mid = 0.5 * (EDGES[:-1] + EDGES[1:])
    d = np.linalg.norm(centres[:, None] - SENSORS[None], axis=2)
    mu = -45.0 - 25.0 * np.log10(np.maximum(d, 0.3))
    hist = np.exp(-0.5 * ((mid[None, None] - mu[..., None]) / 1.5) ** 2)
    hist /= hist.sum(axis=2, keepdims=True)
    return RadioMapArrays(centres, ("a", "b", "c", "d"), EDGES, hist, cell)


def readings_at(m: RadioMapArrays, xy_of_t, t: np.ndarray, seed: int = 0) -> Readings:
    """Each reading from the map's own distribution at the cell holding the beacon's position."""
    rng = np.random.default_rng(seed)
    sensor = np.arange(len(t)) % 4
    rssi = np.empty(len(t))
    mid = 0.5 * (EDGES[:-1] + EDGES[1:])
    for i, (ti, s) in enumerate(zip(t, sensor, strict=True)):
        c = int(np.argmin(np.linalg.norm(m.centres - xy_of_t(ti), axis=1)))
        rssi[i] = rng.choice(mid, p=m.hist[c, s]) - 0.5  # an integer dBm: the bin's lower edge
    return Readings(t, sensor, rssi)


@pytest.mark.parametrize("method", ["knn", "grid-hmm"])
def test_standing_beacon_is_found_in_its_cell(method: str) -> None:
    m = path_loss_map()
    t = np.arange(0.0, 20.0, 0.05)
    r = readings_at(m, lambda _t: np.array([6.5, 3.5]), t)
    est = knn(m, r) if method == "knn" else grid_hmm(m, r)
    late = est.t > 5.0
    err = np.linalg.norm(est.xy[late] - [6.5, 3.5], axis=1)
    assert np.median(err) < 0.5  # within its 1 m cell


def test_hmm_follows_a_walk_and_beats_knn_on_it() -> None:
    m = path_loss_map()
    t = np.arange(0.0, 40.0, 0.05)

    def walk(ti: float) -> np.ndarray:  # 0.4 m/s along a diagonal and back
        s = 0.4 * (ti if ti < 20 else 40 - ti)
        return np.array([1.0, 1.0]) + s * np.array([0.7, 0.5])

    r = readings_at(m, walk, t, seed=4)
    est_h, est_k = grid_hmm(m, r, speed_mps=0.5), knn(m, r, window_s=1.0)
    err_h = np.linalg.norm(est_h.xy - np.array([walk(ti) for ti in est_h.t]), axis=1)
    err_k = np.linalg.norm(est_k.xy - np.array([walk(ti) for ti in est_k.t]), axis=1)
    assert np.nanpercentile(err_h, 75) < 1.0
    assert np.nanmedian(err_k) < 1.5
    assert np.nanpercentile(err_h, 75) < np.nanpercentile(err_k, 75)


def test_hmm_is_causal_and_silent_before_the_first_reading() -> None:
    m = path_loss_map()
    t = np.arange(3.0, 10.0, 0.1)
    r = readings_at(m, lambda _t: np.array([2.5, 7.5]), t)
    est = grid_hmm(m, r, step_s=0.5)
    assert est.t[0] == pytest.approx(3.5)
    assert np.isfinite(est.xy).all()
    # an estimate uses no reading at or after its own time: the same readings cut at 6 s give
    # the same estimates up to 6 s
    cut = r.t < 6.0
    est2 = grid_hmm(m, Readings(r.t[cut], r.sensor[cut], r.rssi[cut]), step_s=0.5)
    np.testing.assert_allclose(est2.xy[est2.t <= 6.0], est.xy[: int((est2.t <= 6.0).sum())])


def test_occupancy_mask_removes_occupied_cells(tmp_path: Path) -> None:
    edges = (-100.0, -99.0, -98.0)
    cells = {(0.0, 0.0): {"e78f135624ce": (0.5, 0.5)}, (1.0, 0.0): {"e78f135624ce": (1.0, 0.0)}}
    grid = RadioMapGrid("000000000101", ((0.0, 0.0), (2.0, 1.0)), 1.0, edges, cells)
    occ = tmp_path / "o.occ"
    occ.write_text(
        "[[0.0, 0.0], [2.0, 1.0]]::1.0\n[0.0, 0.0]::1\n[1.0, 0.0]::0\n", encoding="utf-8"
    )
    m = radiomap_arrays([grid], "e78f135624ce", occ)
    np.testing.assert_allclose(m.centres, [[1.5, 0.5]])
    assert radiomap_arrays([grid], "e78f135624ce").centres.shape == (2, 2)


def annotator_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "annotator"
    return (
        [str(exe)]
        if exe.is_file()
        else [sys.executable, "-c", "from annotator.cli import main; main()"]
    )


def run(*args: str) -> None:
    res = subprocess.run(
        [*annotator_cmd(), *args], capture_output=True, text=True, timeout=300, check=False
    )
    assert res.returncode == 0, res.stderr


def test_baselines_on_the_bundled_published_track(tmp_path: Path) -> None:
    """Radio map from the published histograms (1 m cells), both baselines on straight_01,
    scored against its annotation: both clearly better than always answering the room's
    free-floor centroid."""
    run(
        "radiomap",
        str(DATA / "hst" / "set_1" / "tetam_multi_rssi.hst"),
        "--occupancy",
        str(DATA / "occ" / "tetam_1.0.occ"),
        "--out",
        str(tmp_path / "rm"),
        "--no-plots",
    )
    truth = DATA / "trk" / "straight_01_all_sensors.mbd"
    ce75 = {}
    for method in ("knn", "grid-hmm"):
        est = tmp_path / f"{method}.csv"
        run(
            "localize",
            str(DATA / "trk" / "straight_01"),
            "--radiomap",
            str(tmp_path / "rm"),
            "--method",
            method,
            "--out",
            str(est),
        )
        run("score", str(est), "--truth", str(truth), "--out", str(tmp_path / method), "--no-plots")
        body = json.loads((tmp_path / method / "score.json").read_text(encoding="utf-8"))
        assert body["coverage"]["scored_fraction"] > 0.95
        ce75[method] = body["error_2d_m"]["ce75"]
    # the trivial answer: the centroid of the free cells, every time
    from annotator.core.scoring import score
    from annotator.io.localize import radiomap_arrays as arrays
    from annotator.io.localize import read_radiomap_grids
    from annotator.io.scoring import read_truth

    m = arrays(read_radiomap_grids(tmp_path / "rm"), "e78f135624ce")
    ref = read_truth(truth)
    t = ref.t[::5]
    centroid = np.tile([*m.centres.mean(axis=0), np.nan], (len(t), 1))
    trivial = score(t, centroid, ref).summary_2d.ce75
    assert max(ce75.values()) < 0.6 * trivial, (ce75, trivial)

    # the same readings as a collector run (rssi/<sensor>.mbd, no positions): the same estimates
    run_dir = tmp_path / "run"
    (run_dir / "rssi").mkdir(parents=True)
    for f in (DATA / "trk" / "straight_01").glob("*.mbd"):
        rows = [
            ",".join(line.split(",")[:4]) for line in f.read_text(encoding="utf-8").splitlines()
        ]
        (run_dir / "rssi" / f.name).write_text("\n".join(rows) + "\n", encoding="utf-8")
    run(
        "localize",
        str(run_dir),
        "--radiomap",
        str(tmp_path / "rm"),
        "--method",
        "grid-hmm",
        "--out",
        str(tmp_path / "from_run.csv"),
    )
    assert (tmp_path / "from_run.csv").read_text() == (tmp_path / "grid-hmm.csv").read_text()


def test_localize_bad_input_is_one_line_error(tmp_path: Path) -> None:
    track = str(DATA / "trk" / "straight_01")
    for args, message in (
        (["--radiomap", str(tmp_path / "nowhere")], "not a folder of .grd files"),
        (
            ["--radiomap", str(tmp_path), "--method", "magic"],
            "--method must be one of knn, grid-hmm",
        ),
        (["--radiomap", str(tmp_path)], "no .grd files"),
    ):
        res = subprocess.run(
            [*annotator_cmd(), "localize", track, "--out", str(tmp_path / "e.csv"), *args],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert res.returncode == 1, res.stderr
        assert message in res.stderr
        assert "Traceback" not in res.stderr
        assert not (tmp_path / "e.csv").exists()
