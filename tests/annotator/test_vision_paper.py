"""Method paper: per-marker poses, close-marker selection, greedy outlier elimination, random-walk KF."""

from __future__ import annotations

import numpy as np
from _track_helpers import make_path, make_rig, make_room, project

from annotator.vision.paper import (
    MarkerPoses,
    PaperSettings,
    marker_poses,
    paper_track,
    select_poses,
)


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


def test_random_walk_filter_converges_on_a_still_bundle():
    rng = np.random.default_rng(0)
    truth = np.array([5.0, 6.0, 1.5])
    t = np.arange(300) / 30
    poses = []
    for _ in t:
        p = truth + rng.normal(0, 0.05, (3, 3))
        poses.append(MarkerPoses(p, np.repeat(np.eye(3)[None], 3, 0), rng.uniform(1, 5, 3)))
    tb, x, R, used = paper_track(t, poses, 1 / 30, PaperSettings())
    assert len(tb) == 20  # 300 frames in batches of 15
    assert np.allclose(np.diff(tb), 0.5)
    assert np.linalg.norm(x[-1] - truth) < 0.02
    assert used.max() == 10  # U poses survive each batch of 45
    assert np.allclose(R[-1], np.eye(3))
