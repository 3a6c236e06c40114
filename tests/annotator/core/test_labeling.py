"""Labelling readings with interpolated poses: exact on motions interpolation reproduces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.labeling import (
    AFTER_SPAN,
    BEFORE_SPAN,
    COVERED,
    IN_GAP,
    LABELLED,
    describe_counts,
    label_readings,
    tracked_span_coverage,
)
from annotator.core.trajectory import Trajectory

T0 = 1_700_000_000.0
VEL = np.array([0.4, -0.1, 0.02])  # m/s
P0 = np.array([3.0, 4.0, 1.5])
AXIS = np.array([0.2, -0.3, 0.9]) / np.linalg.norm([0.2, -0.3, 0.9])
OMEGA = 0.6  # rad/s about AXIS
R0 = Rotation.from_euler("xyz", [0.1, -0.2, 1.0])


def truth(t_rel: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Linear motion and a constant-rate rotation: what linear interpolation and Slerp reproduce."""
    return P0 + t_rel[:, None] * VEL, Rotation.from_rotvec(np.outer(t_rel * OMEGA, AXIS)) * R0


def make_poses(
    n: int = 151, dt: float = 1 / 30, *, gaps: list[tuple[float, float]] = (), t0: float = T0
) -> Trajectory:
    t_rel = np.arange(n) * dt
    p, r = truth(t_rel)
    p = p.copy()
    for a, b in gaps:
        p[(t_rel >= a) & (t_rel <= b)] = np.nan
    sigma = 0.005 + 0.001 * t_rel
    markers = (np.arange(n) % 5) + 1
    return Trajectory.from_rotation(t0 + t_rel, p, r, {"sigma_m": sigma, "markers": markers})


def to_ns(t_rel: np.ndarray, t0: float = T0) -> np.ndarray:
    return int(t0 * 1e9) + np.round(t_rel * 1e9).astype(np.int64)


def test_labels_equal_truth_inside_the_span() -> None:
    rng = np.random.default_rng(0)
    poses = make_poses()
    t_rel = np.sort(rng.uniform(0.0, 5.0, 500))
    labels = label_readings(poses, to_ns(t_rel))
    assert labels.labelled.all()
    p, r = truth(t_rel)
    np.testing.assert_allclose(labels.positions, p, atol=1e-6)
    np.testing.assert_allclose(labels.rotations, r.as_matrix(), atol=1e-6)
    assert labels.counts["labelled"] == 500


def test_rotations_are_true_rotations() -> None:
    rng = np.random.default_rng(1)
    labels = label_readings(make_poses(), to_ns(rng.uniform(0.0, 5.0, 300)))
    R = labels.rotations
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max()
    assert err < 1e-9
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_nothing_outside_the_span_is_labelled() -> None:
    poses = make_poses(n=31)  # 0 .. 1.0 s
    t_rel = np.array([-0.5, -1e-6, 0.0, 0.5, 1.0, 1.0 + 1e-6, 3.0])
    labels = label_readings(poses, to_ns(t_rel))
    assert labels.reason.tolist() == [
        BEFORE_SPAN,
        BEFORE_SPAN,
        LABELLED,
        LABELLED,
        LABELLED,
        AFTER_SPAN,
        AFTER_SPAN,
    ]
    assert np.isnan(labels.positions[~labels.labelled]).all()
    assert np.isnan(labels.rotations[~labels.labelled]).all()
    # The span ends are the poses themselves, exactly.
    np.testing.assert_allclose(labels.positions[2], poses.position[0], atol=1e-12)
    np.testing.assert_allclose(labels.positions[4], poses.position[-1], atol=1e-9)


def test_gaps_longer_than_the_threshold_are_not_labelled() -> None:
    poses = make_poses(n=151, gaps=[(1.0, 2.0), (3.0, 3.2)])  # a 1.07 s and a 0.27 s hole
    t_rel = np.array([0.5, 1.2, 1.5, 1.95, 3.1, 4.0])
    labels = label_readings(poses, to_ns(t_rel), max_gap=0.5)
    assert labels.reason.tolist() == [LABELLED, IN_GAP, IN_GAP, IN_GAP, LABELLED, LABELLED]
    p, _ = truth(t_rel)
    np.testing.assert_allclose(labels.positions[labels.labelled], p[labels.labelled], atol=1e-6)
    assert labels.gap_s[3] == pytest.approx(2.0 + 1 / 30 - 1.95, abs=1e-3)
    assert tracked_span_coverage(labels) == pytest.approx(3 / 6)
    # A looser threshold bridges the big hole too (still interpolating, never extrapolating).
    assert label_readings(poses, to_ns(t_rel), max_gap=1.5).labelled.all()


def test_quality_columns() -> None:
    poses = make_poses(n=31)
    t_rel = np.array([0.0, 0.01, 0.5 + 1 / 60 - 0.001, 1 / 30 * 7])
    labels = label_readings(poses, to_ns(t_rel))
    np.testing.assert_allclose(labels.sigma, 0.005 + 0.001 * t_rel, atol=1e-9)
    # markers: those of the nearest pose (frame k uses k % 5 + 1)
    assert labels.markers.tolist() == [1, 1, (15 % 5) + 1, (7 % 5) + 1]
    np.testing.assert_allclose(labels.gap_s, [0.0, 0.01, 1 / 60 - 0.001, 0.0], atol=1e-6)


