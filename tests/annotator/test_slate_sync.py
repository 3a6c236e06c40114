"""`sync.mode: slate` end to end: `annotator simulate --slate` films the clock slate for a second
before and after the walk, `annotator run` reads it, maps each video onto the RSSI clock and
leaves the slate's frames out of the trajectory; a video without a slate falls back on the
hands cover."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from annotator.io.trajectory import read_trajectory
from annotator_cli import invoke

pytestmark = pytest.mark.slow

T0 = 1_700_000_000.0  # `annotator simulate`'s walk starts here
START_OFFSET = 0.41  # and the back camera this much later
SLATE_S = 1.0
RENDER = [
    "--duration", "10", "--slate", str(SLATE_S), "--cover", "1.0:1.5", "--rssi-rate", "10",
    "--readout", "0.015", "--write-readout", "--jobs", "2",
]  # fmt: skip


@pytest.fixture(scope="module")
def render(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("slate") / "render"
    invoke("simulate", "--out", str(out), *RENDER)
    return out


def test_slate_sync_maps_each_video_within_a_refresh(render: Path) -> None:
    text = (render / "experiment.yaml").read_text()
    assert "mode: slate" in text
    # not told when the videos started: only the slate says
    exp = render / "slate.yaml"
    exp.write_text(text.split("  video_start:")[0])
    results = render / "results"
    out = invoke("run", str(exp), "--out", str(results))
    assert "(slate)" in out
    report = json.loads((results / "report.json").read_text())
    assert report["sync"]["mode"] == "slate"
    truth = {"front": T0 - SLATE_S, "back": T0 + START_OFFSET - SLATE_S}
    for name, cam in report["sync"]["cameras"].items():
        assert cam["method"] == "slate"
        error = cam["video_start"] - truth[name]
        # within one refresh of a 60 Hz screen; and the stated sigma covers it
        assert abs(error) < 1 / 60, (name, error)
        assert abs(error) < 3 * cam["video_start_sigma_s"]
        slate = cam["slate"]
        assert len(slate["filmings_pts_s"]) == 2  # the start and the end
        assert slate["frames_used"] >= 40
        assert slate["frames_refused"] == 0
    # The walk measured each camera's clock against the other's: the moves are opposite (their
    # mean stays the slate's), each within a refresh, and they are in the starts above.
    moves = [cam["refined_offset_s"] for cam in report["sync"]["cameras"].values()]
    assert sum(moves) == pytest.approx(0.0, abs=1e-6)
    assert max(abs(m) for m in moves) < 1 / 60
    # the slate's frames are not rows of the trajectory: it spans the walk alone, every row posed
    traj = read_trajectory(results / "trajectory.csv")
    assert traj.t[0] >= T0 - 0.05
    assert traj.t[-1] <= T0 + 10 + 0.05
    outside = np.ones(len(traj.t), bool)
    outside &= ~((traj.t > T0 + 0.9) & (traj.t < T0 + 2.8))  # the hands over the lenses
    assert traj.valid[outside].mean() > 0.97


def test_without_a_slate_the_hands_cover_is_the_fallback(render: Path) -> None:
    """The same capture cut so that the back video never saw the slate: that camera falls back
    on the hands cover and says so; the front one keeps its slate."""
    import cv2

    src = cv2.VideoCapture(str(render / "back.mp4"))
    fps = src.get(cv2.CAP_PROP_FPS)
    size = (int(src.get(cv2.CAP_PROP_FRAME_WIDTH)), int(src.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    cut = render / "back_cut.mp4"
    out = cv2.VideoWriter(str(cut), cv2.VideoWriter.fourcc(*"mp4v"), fps, size)
    skip = int(round(fps * (SLATE_S - START_OFFSET + 0.2)))  # past the start's slate
    last = int(src.get(cv2.CAP_PROP_FRAME_COUNT)) - int(round(fps * (SLATE_S + 0.2)))
    k = 0
    while True:
        ok, frame = src.read()
        if not ok:
            break
        if skip <= k < last:
            out.write(frame)
        k += 1
    out.release()
    text = (render / "experiment.yaml").read_text().split("  video_start:")[0]
    exp = render / "fallback.yaml"
    exp.write_text(text.replace("back.mp4", "back_cut.mp4"))
    results = render / "fallback"
    invoke("run", str(exp), "--out", str(results))
    cams = json.loads((results / "report.json").read_text())["sync"]["cameras"]
    assert cams["front"]["method"] == "slate"
    assert cams["back"]["method"].startswith("auto")
    assert "slate" not in cams["back"]
    back_start = T0 + START_OFFSET - SLATE_S + skip / fps
    assert abs(cams["back"]["video_start"] - back_start) < 0.1
