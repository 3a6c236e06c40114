"""Method paper: per-marker poses, close-marker selection, greedy outlier elimination, random-walk KF."""

from __future__ import annotations

import numpy as np

from annotator.vision.paper import (
    MarkerPoses,
    PaperSettings,
    marker_poses,
    paper_track,
    select_poses,
)
from track_helpers import make_path, make_rig, make_room, project


def test_selection_keeps_close_markers_then_drops_the_farthest_from_the_mean():
    pos = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [1.0, 0, 0], [0, 0, 0.005], [5, 5, 5.0]])
    dist = np.array([1.0, 1.1, 1.2, 1.3, 1.4, 9.0])
    keep = select_poses(pos, dist, close=5, keep=4)
    assert sorted(keep.tolist()) == [0, 1, 2, 4]  # index 5 too far away, index 3 the outlier


def test_per_marker_poses_are_exact_without_noise():
    room, rig = make_room(), make_rig()
    _, pos, rot = make_path(30, 0.3)
    n = 0
    for k in range(len(pos)):
        for cam in rig.values():
            det = project(room, cam, rot[k].as_matrix(), pos[k], max_dist=4.0)
            mp = marker_poses(det, room, cam)
            near = mp.distance < 4.0
            if near.any():
                # IPPE_SQUARE picks the better of two mirror poses; noise-free, that is the true one.
                assert np.abs(mp.position[near] - pos[k]).max() < 0.02
                n += int(near.sum())
    assert n > 10


