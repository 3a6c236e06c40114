"""Radio maps: Wasserstein (quantile-function) interpolation on arrays, and `annotator radiomap`
writing .grd files in the published layout plus heat maps."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.core import radiomap as rm
from annotator.io import radio_data
from bgt_core.formats import devices, grd, hst, occ

DATASET = Path(__file__).resolve().parents[2] / "data" / "dataset"
EDGES = np.arange(-100.0, -19.0)
CENTRES = EDGES[:-1] + 0.5
BEACON = "e78f135624ce"
SENSOR = "000000000001"
runner = CliRunner()


def gaussian(mean: float, sigma: float = 2.0) -> np.ndarray:
    p = np.exp(-0.5 * ((CENTRES - mean) / sigma) ** 2)
    return p / p.sum()


def run(*args):
    return runner.invoke(app, [*map(str, args)], catch_exceptions=False)


def flat(text: str) -> str:
    return "".join(text.split())


# ---------------------------------------------------------------------------------------------
# pure interpolation


def test_one_histogram_with_weight_one_comes_back():
    h = gaussian(-70.5) * 0.5 + gaussian(-50.5, 4) * 0.5
    np.testing.assert_allclose(rm.wasserstein_mix(h[None], [1.0], EDGES), h, atol=1e-14)


def test_mixing_shifted_shapes_shifts_the_shape():
    a, b = gaussian(-80.5), gaussian(-60.5)
    half = rm.wasserstein_mix(np.stack([a, b]), [0.5, 0.5], EDGES)
    np.testing.assert_allclose(half, gaussian(-70.5), atol=1e-12)
    quarter = rm.wasserstein_mix(np.stack([a, b]), [3.0, 1.0], EDGES)  # weights are normalised
    np.testing.assert_allclose(quarter, gaussian(-75.5), atol=1e-12)
    # unlike a bin-wise average, which keeps two bumps and nothing in between
    binwise = 0.5 * (a + b)
    assert binwise[CENTRES == -70.5][0] < 1e-5
    assert half[CENTRES == -70.5][0] == pytest.approx(gaussian(-70.5).max())


def test_mix_of_sparse_histograms_is_exact():
    a = np.zeros(80)
    a[[10, 30]] = [0.3, 0.7]
    b = np.zeros(80)
    b[50] = 1.0
    m = rm.wasserstein_mix(np.stack([a, b]), [0.5, 0.5], EDGES)
    # the lower 30 % of a (bin 10) pairs with the lower 30 % of b: midway is bin 30; the rest, bin 40
    np.testing.assert_allclose(m[[30, 40]], [0.3, 0.7], atol=1e-12)
    assert m.sum() == pytest.approx(1.0)
    assert np.count_nonzero(m > 1e-12) == 2


def test_interpolate_at_a_fingerprint_returns_it_unchanged():
    rng = np.random.default_rng(1)
    hists = rng.random((5, 80)) ** 4
    hists /= hists.sum(axis=1, keepdims=True)
    xy = rng.random((5, 2)) * 10
    out = rm.interpolate(xy, hists, xy[[3, 0]], EDGES)
    np.testing.assert_array_equal(out, hists[[3, 0]])


def test_interpolate_midway_and_neighbour_rule():
    xy = np.array([[0.0, 0.0], [4.0, 0.0], [100.0, 0.0]])
    hists = np.stack([gaussian(-80.5), gaussian(-60.5), gaussian(-30.5)])
    # midway between the two near ones, k = 2: equal weights, the far one is not a neighbour
    out = rm.interpolate(xy, hists, [[2.0, 0.0]], EDGES, neighbours=2)
    np.testing.assert_allclose(out[0], gaussian(-70.5), atol=1e-12)
    # a quarter of the way: inverse-square weights 1/1 : 1/9 -> 0.9 : 0.1 -> -78.5
    out = rm.interpolate(xy, hists, [[1.0, 0.0]], EDGES, neighbours=2)
    np.testing.assert_allclose(out[0], gaussian(-78.5), atol=1e-12)
    # k = 1 is the nearest fingerprint
    out = rm.interpolate(xy, hists, [[2.9, 0.0]], EDGES, neighbours=1)
    np.testing.assert_array_equal(out[0], hists[1])


def test_missing_fingerprints_are_skipped_and_gaps_stay_gaps():
    xy = np.array([[0.0, 0.0], [1.0, 0.0]])
    hists = np.stack([np.full(80, np.nan), gaussian(-60.5)])
    out = rm.interpolate(xy, hists, [[0.0, 0.0]], EDGES)
    np.testing.assert_array_equal(out[0], gaussian(-60.5))
    none = rm.interpolate(xy, np.full((2, 80), np.nan), [[0.0, 0.0]], EDGES)
    assert np.isnan(none).all()


def test_mean_rssi():
    assert rm.mean_rssi(gaussian(-70.5), EDGES) == pytest.approx(-70.5)


# ---------------------------------------------------------------------------------------------
# the command

FPS = {
    (0.25, 0.25, 1.0): gaussian(-80.5),
    (2.25, 0.25, 1.0): gaussian(-60.5),
    (1.25, 1.75, 1.0): gaussian(-70.5, 3),
}


@pytest.fixture
def small_hst(tmp_path: Path) -> Path:
    devs = devices.Devices(
        {SENSOR: devices.Device(SENSOR, (1.0, 1.0, 2.0), 255, "s1")},
        {BEACON: devices.Device(BEACON, (), 0, "b1")},
    )
    h = hst.histograms_from_mapping(EDGES, devs, {p: {SENSOR: {BEACON: v}} for p, v in FPS.items()})
    path = tmp_path / "small.hst"
    hst.write_hst(h, path)
    return path


GRD_HEADER = re.compile(
    r"^(?P<mac>[0-9a-f]{12})::\[\[(?P<x0>[-0-9.e]+), (?P<y0>[-0-9.e]+)\], "
    r"\[(?P<x1>[-0-9.e]+), (?P<y1>[-0-9.e]+)\]\]::(?P<cell>[0-9.]+)::\[(?P<bins>[^\]]+)\]$"
)
GRD_ROW = re.compile(
    r"^\[(?P<gx>[-0-9.e]+), (?P<gy>[-0-9.e]+)\]::(?P<beacon>[0-9a-f]{12})::\[(?P<p>[^\]]+)\]$"
)


def test_radiomap_writes_grd_in_the_published_layout(small_hst: Path, tmp_path: Path):
    out = tmp_path / "maps"
    result = run("radiomap", small_hst, "--cell", "0.5", "--out", out)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        f"small_{SENSOR}_0.5.grd",
        f"small_{SENSOR}_0.5.png",
    ]
    assert (out / f"small_{SENSOR}_0.5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = (out / f"small_{SENSOR}_0.5.grd").read_text().splitlines()
    head = GRD_HEADER.match(lines[0])
    assert head is not None, lines[0]
    assert head["mac"] == SENSOR
    assert float(head["cell"]) == 0.5
    assert [float(v) for v in head["bins"].split(", ")] == list(EDGES)
    # extent: the fingerprints and the sensor, from a cell-aligned lower-left corner
    assert (float(head["x0"]), float(head["y0"]), float(head["x1"]), float(head["y1"])) == (
        0.0,
        0.0,
        2.25,
        1.75,
    )
    xs, ys = occ.grid_corners(((0.0, 0.0), (2.25, 1.75)), 0.5)
    seen = set()
    for line in lines[1:]:
        row = GRD_ROW.match(line)
        assert row is not None, line[:80]
        assert row["beacon"] == BEACON
        p = np.array([float(v) for v in row["p"].split(", ")])
        assert len(p) == 81  # one value per bin edge, as the published files
        assert p[-1] == 0.0
        assert p.sum() == pytest.approx(1.0, abs=1e-9)
        assert (p >= 0).all()
        seen.add((float(row["gx"]), float(row["gy"])))
    assert seen == {(x, y) for x in xs for y in ys}
    assert len(lines) - 1 == len(seen)
    # cells whose centre is a fingerprint get that fingerprint back, exactly
    g = grd.read_grd(out / f"small_{SENSOR}_0.5.grd")
    for (x, y, _), hist in FPS.items():
        np.testing.assert_array_equal(g.cells[(x - 0.25, y - 0.25)][BEACON], hist)
    # and the cell midway between the two lower ones is the shifted shape's neighbourhood:
    # its mean lies between theirs
    mid = rm.mean_rssi(np.array(g.cells[(1.0, 0.0)][BEACON]), EDGES)
    assert -80.5 < mid < -60.5


def _occupancy(tmp_path: Path) -> tuple[Path, set, set]:
    limits = ((0.0, 0.0), (2.25, 1.75))
    xs, ys = occ.grid_corners(limits, 0.5)
    cells = {(x, y): int((x + y) % 1.0 == 0.5) for y in ys for x in xs}
    path = tmp_path / "site_0.5.occ"
    occ.write_occ(occ.Occupancy(limits, 0.5, cells), path)
    return path, {c for c, v in cells.items() if v == 0}, {c for c, v in cells.items() if v == 1}


def test_occupancy_mask_is_respected(small_hst: Path, tmp_path: Path):
    path, free, occupied = _occupancy(tmp_path)
    assert free
    assert occupied
    out = tmp_path / "free"
    assert (
        run("radiomap", small_hst, "--occupancy", path, "--out", out, "--no-plots").exit_code == 0
    )
    g = grd.read_grd(out / f"small_{SENSOR}_0.5.grd")
    assert set(g.cells) == free
    assert g.limits == ((0.0, 0.0), (2.25, 1.75))
    assert not list(out.glob("*.png"))
    out1 = tmp_path / "occupied"
    assert (
        run(
            "radiomap",
            small_hst,
            "--occupancy",
            path,
            "--out",
            out1,
            "--no-plots",
            "--free-value",
            "1",
        ).exit_code
        == 0
    )
    assert set(grd.read_grd(out1 / f"small_{SENSOR}_0.5.grd").cells) == occupied


def test_radiomap_on_the_tetam_site(tmp_path: Path):
    h_path = tmp_path / "tetam.hst"
    assert run("fingerprints", DATASET / "fpt", "--out", h_path).exit_code == 0
    h = hst.read_hst(h_path)
    site = radio_data.detect_site(h.devices)
    assert site is not None
    assert site.name == "tetam"
    occ_path = DATASET / "occ" / "tetam_1.0.occ"
    out = tmp_path / "maps"
    result = run("radiomap", h_path, "--occupancy", occ_path, "--out", out, "--no-plots")
    assert result.exit_code == 0, result.output
    o = occ.read_occ(occ_path)
    free = {c for c, v in o.cells.items() if v == 0}
    grids = sorted(out.glob("*.grd"))
    assert len(grids) == 12
    fp = h.fingerprints[(2.59, 2.19, 2.05)]
    for path in grids:
        g = grd.read_grd(path)
        assert path.name == f"tetam_{g.sensor}_1.0.grd"
        assert g.limits == o.limits
        assert set(g.cells) == free
        # a single fingerprint: every cell is that fingerprint's histogram
        some = next(iter(g.cells.values()))[BEACON]
        np.testing.assert_allclose(some, fp[g.sensor][BEACON], atol=1e-12)


def test_heat_map_over_the_tetam_floor_plan(tmp_path: Path):
    import matplotlib.image

    full = tmp_path / "full.hst"
    assert run("fingerprints", DATASET / "fpt", "--out", full).exit_code == 0
    h = hst.read_hst(full)
    # one sensor's fingerprints keep the plot test short; the devices (and so the site) stay tetam's
    one = hst.FingerprintHistograms(
        h.bins,
        h.devices,
        {p: {"b827eb4521b4": s["b827eb4521b4"]} for p, s in h.fingerprints.items()},
    )
    path = tmp_path / "one.hst"
    hst.write_hst(one, path)
    out = tmp_path / "maps"
    assert run("radiomap", path, "--cell", "1.0", "--out", out).exit_code == 0
    png = out / "one_b827eb4521b4_1.0.png"
    image = matplotlib.image.imread(str(png))
    assert image.shape[0] > 400
    assert image.shape[1] > 400
    # the tetam grid comes from tetam.par's limits when no occupancy grid is given
    g = grd.read_grd(out / "one_b827eb4521b4_1.0.grd")
    assert g.limits == ((0.0, 0.0), (20.660138018121128, 17.64103475472807))
    assert len(g.cells) == 22 * 19


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            ["--cell", "1.0", "--occupancy", str(DATASET / "occ" / "tetam_0.5.occ")],
            "does not match",
        ),
        ([], "give --cell"),
        (["--cell", "0.5", "--neighbours", "0"], "--neighbours"),
        (["--cell", "0.5", "--free-value", "2"], "--free-value"),
    ],
)
def test_radiomap_bad_options(small_hst: Path, tmp_path: Path, extra, message):
    result = run("radiomap", small_hst, "--out", tmp_path / "m", *extra)
    assert result.exit_code == 1
    assert flat(message) in flat(result.output)
    assert not (tmp_path / "m").exists()


def test_malformed_hst_is_one_line_naming_file_and_line(tmp_path: Path):
    bad = tmp_path / "bad.hst"
    bad.write_text('Bins:[-100.0, -99.0]\nDongles:{}\nBeacons:{}\nFingerprints:{"(1, 2)": {}}\n')
    result = run("radiomap", bad, "--cell", "0.5", "--out", tmp_path / "m")
    assert result.exit_code == 1
    assert flat(f"{bad}:4:") in flat(result.output)
    assert "Traceback" not in result.output


def test_help_explains():
    result = run("radiomap", "--help")
    assert result.exit_code == 0
    assert "Wasserstein" in result.output
    assert "--occupancy" in result.output
