"""No systematic sync bias on known truth: the demo scenario's rendered video and simulated agents,
over seeds. The mean video-start error is small against a tolerance that a real RSSI lag of the
size the demo showed with seed 0 (+13 ms) fails, checked on the same data."""

from __future__ import annotations

import numpy as np
import pytest

from annotator import demo
from annotator.core.sync import CoverEvent, detect_rssi_events, detect_video_events, fit_clock_map
from annotator.io.sync import brightness_series
from annotator.render import render_experiment
from sensor_agent.scanning.simulated import simulate_fleet

T0 = 1_700_000_000.0
DURATION = 12.0  # two cover events (2 s and 9 s after t0), as `annotator demo --duration 12`
SEEDS = range(12)
TOLERANCE = 0.008  # s; the standard error of a 12-seed mean is ~3 ms


def _readings(seed: int):
    """The three simulated agents' readings, as `annotator demo` makes them with this seed."""
    settings = demo.DemoSettings(out=None, duration_s=DURATION, seed=seed)  # type: ignore[arg-type]
    events = demo.rssi_events(settings)
    ts, rs, ss = [], [], []
    for sim in simulate_fleet(
        "tetam", demo.split_sensors(), demo.demo_path(), round(T0 * 1e9), seed=seed, events=events
    ):
        for mac, r in sim.generate(DURATION + 1.0):
            ts.append(r.t_ns / 1e9)
            rs.append(r.rssi)
            ss.append(mac)
    return np.array(ts), np.array(rs, float), np.array(ss)


@pytest.fixture(scope="module")
def front_events(tmp_path_factory: pytest.TempPathFactory):
    """Cover events of the demo walk's front camera (starts at T0), rendered small."""
    settings = demo.DemoSettings(out=None, duration_s=DURATION)  # type: ignore[arg-type]
    out = tmp_path_factory.mktemp("walk")
    render_experiment(
        out,
        demo.bundle_pose_at(demo.demo_path(), T0),
        (T0, T0 + DURATION),
        width=320,
        height=180,
        start_offset=settings.start_offset_s,
        covers=settings.covers(),
        seed=0,
        jobs=1,
    )
    events = detect_video_events(*brightness_series(out / "front.mp4"), name="front")
    assert len(events) == 2
    return events


def test_video_start_has_no_systematic_error_over_seeds(front_events) -> None:
    err, sig, lagged = [], [], []
    for seed in SEEDS:
        t, r, s = _readings(seed)
        cm = fit_clock_map(front_events, detect_rssi_events(t, r, s))
        err.append(cm.video_start - T0)
        sig.append(cm.video_start_sigma)
        # The same readings stamped 13 ms late: what a detector or clock lag of the demo's size does.
        lagged.append(
            fit_clock_map(front_events, detect_rssi_events(t + 0.013, r, s)).video_start - T0
        )
    err, sig, lagged = np.array(err), np.array(sig), np.array(lagged)
    print(
        f"video-start error over {len(err)} seeds: mean {1e3 * err.mean():+.2f} ms, sd {1e3 * err.std():.2f} ms; "
        f"with a 13 ms lag: mean {1e3 * lagged.mean():+.2f} ms"
    )
    assert abs(err.mean()) < TOLERANCE, (
        f"mean video-start error {1e3 * err.mean():+.1f} ms over {len(err)} seeds"
    )
    # The check can fail: a 13 ms lag of every reading shows as a mean error outside the tolerance.
    assert lagged.mean() > TOLERANCE
    assert lagged.mean() - err.mean() == pytest.approx(0.013, abs=0.004)
    # Each error lies within 2.5 reported sigma (an honest sigma holds ~99 % there).
    assert np.all(np.abs(err) < 2.5 * sig), np.abs(err) / sig


def _two_events(
    rng: np.random.Generator, span: float, drift: float, start: float = 5.0, sigma: float = 0.017
) -> tuple[list[CoverEvent], list[CoverEvent]]:
    """Video events 2 s and 2 s + span into the video; their RSSI edges with ``sigma`` of noise
    (the demo's RSSI edges scatter by ~17 ms) and the video's +-20 ms symmetric widening."""
    video = [
        CoverEvent(2.0, 3.5, 0.0056, 0.0056),
        CoverEvent(2.0 + span, 3.5 + span, 0.0056, 0.0056),
    ]
    rssi = [
        CoverEvent(
            start + e.cover * (1 + drift) + rng.normal(0, sigma) + 0.02,
            start + e.release * (1 + drift) + rng.normal(0, sigma) - 0.02,
            sigma,
            sigma,
        )
        for e in video
    ]
    return video, rssi


@pytest.mark.parametrize("drift", [0.0, 50e-6])
def test_drift_prior_keeps_the_noise_of_two_close_events_out_of_the_clock_map(drift: float) -> None:
    # Two events 25 s apart (the 30 s demo) measure the drift to ~650 ppm: fitted freely, that
    # noise doubles the variance of the mapped time at the ends of the video.
    rng = np.random.default_rng(7)
    err, sig, err_flat = [], [], []
    for _ in range(200):
        video, rssi = _two_events(rng, 25.0, drift)
        for pts in (0.0, 30.0):
            truth = 5.0 + pts * (1 + drift)
            cm = fit_clock_map(video, rssi)
            err.append(float(cm.to_rssi(pts)) - truth)
            sig.append(float(cm.sigma_at(pts)))
            err_flat.append(
                float(fit_clock_map(video, rssi, drift_prior=None).to_rssi(pts)) - truth
            )
    err, sig, err_flat = np.array(err), np.array(sig), np.array(err_flat)
    rms, rms_flat = np.sqrt(np.mean(err**2)), np.sqrt(np.mean(err_flat**2))
    print(
        f"drift {drift * 1e6:g} ppm: rms {1e3 * rms:.1f} ms with the prior, {1e3 * rms_flat:.1f} ms flat"
    )
    assert rms < 0.8 * rms_flat
    assert np.mean(np.abs(err) <= 2 * sig) >= 0.92


def test_drift_prior_lets_a_large_drift_through() -> None:
    # A nominal-rate clock 1000 ppm off over a 10 min walk: the data decide, the prior does not pull.
    rng = np.random.default_rng(8)
    for _ in range(20):
        video, rssi = _two_events(rng, 590.0, 1e-3)
        cm = fit_clock_map(video, rssi)
        assert abs(cm.drift - 1e-3) < 3 * cm.drift_sigma
        assert abs(float(cm.to_rssi(595.0)) - (5.0 + 595.0 * 1.001)) < 0.05