def make_frame(p: np.ndarray | None, distance: float = 2.0) -> MarkerPoses:
    """One frame's marker poses: a single pose at ``p`` (identity rotation), or none."""
    if p is None:
        return MarkerPoses(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
    return MarkerPoses(np.asarray(p, float)[None], np.eye(3)[None], np.array([distance]))


def two_cameras(n_front: int = 30, n_back: int = 30) -> tuple[np.ndarray, list[int]]:
    """Frame times of two 30 fps cameras half a frame apart, camera-major like the pipeline
    passes them, and each frame's rank in time (front k at k/30 s, back k at k/30 + 1/60 s)."""
    t = np.concatenate([np.arange(n_front) / 30, np.arange(n_back) / 30 + 1 / 60])
    rank = [2 * k for k in range(n_front)] + [2 * k + 1 for k in range(n_back)]
    return t, rank


def test_batches_count_frames_of_both_cameras_in_time_order_and_stamp_the_last():
    # 64 frames, 32 per camera: F = 15 closes 4 batches (0.25 s each); the last 4 frames never close one.
    t, rank = two_cameras(32, 32)
    # Each frame's pose is its rank in time, so a batch mean says exactly which frames it held.
    poses = [make_frame(np.full(3, 0.01 * r)) for r in rank]
    tb, x, R, used = paper_track(t, poses, PaperSettings(frames=15, close=15, keep=15))
    np.testing.assert_allclose(tb, np.array([14, 29, 44, 59]) / 60)
    assert used.tolist() == [15, 15, 15, 15]
    # Batch means 0.07, 0.22, 0.37, 0.52 (ranks 15b..15b+14) on every axis. Along (1,1,1) the
    # all-ones start P = J is a scalar filter with p0 = 3: gains 3.01/3.16 (x stays at the first
    # mean), then 0.15288/0.30288 = 0.504754, then 0.085713/0.235713 = 0.363633.
    x1 = 0.07 + 0.504754 * 0.15
    x2 = x1 + 0.363633 * (0.37 - x1)
    np.testing.assert_allclose(x[:3, 0], [0.07, x1, x2], atol=1e-6)
    np.testing.assert_allclose(x[:, 1], x[:, 0])
    np.testing.assert_allclose(R, np.repeat(np.eye(3)[None], 4, 0), atol=1e-12)


def test_frames_without_markers_count_and_an_empty_batch_is_a_nan_row():
    t, rank = two_cameras(30, 30)
    # The back camera sees nothing; the front one is blind in batch 1 (ranks 15..29).
    poses = [
        make_frame(None) if r % 2 or 15 <= r < 30 else make_frame([1.0, 2.0, 3.0]) for r in rank
    ]
    tb, x, _, used = paper_track(t, poses, PaperSettings(frames=15))
    np.testing.assert_allclose(tb, np.array([14, 29, 44, 59]) / 60)
    assert used.tolist() == [8, 0, 8, 7]  # the front frames (even ranks) of each batch of 15
    assert np.isnan(x[1]).all()
    np.testing.assert_allclose(x[[0, 2, 3]], np.tile([1.0, 2.0, 3.0], (3, 1)))


def test_all_ones_start_couples_the_axes_like_the_original():
    # A 0.1 m step in x at batch 1. Along (1,1,1) the gain is 0.504754 (as above); across it P
    # starts at 0, so p = 0.01 -> gain 0.0625 -> p = 0.009375, then 0.019375 -> gain 0.114391.
    # The x step splits into both: x moves 0.1 (k_u + 2 k_o) / 3, y and z 0.1 (k_u - k_o) / 3.
    t = np.arange(30) / 30
    poses = [
        make_frame([0.0, 0.0, 0.0]) if k < 15 else make_frame([0.1, 0.0, 0.0]) for k in range(30)
    ]
    _, x, _, _ = paper_track(t, poses, PaperSettings(frames=15))
    k_u, k_o = 0.504754, 0.114391
    np.testing.assert_allclose(
        x[1], 0.1 * np.array([k_u + 2 * k_o, k_u - k_o, k_u - k_o]) / 3, atol=1e-6
    )


def test_settings_change_the_filter_gain():
    t = np.arange(30) / 30
    poses = [
        make_frame([0.0, 0.0, 0.0]) if k < 15 else make_frame([0.3, 0.3, 0.3]) for k in range(30)
    ]
    # Along (1,1,1) with q = 1, process 0.5: p = 3.5 -> gain 3.5/4.5, p = 3.5/4.5 -> 1.277778 -> gain 0.560976.
    _, x, _, _ = paper_track(t, poses, PaperSettings(frames=15, q=1.0, process=0.5))
    np.testing.assert_allclose(x[1], np.full(3, 0.3 * 0.560976), atol=1e-6)


def test_fewer_frames_than_one_batch_give_no_rows():
    t = np.arange(14) / 30
    tb, x, R, used = paper_track(t, [make_frame([0.0, 0.0, 0.0])] * 14, PaperSettings(frames=15))
    assert tb.shape == (0,)
    assert x.shape == (0, 3)
    assert R.shape == (0, 3, 3)
    assert used.shape == (0,)


def test_random_walk_filter_converges_on_a_still_bundle():
    rng = np.random.default_rng(0)
    truth = np.array([5.0, 6.0, 1.5])
    t = np.arange(300) / 30
    poses = []
    for _ in t:
        p = truth + rng.normal(0, 0.05, (3, 3))
        poses.append(MarkerPoses(p, np.repeat(np.eye(3)[None], 3, 0), rng.uniform(1, 5, 3)))
    tb, x, R, used = paper_track(t, poses, PaperSettings())
    assert len(tb) == 20  # 300 frames in batches of 15
    np.testing.assert_allclose(tb, t[14::15])
    assert np.linalg.norm(x[-1] - truth) < 0.02
    assert used.max() == 10  # U poses survive each batch of 45
    assert np.allclose(R[-1], np.eye(3))


def test_track_cli_refuses_bad_paper_settings(tmp_path):
    from typer.testing import CliRunner

    from annotator.cli import app

    res = CliRunner().invoke(
        app,
        [
            "track",
            str(tmp_path / "experiment.yaml"),
            "--out",
            str(tmp_path / "o"),
            "--method",
            "paper",
            "--close",
            "5",
            "--keep",
            "6",
        ],
    )
    assert res.exit_code == 1
    assert "1 <= --keep <= --close" in res.output
    assert "Traceback" not in res.output
