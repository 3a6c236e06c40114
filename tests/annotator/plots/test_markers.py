"""`annotator markers print`: page count and size in the PDF, true printed size of the marker."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from typer.testing import CliRunner

from annotator.cli import app
from annotator.errors import ConfigError
from annotator.plots.marker_sheets import INCH, choose_paper, marker_page, parse_ids

PT_PER_M = 72 / INCH


def test_pdf_has_one_true_size_page_per_marker(tmp_path: Path) -> None:
    out = tmp_path / "markers.pdf"
    res = CliRunner().invoke(
        app, ["markers", "print", "--ids", "0-29", "--length", "0.298", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    pdf = out.read_bytes()
    assert pdf.startswith(b"%PDF")
    assert len(re.findall(rb"/Type\s*/Page\b", pdf)) == 30
    boxes = np.array(re.findall(rb"/MediaBox\s*\[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf), float)
    assert boxes.shape == (30, 2)
    # 298 mm plus margins does not fit A3 (297 mm wide): A2 portrait, 420 x 594 mm.
    np.testing.assert_allclose(
        boxes, np.broadcast_to([0.420 * PT_PER_M, 0.594 * PT_PER_M], boxes.shape), atol=0.01
    )


def dark_boxes(img: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Bounding boxes (x, y, w, h) of connected dark regions, largest first."""
    n, _, stats, _ = cv2.connectedComponentsWithStats((img < 128).astype(np.uint8))
    boxes = [tuple(int(v) for v in stats[i, :4]) for i in range(1, n)]
    return sorted(boxes, key=lambda b: -b[2] * b[3])


@pytest.mark.parametrize(("marker_id", "length", "paper"), [(7, 0.298, "A2"), (29, 0.15, "A4")])
def test_rendered_page_has_the_marker_at_true_size(
    marker_id: int, length: float, paper: str
) -> None:
    dpi = 100
    fig, box = marker_page(marker_id, length, "DICT_6X6_50", paper)
    assert fig.get_size_inches() == pytest.approx(
        np.array([0.210, 0.297]) / INCH if paper == "A4" else np.array([0.420, 0.594]) / INCH
    )
    fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    gray = cv2.cvtColor(np.asarray(canvas.buffer_rgba())[..., :3], cv2.COLOR_RGB2GRAY)
    px_per_m = dpi / INCH
    boxes = dark_boxes(gray)
    x, y, w, h = boxes[0]  # the marker's black square (its border is one connected region)
    assert w == pytest.approx(length * px_per_m, abs=1.5)
    assert h == pytest.approx(length * px_per_m, abs=1.5)
    bar = next(b for b in boxes[1:] if b[2] > 5 * b[3])  # the long thin scale bar
    assert bar[2] == pytest.approx(0.100 * px_per_m, abs=1.5)
    assert bar[1] > y + h, "scale bar below the marker"
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50))
    corners, ids, _ = det.detectMarkers(gray)
    assert ids is not None
    assert ids.ravel().tolist() == [marker_id]
    side = np.linalg.norm(corners[0][0, 1] - corners[0][0, 0])
    assert side == pytest.approx(length * px_per_m, abs=2.0)


def test_parse_ids() -> None:
    assert parse_ids("0-3,7, 5-5") == [0, 1, 2, 3, 7, 5]
    assert parse_ids("2,2") == [2]
    for bad in ("a-b", "5-2", "-1", ""):
        with pytest.raises(ConfigError):
            parse_ids(bad)


def test_paper_choice() -> None:
    assert choose_paper(0.15) == "A4"
    assert choose_paper(0.25) == "A3"
    assert choose_paper(0.298) == "A2"
    with pytest.raises(ConfigError, match="does not fit on A4"):
        choose_paper(0.298, "a4")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--ids", "49-50"], "marker id 50 is not in DICT_6X6_50"),
        (["--ids", "x"], "--ids 'x'"),
        (["--paper", "A4"], "does not fit on A4"),
        (["--dictionary", "DICT_FOO"], "unknown ArUco dictionary"),
    ],
)
def test_bad_options_are_one_line_errors(tmp_path: Path, args: list[str], message: str) -> None:
    out = tmp_path / "m.pdf"
    res = CliRunner().invoke(app, ["markers", "print", "--out", str(out), *args])
    assert res.exit_code == 1
    assert message in res.output
    assert not out.exists()
