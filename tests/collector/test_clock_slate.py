"""`collector slate`: the page a camera films for `sync.mode: slate`. Its code table is OpenCV's
own, its clock follows the host's, and a screenshot of it in a real browser (Debian's chromium)
reads back, with the annotator's reader, as the time it was taken."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
uvicorn = pytest.importorskip("uvicorn")
cv2 = pytest.importorskip("cv2")

from annotator.core.sync.slate import (  # noqa: E402
    SLATE_DICTIONARY,
    read_slate_markers,
    unwrap_ms,
)
from collector.web.slate import build_slate_app, slate_codes  # noqa: E402
from loopback import free_port  # noqa: E402
from polling import wait_for  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def test_the_code_table_is_opencvs_dictionary() -> None:
    table = json.loads(slate_codes())
    assert table["dictionary"] == SLATE_DICTIONARY
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, SLATE_DICTIONARY))
    assert len(table["codes"]) == 1000
    for marker_id in (0, 1, 417, 999):
        cells = cv2.aruco.generateImageMarker(d, marker_id, 7)[1:6, 1:6] > 127
        bits = int("".join("1" if c else "0" for c in cells.ravel()), 2)
        assert table["codes"][marker_id] == bits


@pytest.fixture
def slate_url() -> Iterator[str]:
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(build_slate_app(), host="127.0.0.1", port=port, log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 20, "the slate to listen")
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        server.should_exit = True
        thread.join(10)


def test_time_is_the_hosts_clock(slate_url: str) -> None:
    before = time.time() * 1000
    with urllib.request.urlopen(slate_url + "time") as r:
        assert r.headers["Cache-Control"] == "no-store"
        t_ms = json.load(r)["t_ms"]
    assert before - 1 <= t_ms <= time.time() * 1000 + 1


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_a_screenshot_of_the_page_reads_as_the_time_it_was_taken(slate_url: str) -> None:
    shot = Path(tempfile.mkdtemp(prefix="slate-")) / "slate.png"
    before = time.time()
    subprocess.run(
        [
            CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--window-size=1280,720", "--virtual-time-budget=3000", f"--screenshot={shot}",
            slate_url,
        ],
        capture_output=True, timeout=120,
    )  # fmt: skip
    after = time.time()
    print(f"slate screenshot: {shot}")
    img = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, SLATE_DICTIONARY))
    corners, ids, _ = cv2.aruco.ArucoDetector(d).detectMarkers(img)
    assert ids is not None, "no marker of the slate in the screenshot"
    codes = read_slate_markers(np.asarray(corners), np.asarray(ids))
    assert codes, f"markers {ids.ravel().tolist()} make no code that passes its check"
    for value, _row in codes:
        shown = unwrap_ms(np.array([value]), before)[0]
        # the time shown lies within the browser's run (a headless browser's virtual time may
        # run a little ahead of the wall clock)
        assert before - 0.5 <= shown <= after + 3.5, (shown - before, after - before)
    rows = sorted(row for _, row in codes)
    assert rows[0] < img.shape[0] / 2  # the upper code sits in the upper half
