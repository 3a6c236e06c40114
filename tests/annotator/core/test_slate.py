"""The clock slate: its code, reading it from pictures the renderer draws, and fitting a video's
clock map from the frames that show it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from annotator.core.sync.slate import (
    PERIOD_MS,
    SLATE_DICTIONARY,
    SlateReading,
    decode_slate,
    encode_slate,
    fit_slate_clock,
    read_slate_markers,
    slate_value_shown,
    unwrap_ms,
)
from annotator.errors import NoDataError
from annotator.render.slate import SlateShot, slate_frame

T0 = 1_790_000_000.0


def detector() -> cv2.aruco.ArucoDetector:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, SLATE_DICTIONARY))
    return cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters())


def read(img: np.ndarray) -> list[tuple[int, float]]:
    corners, ids, _ = detector().detectMarkers(img)
    return [] if ids is None else read_slate_markers(np.asarray(corners), np.asarray(ids))


def test_code_round_trip_and_check_digit() -> None:
    for t_ms in (0, 1, 999, 1_790_000_123_456, PERIOD_MS - 1):
        ids = encode_slate(t_ms)
        assert decode_slate(ids) == t_ms % PERIOD_MS
    a, b, c, k = encode_slate(1_790_000_123_456)
    assert (a, b, c) == (0, 123, 456)
    # any one digit wrong, or two codes mixed, is refused
    for i in range(4):
        bad = list(encode_slate(1_790_000_123_456))
        bad[i] = (bad[i] + 1) % 1000
        assert decode_slate(bad) is None
    mixed = [*encode_slate(1_790_000_123_456)[:2], *encode_slate(1_790_000_123_473)[2:3], k]
    assert decode_slate(mixed) is None
    assert decode_slate([1, 2, 3]) is None


def test_unwrap_picks_the_period_nearest_the_capture() -> None:
    t = T0 + 12.345
    assert unwrap_ms(np.array([int(t * 1000) % PERIOD_MS]), T0)[0] == pytest.approx(t, abs=1e-3)


def test_the_two_codes_update_on_alternate_refreshes() -> None:
    hz, phase = 60.0, 0.004
    t = T0 + np.arange(0, 1, 1e-4)
    for row in (0, 1):
        shown = slate_value_shown(t, hz, phase, row) / 1000.0
        err = shown - (t - T0) - T0
        # each shows the middle of its two-refresh hold: unbiased, within one refresh
        assert abs(err).max() <= 1 / hz + 1e-3
        assert abs(err.mean()) < 1e-3
        changes = t[1:][np.diff(shown) != 0]
        assert np.allclose(np.diff(changes), 2 / hz, atol=2e-4)
    a, b = slate_value_shown(t, hz, phase, 0), slate_value_shown(t, hz, phase, 1)
    assert not np.any((np.diff(a) != 0) & (np.diff(b) != 0))  # never both at once


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rendered_slate_reads_back_the_time_at_its_rows(seed: int) -> None:
    """Frames of the slate drawn with a 15 ms rolling shutter and 8 ms exposure: every frame
    gives at least one code, and each code is the time its rows were seen within a refresh."""
    rng = np.random.default_rng(seed)
    shot = SlateShot(60.0, float(rng.uniform(0, 1 / 60)), seed=seed)
    readout, exposure = 0.015, 0.008
    errors = []
    for i in range(12):
        t = T0 + i / 30
        codes = read(slate_frame(shot, t, 960, 540, readout, exposure))
        assert codes, f"frame {i}: no code read"
        for value, row in codes:
            seen = t + readout * row / 540
            errors.append(unwrap_ms(np.array([value]), T0)[0] - seen)
    assert max(abs(e) for e in errors) <= 1 / 60 + 2e-3


def test_a_frame_without_a_slate_reads_nothing() -> None:
    noise = np.random.default_rng(0).integers(0, 255, (540, 960), dtype=np.uint8)
    assert read(noise) == []


def readings_for(
    video_start: float, drift: float, spans: list[tuple[float, float]], hz: float, phase: float
) -> list[SlateReading]:
    """What a 30 fps global-shutter video starting at ``video_start`` reads during ``spans``."""
    out = []
    for a, b in spans:
        for pts in np.arange(a, b, 1 / 30):
            wall = video_start + pts * (1 + drift)
            for row in (0, 1):
                value = int(slate_value_shown(wall, hz, phase, row)) % PERIOD_MS
                out.append(SlateReading(float(pts), 150.0 + 250 * row, value))
    return out


@pytest.mark.parametrize("phase", [0.0, 0.003, 0.008, 0.0131])
def test_fit_finds_the_start_within_half_a_refresh_and_states_it(phase: float) -> None:
    start, drift = T0 + 0.37, 4e-4
    fit = fit_slate_clock(
        readings_for(start, drift, [(0, 1), (29, 30)], 60.0, phase),
        height=540,
        readout=0.0,
        near=T0,
        latency_sigma=0.0,
    )
    cm = fit.clock
    assert cm.method == "slate"
    assert len(fit.segments) == 2
    assert fit.frames_refused == 0
    assert abs(cm.video_start - start) <= 0.5 / 60 + 1e-3
    assert abs(cm.drift - drift) < 5e-4
    # the quantisation floor of both codes: 1/60/sqrt(12) s per filming
    assert cm.video_start_sigma == pytest.approx(1 / 60 / math.sqrt(12) * 1.3, rel=0.5)


def test_fit_applies_the_readout_and_latency() -> None:
    start = T0 + 0.5
    rs = readings_for(start, 0.0, [(0, 1)], 60.0, 0.002)
    # a rolling shutter of 20 ms: the code rows were seen later than the frame's stamp
    late = [SlateReading(r.pts - 0.02 * r.row / 540, r.row, r.value_ms) for r in rs]
    fit = fit_slate_clock(late, height=540, readout=0.02, near=T0, latency=0.004)
    assert abs(fit.clock.video_start - (start + 0.004)) <= 0.5 / 60 + 1e-3
    assert math.isnan(fit.clock.drift_sigma)  # one filming: no drift fitted
    assert fit.row_fraction == pytest.approx((150 + 400) / 2 / 540, abs=1e-6)


def test_a_misread_far_off_is_refused_and_no_slate_is_an_error() -> None:
    rs = readings_for(T0, 0.0, [(0, 1)], 60.0, 0.0)
    rs[5] = SlateReading(rs[5].pts, rs[5].row, (rs[5].value_ms + 400) % PERIOD_MS)
    fit = fit_slate_clock(rs, height=540, readout=0.0, near=T0)
    assert fit.frames_refused == 1
    assert abs(fit.clock.video_start - T0) <= 0.5 / 60 + 1e-3
    with pytest.raises(NoDataError, match="no readable clock slate"):
        fit_slate_clock([], height=540, readout=0.0, near=T0)
