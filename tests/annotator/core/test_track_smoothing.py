"""The offline smoother on arrays: noise reduction, outlier gating, explicit gaps, true rotations."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.smoothing import SmootherSettings, smooth_positions, smooth_rotations, supported


def make_walk(n: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    t = 1_700_000_000.0 + np.arange(n) * dt
    s = np.arange(n) * dt
    return t, np.stack([0.4 * s, 0.3 * np.sin(0.5 * s), 1.5 + 0.05 * np.sin(s)], 1)


def test_positions_get_closer_to_truth_than_the_measurements():
    rng = np.random.default_rng(0)
    t, truth = make_walk(600, 1 / 30)
    z = truth + rng.normal(0, 0.01, truth.shape)
    cov = np.repeat((0.01**2 * np.eye(3))[None], len(t), 0)
    out, sig, ok, _ = smooth_positions(t, z, cov, t)
    raw = np.linalg.norm(z - truth, axis=1)
    err = np.linalg.norm(out - truth, axis=1)
    assert np.median(err) < 0.5 * np.median(raw)
    assert ok.all()
    assert np.all(sig < 0.01)


def test_noise_scale_makes_the_sigma_describe_the_noise_the_frames_show():
    t, truth = make_walk(900, 1 / 30)
    for real, stated in ((0.003, 0.003), (0.003, 0.010), (0.001, 0.010)):
        z = truth + np.random.default_rng(4).normal(0, real, truth.shape)
        cov = np.repeat((stated**2 * np.eye(3))[None], len(t), 0)
        out, sig, _, scale = smooth_positions(t, z, cov, t)
        err = np.sqrt(np.mean((out - truth) ** 2))  # per axis, rms over the walk
        # Scaled, the smoother's sigma is its own error, a little on the safe side (0.41-1.60 mm
        # against 0.46-1.71 mm); as stated it was up to 4x too large.
        assert err <= np.median(sig * scale) <= 1.25 * err
        assert scale < 0.85 if stated > real else scale > 0.7
    # Too few frames to measure a scatter: the stated noise stands.
    cov = np.repeat((0.010**2 * np.eye(3))[None], 20, 0)
    assert smooth_positions(t[:20], z[:20], cov, t[:20])[3] == 1.0


def test_outliers_are_gated_and_do_not_pull_the_track():
    rng = np.random.default_rng(1)
    t, truth = make_walk(300, 1 / 30)
    z = truth + rng.normal(0, 0.003, truth.shape)
    bad = np.arange(20, 300, 37)
    z[bad] += np.array([0.5, -0.4, 0.3])  # wrong-branch poses, half a metre off
    cov = np.repeat((0.003**2 * np.eye(3))[None], len(t), 0)
    out, _, ok, _ = smooth_positions(t, z, cov, t)
    assert not ok[bad].any()
    assert ok.sum() == len(t) - len(bad)
    assert np.linalg.norm(out - truth, axis=1).max() < 0.01


def test_gap_longer_than_max_gap_is_nan_and_query_times_between_frames_interpolate():
    t, truth = make_walk(300, 1 / 30)
    keep = (t - t[0] < 3.0) | (t - t[0] > 5.0)  # two seconds without any measurement
    cov = np.repeat((0.002**2 * np.eye(3))[None], keep.sum(), 0)
    t_q = t + 1 / 60  # half-way between frames
    out, sig, _, _ = smooth_positions(
        t[keep], truth[keep], cov, t_q, SmootherSettings(max_gap_s=0.5)
    )
    in_gap = (t_q - t[0] > 3.05) & (t_q - t[0] < 4.95)
    assert np.isnan(out[in_gap]).all()
    assert np.isnan(sig[in_gap]).all()
    valid = np.isfinite(out).all(1)
    assert valid.sum() > 200
    true_q = np.stack([np.interp(t_q[valid], t, truth[:, i]) for i in range(3)], 1)
    assert np.abs(out[valid] - true_q).max() < 0.005


def test_supported_marks_only_interpolation_or_short_extrapolation():
    tm = np.array([0.0, 0.1, 0.2, 2.0, 2.1])
    tq = np.array([-0.5, -0.05, 0.15, 1.0, 2.05, 2.15, 3.0])
    assert supported(tm, tq, max_gap=0.5, max_extrapolate=0.1).tolist() == [
        False,
        True,
        True,
        False,
        True,
        True,
        False,
    ]


def test_rotations_smoothed_on_so3_stay_rotations_and_reduce_noise():
    rng = np.random.default_rng(2)
    n, dt = 400, 1 / 30
    t = np.arange(n) * dt
    truth = Rotation.from_euler(
        "zyx", np.stack([1.2 * t, 0.1 * np.sin(t), 0.05 * np.cos(2 * t)], 1)
    )
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (n, 3)))
    meas = truth * noise
    meas_list = list(meas)
    outlier = Rotation.from_euler("x", 40, degrees=True)
    for i in (50, 51, 200):
        meas_list[i] = meas_list[i] * outlier
    meas = Rotation.concatenate(meas_list)
    R, ok = smooth_rotations(t, meas, np.full(n, np.radians(0.5) ** 2), t)
    assert not ok[[50, 51, 200]].any()
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(R), 1.0)
    err = np.degrees((Rotation.from_matrix(R) * truth.inv()).magnitude())
    raw = np.degrees((meas * truth.inv()).magnitude())
    assert np.median(err) < 0.4 * np.median(raw[ok])


def test_steady_turn_is_followed_without_lag():
    t = np.arange(120) / 30
    truth = Rotation.from_euler("z", (1.5 * t)[:, None])  # 86 deg/s
    out, _ = smooth_rotations(t, truth, np.full(len(t), 1e-6), t + 1 / 60)
    err = np.degrees(
        (
            Rotation.from_matrix(out[:-3])
            * Rotation.from_euler("z", (1.5 * (t[:-3] + 1 / 60))[:, None]).inv()
        ).magnitude()
    )
    assert err.max() < 0.01


def test_rotation_far_from_any_measurement_is_none():
    t = np.array([0.0, 0.1, 0.2])
    out, _ = smooth_rotations(t, Rotation.identity(3), np.full(3, 1e-6), np.array([0.1, 5.0]))
    assert np.isfinite(out[0]).all()
    assert np.isnan(out[1]).all()


def test_a_bad_start_after_a_gap_does_not_lose_the_track():
    """The first poses after a gap set the filter's velocity; if they are off, every later
    measurement fails the gate. The filter re-anchors on the measurements instead of coasting away."""
    rng = np.random.default_rng(2)
    t, truth = make_walk(120, 1 / 60)
    z = truth + rng.normal(0, 0.002, truth.shape)
    z[0] += [0.0, 0.04, 0.0]
    z[1] += [0.0, -0.03, 0.0]  # two poor poses: a velocity of -4 m/s
    cov = np.repeat((0.002**2 * np.eye(3))[None], len(t), 0)
    out, _, ok, _ = smooth_positions(t, z, cov, t)
    err = np.linalg.norm(out - truth, axis=1)
    assert ok[10:].all()
    assert err[10:].max() < 0.01
    assert err.max() < 0.05


def test_bridged_fills_short_gaps_between_poses_and_leaves_long_ones_and_the_ends():
    from annotator.core.trajectory import Trajectory

    t = np.arange(40) * 0.1
    yaw = np.radians(30) * t  # a steady 30 deg/s turn
    pos = np.stack([t, 0.5 * t, np.ones_like(t)], 1)
    rot = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    short, long_ = np.arange(5, 12), np.arange(20, 38)  # 0.8 s and 1.9 s between poses
    p, r = pos.copy(), rot.copy()
    for rows in (short, long_, np.arange(0, 2)):
        p[rows], r[rows] = np.nan, np.nan
    out = Trajectory(t, p, r).bridged(1.0)
    assert np.allclose(out.position[short], pos[short])  # linear motion: exact
    angle = Rotation.from_matrix(out.rotation[short]).as_euler("xyz")[:, 2]
    assert np.allclose(angle, yaw[short])  # a steady turn: slerp is exact
    assert not out.valid[long_].any()  # longer than asked: still a gap
    assert not out.valid[:2].any()  # before the first pose: never extrapolated
    assert Trajectory(t, pos, rot).bridged(1.0).valid.all()


def test_the_motion_for_the_self_calibration_keeps_a_carried_bundles_wobble():
    """A 3 Hz, 4 deg wobble (a bundle carried at a brisk walk) seen at 120 frames/s with 0.2 deg
    noise: the smoothed rotations keep about a third of its angular rate (0.08 s kernel), the
    motion handed to the self-calibration (0.04 s) three quarters."""
    from annotator.core.tracking import motion_rotations
    from annotator.core.trajectory import Trajectory

    rng = np.random.default_rng(4)
    t = np.arange(0, 4, 1 / 120)
    amp, f = np.radians(4.0), 3.0
    truth = Rotation.from_rotvec(np.column_stack([amp * np.sin(2 * np.pi * f * t), 0 * t, 0 * t]))
    noisy = truth * Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (len(t), 3)))
    cov = np.repeat((np.diag([np.radians(0.2) ** 2] * 3 + [0.002**2] * 3))[None], len(t), 0)
    meas = Trajectory(t, np.zeros((len(t), 3)), noisy.as_matrix(), {"cov": cov})
    s = SmootherSettings()
    wide, _ = smooth_rotations(t, noisy, np.full(len(t), np.radians(0.2) ** 2), t, s)
    narrow = motion_rotations(meas, t, wide, s)

    def rate_gain(R: np.ndarray) -> float:
        inner = slice(60, -60)  # away from the ends
        angle = Rotation.from_matrix(R[inner]).as_rotvec()[:, 0]
        return float(np.std(np.diff(angle)) / np.std(np.diff(truth.as_rotvec()[inner, 0])))

    print(f"rate gain: wide {rate_gain(wide):.2f}, narrow {rate_gain(narrow):.2f}")
    assert 0.25 < rate_gain(wide) < 0.45
    assert 0.65 < rate_gain(narrow) < 0.95
    # Rows the wide fit has no rotation for stay without one.
    gap = wide.copy()
    gap[100:110] = np.nan
    assert np.isnan(motion_rotations(meas, t, gap, s)[100:110]).all()
    assert np.isfinite(motion_rotations(meas, t, gap, s)[110:]).all()


def test_a_fast_turn_where_the_cameras_lose_the_markers_for_0_65_s_is_bridged_honestly():
    """A 1.2 m/s walk round a corner turning at up to ~60 deg/s, with no pose for 0.65 s in the
    middle of the turn (both cameras saw only blurred, far markers): every row of the hole gets
    a position within 2.8 of its sigma and a rotation within 3 deg; a 1 s hole stays a gap."""
    from annotator.core.tracking import smooth
    from annotator.core.trajectory import Trajectory

    rng = np.random.default_rng(7)
    t = np.arange(0, 4, 1 / 60)
    heading = np.radians(90) / (1 + np.exp(-(t - 2) / 0.25))  # a 90 deg turn centred at 2 s
    rate = np.gradient(heading, t)
    assert np.degrees(rate.max()) > 80  # the heading's rate; the bundle turns with it
    vel = 1.2 * np.column_stack([np.cos(heading), np.sin(heading), 0 * t])
    truth = np.cumsum(vel, axis=0) / 60
    rot = Rotation.from_euler("z", heading[:, None])
    noise = 0.003
    z = truth + rng.normal(0, noise, truth.shape)
    cov = np.repeat(np.diag([np.radians(0.3) ** 2] * 3 + [noise**2] * 3)[None], len(t), 0)
    s = SmootherSettings()
    for hole_s, bridged in ((0.65, True), (1.0, False)):
        seen = np.abs(t - 2) > hole_s / 2
        meas = Trajectory(t[seen], z[seen], rot[seen].as_matrix(), {"cov": cov[seen]})
        pos, R, sig = smooth(meas, t, s)
        hole = ~seen
        if not bridged:
            assert np.isnan(pos[hole]).all()
            continue
        assert np.isfinite(pos[hole]).all()
        assert np.isfinite(R[hole]).all()
        err = np.linalg.norm(pos - truth, axis=1)
        assert (err[hole] < 2.8 * np.sqrt(3) * sig[hole]).all()  # sig is per axis
        assert err[hole].max() < 0.05
        angle = (Rotation.from_matrix(R[hole]).inv() * rot[hole]).magnitude()
        assert np.degrees(angle).max() < 3.0
