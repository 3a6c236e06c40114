"""Sync stages on synthetic series with known cover/release times."""

from __future__ import annotations

import math

import numpy as np
import pytest

from annotator.core.sync import (
    CoverEvent,
    VideoSeries,
    detect_rssi_events,
    detect_video_events,
    fit_clock_map,
    manual_clock_map,
    synchronise,
)
from annotator.errors import NoDataError

FPS = 30.0
FRAME = 1.0 / FPS


def covered_fraction(
    pts: np.ndarray,
    events: list[tuple[float, float]],
    ramp: float = 0.0,
    exposure: float = FRAME,
    sub: int = 40,
) -> np.ndarray:
    """Fraction of each frame's exposure (centred on its PTS) during which the lens is covered.

    With ``ramp`` > 0 the hands take that long to cover (and to uncover) the lens; the edge time
    is the middle of the ramp.
    """
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    s = pts[:, None] + offs[None, :] * exposure
    f = np.zeros_like(s)
    for a, b in events:
        if ramp > 0:
            up = np.clip((s - (a - ramp / 2)) / ramp, 0, 1)
            down = np.clip(((b + ramp / 2) - s) / ramp, 0, 1)
            f = np.maximum(f, np.minimum(up, down))
        else:
            f = np.maximum(f, ((s >= a) & (s < b)).astype(float))
    return f.mean(axis=1)