def test_nan_rotation_row_is_a_gap_and_duplicates_are_ignored() -> None:
    poses = make_poses(n=31)
    rot = poses.rotation.copy()
    rot[10] = np.nan
    t = poses.t.copy()
    t[20] = t[19]  # a duplicated timestamp
    p2 = Trajectory(t, poses.position, rot)
    labels = label_readings(p2, to_ns(np.array([10 / 30, 0.2])))
    assert labels.labelled.all()
    p, _ = truth(np.array([10 / 30, 0.2]))
    np.testing.assert_allclose(labels.positions, p, atol=1e-6)
    assert (labels.markers == -1).all()
    assert np.isnan(labels.sigma).all()


def test_no_poses_labels_nothing() -> None:
    poses = make_poses(n=5, gaps=[(-1.0, 10.0)])
    labels = label_readings(poses, to_ns(np.array([0.01, 0.05])))
    assert not labels.labelled.any()


def test_cover_events_are_excluded_and_not_counted_against_coverage() -> None:
    poses = make_poses(n=151)  # 0 .. 5 s
    t_rel = np.array([0.5, 1.0, 1.4, 2.0, 4.9, 6.0])
    labels = label_readings(poses, to_ns(t_rel), exclude=[(T0 + 0.9, T0 + 1.5), (T0 + 5.5, np.inf)])
    assert labels.reason.tolist() == [LABELLED, COVERED, COVERED, LABELLED, LABELLED, AFTER_SPAN]
    assert np.isnan(labels.positions[1:3]).all()
    assert labels.counts["during a cover event"] == 2
    assert tracked_span_coverage(labels) == 1.0


def test_the_summary_sentence_says_what_it_counts() -> None:
    """Readings in and out of the span, a gap and a cover, told apart in one sentence (issue 30:
    "100.0 % (3032 of 3358 readings)" read as a contradiction)."""
    poses = make_poses(n=151, gaps=[(3.0, 4.0)])  # 0 .. 5 s, no pose from 3 to 4 s
    t_rel = np.array([-1.0, 0.5, 1.0, 1.4, 2.0, 3.5, 4.9, 6.0, 7.0])
    labels = label_readings(poses, to_ns(t_rel), exclude=[(T0 + 0.9, T0 + 1.5)])
    text = describe_counts(labels.counts)
    assert text == (
        "labelled 3 of 4 readings inside the tracked span (1 in tracking gaps longer than the "
        "largest gap allowed); 5 left out (1 before it starts, 2 after it ends, 2 while the bundle "
        "was covered)"
    )
    # report.json's counts (underscores, plus totals) give the same sentence
    report = {k.replace(" ", "_"): v for k, v in labels.counts.items()} | {"readings_of_beacon": 9}
    assert describe_counts(report) == text
    everything = label_readings(poses, to_ns(np.array([0.5, 1.0])))
    assert describe_counts(everything.counts) == "labelled 2 of 2 readings inside the tracked span"


def test_sync_uncertainty_is_per_axis_like_the_trajectorys_sigma() -> None:
    """A clock error moves a label along the motion only: sigma (per axis) must give the 3-D error's
    mean square as 3 sigma^2, so the sync adds speed x time_sigma / sqrt(3) in quadrature (adding
    all of it to every axis claimed three times the variance; this fails at a ratio of ~0.34)."""
    from annotator.core.labeling import label_readings

    def circle(t: np.ndarray) -> np.ndarray:  # 1.5 m/s round a 2 m circle: the error turns too
        return np.stack([2 * np.cos(0.75 * t), 2 * np.sin(0.75 * t), np.ones_like(t)], 1)

    t = np.arange(0.0, 20.0, 0.05)
    pos = circle(t)
    rot = np.repeat(np.eye(3)[None], len(t), axis=0)
    poses = Trajectory(t, pos, rot, {"sigma_m": np.full(len(t), 1e-4)})
    rng = np.random.default_rng(3)
    t_true = rng.uniform(1.0, 19.0, 4000)
    ts = 0.01
    t_ns = np.round((t_true + rng.normal(0.0, ts, t_true.size)) * 1e9).astype(np.int64)
    plain = label_readings(poses, t_ns)
    synced = label_readings(poses, t_ns, time_sigma=ts)
    assert np.allclose(plain.sigma, 1e-4)
    assert np.allclose(synced.positions, plain.positions)
    err2 = np.sum((synced.positions - circle(t_true)) ** 2, axis=1)
    ratio = np.mean(err2) / np.mean(3 * synced.sigma**2)
    assert 0.9 < ratio < 1.1, ratio  # measured 1.0
    # 1.5 m/s x 10 ms along the motion, spread over three axes; the pose's own 0.1 mm beside it.
    assert np.allclose(synced.sigma, np.hypot(1e-4, 1.5 * ts / np.sqrt(3)), rtol=2e-3)
