"""Bundle pose from projected marker corners of known poses: accuracy, gating, ambiguity."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.vision.detection import Detections
from annotator.vision.pose import observe, solve_bundle_pose
from track_helpers import make_calibration, make_path, make_rig, make_room, project


def _observations(room, rig, R, p, noise, rng, cams=("front", "back")):
    out = []
    for name in cams:
        cam = rig[name]
        det = project(room, cam, R, p, noise, rng)
        out.append(observe(det, room, cam.calibration, cam.R_bundle_camera, cam.t_bundle_camera))
    return out


def test_joint_solve_recovers_known_poses_to_millimetres():
    room, rig, rng = make_room(), make_rig(), np.random.default_rng(3)
    _, pos, rot = make_path(120, 0.1)
    err, ang, z2 = [], [], []
    for k in range(len(pos)):
        pose = solve_bundle_pose(
            _observations(room, rig, rot[k].as_matrix(), pos[k], 0.3, rng), room
        )
        assert pose is not None
        e = pose.t_wb - pos[k]
        err.append(np.linalg.norm(e))
        ang.append(np.degrees((Rotation.from_matrix(pose.R_wb) * rot[k].inv()).magnitude()))
        z2.append(e @ np.linalg.solve(pose.cov[3:, 3:], e))
        assert np.allclose(pose.R_wb.T @ pose.R_wb, np.eye(3), atol=1e-9)
    assert np.median(err) < 0.004
    assert np.percentile(err, 95) < 0.012
    assert np.median(ang) < 0.05
    # The covariance means something: normalised squared errors average ~3 for 3-d (allow 0.3..10).
    assert 0.3 < np.mean(z2) < 10


def test_two_cameras_beat_one():
    room, rig, rng = make_room(), make_rig(), np.random.default_rng(4)
    _, pos, rot = make_path(80, 0.15)
    both, front = [], []
    for k in range(len(pos)):
        obs = _observations(room, rig, rot[k].as_matrix(), pos[k], 0.5, rng)
        if not (len(obs[0].ids) >= 2 and len(obs[1].ids) >= 2):
            continue
        both.append(np.linalg.norm(solve_bundle_pose(obs, room).t_wb - pos[k]))
        front.append(np.linalg.norm(solve_bundle_pose(obs[:1], room).t_wb - pos[k]))
    assert len(both) > 20
    assert np.median(both) < np.median(front)


def test_a_marker_with_wrong_corners_is_dropped():
    room, rig, rng = make_room(), make_rig(), np.random.default_rng(5)
    _, pos, rot = make_path(120, 0.2)
    checked = 0
    for k in range(len(pos)):
        cam = rig["front" if k % 2 else "back"]
        det = project(room, cam, rot[k].as_matrix(), pos[k], 0.2, rng)
        if len(det.ids) < 3:
            continue
        corners = det.corners.copy()
        # One marker's corners warped in a way no pose explains (a mis-detection, a reflection).
        corners[0] += np.array([[9.0, 0.0], [0.0, 9.0], [-9.0, 0.0], [0.0, -9.0]])
        obs = observe(
            Detections(det.ids, corners),
            room,
            cam.calibration,
            cam.R_bundle_camera,
            cam.t_bundle_camera,
        )
        pose = solve_bundle_pose([obs], room)
        assert pose.n_markers == len(det.ids) - 1
        # Same answer as never having seen the bad marker.
        clean = solve_bundle_pose(
            [
                observe(
                    Detections(det.ids[1:], det.corners[1:]),
                    room,
                    cam.calibration,
                    cam.R_bundle_camera,
                    cam.t_bundle_camera,
                )
            ],
            room,
        )
        assert np.allclose(pose.t_wb, clean.t_wb, atol=1e-5)
        assert pose.rms_px < 1.0
        checked += 1
    assert checked >= 5


def test_single_marker_returns_both_mirror_solutions_one_of_them_true():
    room, rig = make_room(), make_rig()
    cam = rig["front"]
    # Stand 2.5 m in front of marker 1 (on a wall facing -y at y = 5.59), looking at it obliquely.
    p = np.array([6.3, 3.2, 1.6])
    R = Rotation.from_euler("z", 80, degrees=True).as_matrix()
    det = project(room, cam, R, p)
    keep = det.ids == 1
    assert keep.any()
    obs = observe(
        Detections(det.ids[keep], det.corners[keep]),
        room,
        cam.calibration,
        cam.R_bundle_camera,
        cam.t_bundle_camera,
    )
    pose = solve_bundle_pose([obs], room)
    assert pose.n_markers == 1
    cands = [pose, *pose.alternatives]
    assert len(cands) == 2
    best = min(np.linalg.norm(c.t_wb - p) for c in cands)
    assert best < 0.005
    # A single square's position is far less certain than several markers' (inflated covariance).
    assert np.sqrt(np.trace(pose.cov[3:, 3:])) > 0.005


def test_nothing_seen_gives_none():
    room, rig = make_room(), make_rig()
    cam = rig["front"]
    obs = observe(
        Detections.empty(), room, cam.calibration, cam.R_bundle_camera, cam.t_bundle_camera
    )
    assert solve_bundle_pose([obs], room) is None


@pytest.mark.parametrize("offset", [np.array([0.02, -0.01, 0.03])])
def test_motion_compensated_extrinsics_match_the_moved_camera(offset):
    """Observations from a slightly later time, with the motion folded into the extrinsics, agree."""
    room, rig, rng = make_room(), make_rig(make_calibration()), np.random.default_rng(6)
    _, pos, rot = make_path(10, 0.3)
    R0, p0 = rot[5].as_matrix(), pos[5]
    dR = Rotation.from_euler("z", 1.5, degrees=True).as_matrix()
    R1, p1 = R0 @ dR, p0 + offset  # the bundle a moment later
    back = rig["back"]
    det = project(room, back, R1, p1, 0.0, rng)
    R_d, t_d = R0.T @ R1, R0.T @ (p1 - p0)
    obs_b = observe(
        det, room, back.calibration, R_d @ back.R_bundle_camera, R_d @ back.t_bundle_camera + t_d
    )
    obs_f = _observations(room, rig, R0, p0, 0.0, rng, cams=("front",))[0]
    pose = solve_bundle_pose([obs_f, obs_b], room)
    assert np.linalg.norm(pose.t_wb - p0) < 1e-4