def make_video(
    rng: np.random.Generator,
    events: list[tuple[float, float]],
    *,
    duration: float = 12.0,
    start_pts: float = 0.0,
    ramp: float = 0.0,
    noise: float = 2.0,
    bright: float = 110.0,
    dark: float = 10.0,
    fps: float = FPS,
    gamma: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pts, mean brightness, marker count of a moving camera whose lens is covered in ``events``.

    ``gamma`` != 1 makes the picture darken non-linearly with the covered fraction, which moves
    each brightness edge away from the cover time (in opposite directions for cover and release).
    """
    pts = start_pts + np.arange(0.0, duration, 1.0 / fps)
    f = covered_fraction(pts, events, ramp, 1.0 / fps) ** gamma
    scene = bright * (
        1.0 + 0.14 * np.sin(0.7 * pts) + 0.05 * np.sin(2.3 * pts)
    )  # the room changes as we move
    b = scene * (1 - f) + dark * f + rng.normal(0.0, noise, pts.size)
    markers = np.where(f > 0.4, 0, rng.integers(1, 7, pts.size))
    return pts, b, markers


def make_rssi(
    rng: np.random.Generator,
    covered: list[tuple[float, float]],
    *,
    duration: float = 30.0,
    t0: float = 1_700_000_000.0,
    sensors: int = 12,
    rate: float = 8.0,
    drop_db: float = 12.0,
    keep: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pooled readings of one beacon at ``sensors`` sensors; in ``covered`` (seconds from t0) the
    level drops by ``drop_db`` and only ``keep`` of the readings survive."""
    ts, rs, ss = [], [], []
    for k in range(sensors):
        n = rng.poisson(rate * duration)
        t = np.sort(rng.uniform(0.0, duration, n))
        level = -55.0 - 3.0 * k + 6.0 * np.sin(0.3 * t + k) + rng.normal(0.0, 4.0, n)
        inside = np.zeros(n, dtype=bool)
        for a, b in covered:
            inside |= (t >= a) & (t < b)
        level[inside] -= drop_db
        survive = ~inside | (rng.random(n) < keep)
        ts.append(t[survive] + t0)
        rs.append(np.round(level[survive]))
        ss.append(np.full(survive.sum(), f"00000000{k:04x}"))
    return np.concatenate(ts), np.concatenate(rs), np.concatenate(ss)


# --- (a) video ---------------------------------------------------------------------------------


@pytest.mark.parametrize("phase", [0.0, 0.23, 0.5, 0.81])
@pytest.mark.parametrize("ramp", [0.0, 0.2])
def test_video_edges_found_to_a_fraction_of_a_frame(phase: float, ramp: float) -> None:
    rng = np.random.default_rng(int(phase * 100) + int(ramp * 10))
    cover, release = 2.0 + phase * FRAME, 3.6 + (1 - phase) * 0.37 * FRAME
    pts, b, mc = make_video(rng, [(cover, release)], ramp=ramp)
    (ev,) = detect_video_events(pts, b, mc, name="front")
    assert ev.source == "brightness"
    assert abs(ev.cover - cover) < 0.25 * FRAME
    assert abs(ev.release - release) < 0.25 * FRAME
    for err, sig in ((ev.cover - cover, ev.cover_sigma), (ev.release - release, ev.release_sigma)):
        assert 0 < sig < FRAME
        assert abs(err) < 4 * sig + 1e-3


def test_video_pts_offset_and_two_events() -> None:
    rng = np.random.default_rng(7)
    truth = [(10.412, 11.873), (95.05, 96.2)]
    pts, b, mc = make_video(rng, truth, duration=100.0, start_pts=5.0)
    evs = detect_video_events(pts, b, mc)
    assert len(evs) == 2
    for ev, (a, z) in zip(evs, truth, strict=True):
        assert ev.cover == pytest.approx(a, abs=0.25 * FRAME)
        assert ev.release == pytest.approx(z, abs=0.25 * FRAME)


def test_short_cover_in_a_long_video() -> None:
    rng = np.random.default_rng(9)
    cover, release = 301.37, 302.81  # 1.4 s in 10 minutes: 0.2 % of the frames
    pts, b, mc = make_video(rng, [(cover, release)], duration=600.0)
    b[[1000, 9000]] = 0.0  # two glitched black frames are not covers
    (ev,) = detect_video_events(pts, b, mc)
    assert ev.source == "brightness"
    assert abs(ev.cover - cover) < 0.25 * FRAME
    assert abs(ev.release - release) < 0.25 * FRAME


def test_video_marker_count_alone_when_too_little_light_change() -> None:
    rng = np.random.default_rng(3)
    cover, release = 2.5, 4.0
    pts, b, mc = make_video(rng, [(cover, release)], bright=40.0, dark=35.0, noise=1.0)
    (ev,) = detect_video_events(pts, b, mc)
    assert ev.source == "markers"
    assert abs(ev.cover - cover) <= FRAME
    assert abs(ev.release - release) <= FRAME


def test_video_starting_covered_gives_only_the_release() -> None:
    rng = np.random.default_rng(4)
    pts, b, mc = make_video(rng, [(-1.0, 1.234)])
    (ev,) = detect_video_events(pts, b, mc)
    assert math.isnan(ev.cover)
    assert ev.release == pytest.approx(1.234, abs=0.25 * FRAME)
    assert ev.edges() == [(ev.release, ev.release_sigma)]


def test_video_without_event_raises_naming_the_video() -> None:
    rng = np.random.default_rng(5)
    pts, b, mc = make_video(rng, [])
    with pytest.raises(NoDataError, match="back: no cover event"):
        detect_video_events(pts, b, mc, name="back")


def test_dark_scene_with_markers_is_not_a_cover() -> None:
    rng = np.random.default_rng(6)
    pts, b, _ = make_video(rng, [(3.0, 4.5)])
    markers = np.full(pts.size, 4)  # markers stay visible: a dark wall, not hands
    with pytest.raises(NoDataError):
        detect_video_events(pts, b, markers)


def test_too_short_or_too_long_darkness_is_not_a_cover() -> None:
    rng = np.random.default_rng(8)
    pts, b, mc = make_video(rng, [(2.0, 2.1), (4.0, 9.0)], duration=14.0)
    with pytest.raises(NoDataError):
        detect_video_events(pts, b, mc, min_duration=0.3, max_duration=3.0)


# --- (b) RSSI ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("drop_db", "keep"), [(12.0, 0.3), (15.0, 0.0), (10.0, 1.0)])
def test_rssi_cover_interval_recovered(drop_db: float, keep: float) -> None:
    rng = np.random.default_rng(int(drop_db) + int(10 * keep))
    t0 = 1_700_000_000.0
    cover, release = 8.3217, 9.8911
    t, r, s = make_rssi(rng, [(cover, release)], drop_db=drop_db, keep=keep, t0=t0)
    (ev,) = detect_rssi_events(t, r, s)
    assert ev.source == "rssi"
    assert abs(ev.cover - (t0 + cover)) < 0.1
    assert abs(ev.release - (t0 + release)) < 0.1
    assert 0 < ev.cover_sigma < 0.1
    assert 0 < ev.release_sigma < 0.1


def test_rssi_two_events() -> None:
    rng = np.random.default_rng(11)
    t0 = 1_700_000_000.0
    truth = [(4.0, 5.5), (52.2, 53.4)]
    t, r, s = make_rssi(rng, truth, duration=60.0, t0=t0)
    evs = detect_rssi_events(t, r, s)
    assert len(evs) == 2
    for ev, (a, z) in zip(evs, truth, strict=True):
        assert ev.cover == pytest.approx(t0 + a, abs=0.1)
        assert ev.release == pytest.approx(t0 + z, abs=0.1)


def test_rssi_without_event_raises() -> None:
    rng = np.random.default_rng(12)
    t, r, s = make_rssi(rng, [])
    with pytest.raises(NoDataError, match="RSSI: no cover event"):
        detect_rssi_events(t, r, s)


def test_rssi_too_few_readings_raises() -> None:
    with pytest.raises(NoDataError, match="too few"):
        detect_rssi_events(np.arange(5.0), np.full(5, -60.0), np.zeros(5))


# --- (c) clock map -----------------------------------------------------------------------------


def test_offset_from_one_event_with_detectors_end_to_end() -> None:
    rng = np.random.default_rng(21)
    t0 = 1_700_000_000.0
    video_start = t0 + 2.41  # wall time of the first frame
    cover, release = 5.123, 6.811  # wall seconds from t0
    pts, b, mc = make_video(rng, [(cover - 2.41, release - 2.41)], duration=20.0)
    t, r, s = make_rssi(rng, [(cover, release)], t0=t0)
    cm = fit_clock_map(detect_video_events(pts, b, mc), detect_rssi_events(t, r, s), name="back")
    assert cm.method == "auto"
    assert cm.drift == 0.0
    assert cm.n_edges == 2
    assert abs(cm.video_start - video_start) < 0.05
    assert 0 < cm.video_start_sigma < 0.05
    assert abs(cm.video_start - video_start) < 4 * cm.video_start_sigma + 0.005


def test_drift_from_two_events() -> None:
    rng = np.random.default_rng(22)
    t0 = 1_700_000_000.0
    start, drift = t0 + 1.7, 8e-4  # a camera clock running 800 ppm slow
    wall = [(4.0, 5.6), (112.0, 113.3)]
    to_pts = [((a + t0 - start) / (1 + drift), (z + t0 - start) / (1 + drift)) for a, z in wall]
    pts, b, mc = make_video(rng, to_pts, duration=115.0)
    t, r, s = make_rssi(rng, wall, duration=118.0, t0=t0)
    cm = fit_clock_map(detect_video_events(pts, b, mc), detect_rssi_events(t, r, s))
    assert cm.n_edges == 4
    assert abs(cm.drift - drift) < 3e-4
    assert abs(cm.drift - drift) < 4 * cm.drift_sigma
    assert abs(cm.video_start - start) < 0.05
    # The mapped time at the end of the video is right too (not just the start).
    assert abs(cm.to_rssi(110.0) - (start + 110.0 * (1 + drift))) < 0.05


def test_matching_uses_durations_and_the_prior() -> None:
    video = [CoverEvent(2.0, 3.5, 0.01, 0.01)]
    rssi = [CoverEvent(100.0, 100.8, 0.02, 0.02), CoverEvent(130.0, 131.5, 0.02, 0.02)]
    cm = fit_clock_map(video, rssi)
    assert cm.video_start == pytest.approx(128.0, abs=1e-9)
    # Two events of equal length: the approximate start decides.
    rssi2 = [CoverEvent(100.0, 101.5, 0.02, 0.02), CoverEvent(130.0, 131.5, 0.02, 0.02)]
    assert fit_clock_map(video, rssi2, approx_start=97.5).video_start == pytest.approx(98.0)
    assert fit_clock_map(video, rssi2, approx_start=127.0).video_start == pytest.approx(128.0)


def test_unmatched_events_raise() -> None:
    video = [CoverEvent(2.0, 3.5, 0.01, 0.01)]
    rssi = [CoverEvent(100.0, 106.0, 0.02, 0.02)]
    with pytest.raises(NoDataError, match="front: its cover events"):
        fit_clock_map(video, rssi, name="front")
    with pytest.raises(NoDataError, match="no cover event in the RSSI"):
        fit_clock_map(video, [], name="front")


def test_manual_fallback() -> None:
    cm = manual_clock_map(1_700_000_000.41)
    assert cm.method == "manual"
    assert cm.to_rssi(np.array([0.0, 2.0])) == pytest.approx([1_700_000_000.41, 1_700_000_002.41])
    assert cm.to_video(1_700_000_001.41) == pytest.approx(1.0)


def test_camera_seeing_only_the_release_is_synced_through_the_other() -> None:
    rng = np.random.default_rng(31)
    t0 = 1_700_000_000.0
    covered = (3.0, 4.6)  # wall seconds after t0 (mid-closing to mid-opening of the hands)
    rssi_events = [CoverEvent(t0 + covered[0], t0 + covered[1], 0.004, 0.004, "rssi")]
    starts = {"a": 0.0, "b": 3.8}  # camera b starts recording while covered
    series = {}
    for name, st in starts.items():
        ev = [(covered[0] - st, covered[1] - st)]
        pts, b, mc = make_video(rng, ev, duration=10.0, ramp=0.3, gamma=2.5)
        series[name] = VideoSeries(pts, b, mc)
    res = synchronise(series, rssi_events)
    assert math.isnan(res.video_events["b"][0].cover)
    err = {n: res.clocks[n].video_start - (t0 + st) for n, st in starts.items()}
    assert abs(err["a"]) < 0.008  # the pair cancels the fade's bias
    assert res.clocks["b"].method == "auto via a"
    assert abs(err["b"]) < 0.012
    # Alone, b has only its biased release edge: the error is larger, and so is the stated sigma.
    alone = synchronise({"b": series["b"]}, rssi_events).clocks["b"]
    assert alone.method == "auto"
    assert alone.video_start_sigma >= 0.03
    assert abs(alone.video_start - (t0 + 3.8)) > 0.02
    assert abs(alone.video_start - (t0 + 3.8)) < 3 * alone.video_start_sigma


def test_rssi_edges_at_a_low_reading_rate_have_no_outliers() -> None:
    # 3 readings/s per sensor: chance lulls after the release stretch the coarse interval, and
    # once fooled an edge fit that only looked near the coarse edge (1.4 s off).
    t0 = 1_700_000_000.0
    errors = []
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        cover = rng.uniform(8.0, 9.0)
        release = cover + rng.uniform(1.0, 2.0)
        t, r, s = make_rssi(rng, [(cover, release)], rate=3.0, t0=t0)
        (ev,) = detect_rssi_events(t, r, s)
        errors += [ev.cover - t0 - cover, ev.release - t0 - release]
    assert np.max(np.abs(errors)) < 0.2
    assert np.median(np.abs(errors)) < 0.04
