"""Propagated parameter uncertainty of a pose against the Monte-Carlo spread of real pose solves,
and the motion-blur measure against the image speed of a known motion."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.experiment import CameraCalibration, Experiment, MarkerSetup, Rig
from annotator.core.priors import PRINTED_SCALE, ParameterCovariance, Priors
from annotator.core.uncertainty import (
    BLOCKS,
    FrameView,
    JacobianCache,
    UncertaintySettings,
    condition_on_rest,
    frame_jacobians,
    image_speed,
    propagate,
    row_uncertainty,
    sigma_budget,
    smear_weights,
)
from annotator.vision.detection import Detections
from annotator.vision.geometry import MarkerRoom, marker_corners_local
from annotator.vision.lens import undistort_points
from annotator.vision.pose import observe, solve_bundle_pose
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir
from track_helpers import make_path, make_rig, make_room, project

READOUT_SIGMA = 0.02


def _scene(k: int = 7):
    """Room, rig, and a pose where both cameras see several markers (exact corners)."""
    room, rig = make_room(), make_rig()
    _, pos, rot = make_path(200, 0.1)
    for i in range(k, len(pos)):
        R, p = rot[i].as_matrix(), pos[i]
        dets = {n: project(room, cam, R, p) for n, cam in rig.items()}
        if all(len(d.ids) >= 2 for d in dets.values()):
            return room, rig, R, p, dets
    raise AssertionError("no pose sees markers with both cameras")


def _views(room, rig, R, p, dets, twist=None):
    twist = np.zeros(6) if twist is None else twist
    return [
        FrameView(
            n,
            cam.calibration,
            cam.R_bundle_camera,
            cam.t_bundle_camera,
            dets[n].ids,
            dets[n].corners,
            R,
            p,
            twist,
        )
        for n, cam in rig.items()
    ]


def _params(room, rig) -> ParameterCovariance:
    return ParameterCovariance.from_priors(
        Priors(),
        [int(i) for i in room.ids],
        {n: c.calibration.camera_matrix for n, c in rig.items()},
    )


def _experiment(room: MarkerRoom, rig) -> Experiment:  # noqa: ANN001 - track_helpers' rig
    """The tetam map and this rig as an experiment (no videos, the default priors)."""
    return Experiment(
        Path("experiment.yaml"),
        MarkerSetup(read_marker_map(site_dir("tetam") / "marker_positions.dat"), "", room.length),
        Rig(rig),
        {},
        None,
        None,
    )


def _propagated(room, rig, R, p, dets, twist=None, params=None) -> dict[str, float]:
    jac = frame_jacobians(
        _views(room, rig, R, p, dets, twist),
        room,
        params or _params(room, rig),
        READOUT_SIGMA,
        UncertaintySettings(),
    )
    var, *_ = propagate(jac)
    return dict(zip(BLOCKS, np.sqrt(var), strict=True))  # per-axis 1-sigma, m


def _solve(room, rig, dets, R, p, cams=None, cals=None):
    obs = []
    for n, cam in rig.items():
        R_bc, t_bc = (cam.R_bundle_camera, cam.t_bundle_camera) if cams is None else cams[n]
        cal = cam.calibration if cals is None else cals[n]
        obs.append(observe(dets[n], room, cal, R_bc, t_bc))
    pose = solve_bundle_pose(obs, room, prior=(R, p))
    assert pose is not None
    return pose.t_wb


def _per_axis(errors: list[np.ndarray]) -> float:
    e = np.array(errors)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)) / 3))


def _perturbed_room(
    room: MarkerRoom, cov: dict[int, np.ndarray], rng: np.random.Generator
) -> MarkerRoom:
    Rs, ts = [], []
    for i, mid in enumerate(room.ids):
        d = rng.multivariate_normal(np.zeros(6), cov[int(mid)])
        Rs.append(Rotation.from_rotvec(d[:3]).as_matrix() @ room.R_world_marker[i])
        ts.append(room.t_world_marker[i] + d[3:])
    R, t = np.array(Rs), np.array(ts)
    corners = np.einsum("mij,kj->mki", R, marker_corners_local(room.length)) + t[:, None, :]
    return MarkerRoom(room.ids, R, t, corners, room.length)


N_DRAWS = 200


def test_marker_map_sigma_matches_the_spread_of_solves():
    room, rig, R, p, dets = _scene()
    want = _propagated(room, rig, R, p, dets)["markers"]
    rng = np.random.default_rng(1)
    cov = _params(room, rig).markers
    errs = [_solve(_perturbed_room(room, cov, rng), rig, dets, R, p) - p for _ in range(N_DRAWS)]
    assert want == pytest.approx(_per_axis(errs), rel=0.2)
    assert want > 0.002  # not vacuous: a 1 cm survey moves the pose by millimetres


def test_rig_sigma_matches_the_spread_of_solves():
    room, rig, R, p, dets = _scene()
    want = _propagated(room, rig, R, p, dets)["rig"]
    rng = np.random.default_rng(2)
    cov = _params(room, rig).rig
    errs = []
    for _ in range(N_DRAWS):
        cams = {}
        for n, cam in rig.items():
            d = rng.multivariate_normal(np.zeros(6), cov[n])
            cams[n] = (
                Rotation.from_rotvec(d[:3]).as_matrix() @ cam.R_bundle_camera,
                cam.t_bundle_camera + d[3:],
            )
        errs.append(_solve(room, rig, dets, R, p, cams=cams) - p)
    assert want == pytest.approx(_per_axis(errs), rel=0.2)
    assert want > 0.002


def test_intrinsics_sigma_matches_the_spread_of_solves():
    """With fx and fy strongly correlated, as a calibration's are (a full covariance is used)."""
    room, rig, R, p, dets = _scene()
    base = _params(room, rig)
    cov = {}
    for n, c in base.intrinsics.items():
        full = c.copy()
        full[0, 1] = full[1, 0] = 0.95 * np.sqrt(c[0, 0] * c[1, 1])
        cov[n] = full
    want = _propagated(
        room, rig, R, p, dets, params=ParameterCovariance(base.markers, base.rig, cov)
    )["intrinsics"]
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(N_DRAWS):
        cals = {}
        for n, cam in rig.items():
            c = cam.calibration
            d = rng.multivariate_normal(np.zeros(4), cov[n])
            K = c.camera_matrix.copy()
            K[0, 0] += d[0]
            K[1, 1] += d[1]
            K[0, 2] += d[2]
            K[1, 2] += d[3]
            cals[n] = CameraCalibration(K, c.dist_coeffs, c.width, c.height, c.source, c.model)
        errs.append(_solve(room, rig, dets, R, p, cals=cals) - p)
    assert want == pytest.approx(_per_axis(errs), rel=0.2)
    assert want > 0.001


def test_readout_sensitivity_matches_a_rolling_shutter_render():
    """Corners seen row by row while the bundle turns and walks: the solve's error is what the
    readout column predicts."""
    room, rig, R, p, _ = _scene()
    omega, vel = np.array([0.0, 0.0, 0.8]), np.array([0.5, -0.3, 0.0])
    readout = 0.01

    def pose_at(dt):
        return Rotation.from_rotvec(omega * dt).as_matrix() @ R, p + vel * dt

    dets = {}
    for n, cam in rig.items():
        det = project(room, cam, R, p)
        corners = det.corners.copy()
        for _ in range(3):  # each corner where the bundle was when its row was read
            for i in range(len(det.ids)):
                for c in range(4):
                    Rt, pt = pose_at(readout * corners[i, c, 1] / cam.calibration.height)
                    moved = project(room, cam, Rt, pt)
                    j = np.flatnonzero(moved.ids == det.ids[i])
                    if len(j):
                        corners[i, c] = moved.corners[j[0], c]
        dets[n] = Detections(det.ids, corners)
    err = np.linalg.norm(_solve(room, rig, dets, R, p) - p)
    predicted = (
        np.sqrt(3) * _propagated(room, rig, R, p, dets, np.concatenate([omega, vel]))["readout"]
    )
    predicted *= readout / READOUT_SIGMA
    assert err > 0.002
    assert predicted == pytest.approx(err, rel=0.2)


def test_image_speed_of_a_sideways_walk_is_focal_times_speed_over_depth():
    room, rig, R, p, dets = _scene()
    cam = rig["front"]
    # Move along the front camera's x axis (in the world): pure sideways motion for that camera.
    side = R @ cam.R_bundle_camera[:, 0]
    v = 0.8
    view = _views(room, rig, R, p, dets, np.concatenate([np.zeros(3), v * side]))[0]
    speed = image_speed(view, room)
    idx = room.index(dets["front"].ids)
    c_w = R @ cam.t_bundle_camera + p
    depth = ((room.corners_world[idx].reshape(-1, 3) - c_w) @ (R @ cam.R_bundle_camera))[:, 2]
    f = np.sqrt(cam.calibration.camera_matrix[0, 0] * cam.calibration.camera_matrix[1, 1])
    assert speed == pytest.approx(f * v / depth, rel=0.01)


def test_smear_weights_keep_sharp_frames_and_drop_smeared_ones():
    w = smear_weights(np.array([0.0, 5.0, 10.0, 20.0, 29.0, 31.0, np.nan]), 10.0)
    assert w[:3].tolist() == [1.0, 1.0, 1.0]
    assert w[3] == pytest.approx(4.0)
    assert w[4] == pytest.approx(8.41)
    assert np.isinf(w[5])
    assert w[6] == 1.0


def test_a_correlated_covariance_is_propagated_as_a_whole():
    """A rank-one intrinsics covariance (the front camera's focal lengths off together by 1 px): the
    propagated sigma is the pose change that exact error causes, not what independent fx and fy
    errors would give. (The record has no covariance between cameras: the back one is exact.)"""
    room, rig, R, p, dets = _scene()
    base = _params(room, rig)
    v = np.array([1.0, 1.0, 0.0, 0.0])
    zero = np.zeros((4, 4))
    params = ParameterCovariance(base.markers, base.rig, {"front": np.outer(v, v), "back": zero})
    want = _propagated(room, rig, R, p, dets, params=params)["intrinsics"]
    cals = {n: cam.calibration for n, cam in rig.items()}
    c = cals["front"]
    K = c.camera_matrix.copy()
    K[0, 0] += v[0]
    K[1, 1] += v[1]
    cals["front"] = CameraCalibration(K, c.dist_coeffs, c.width, c.height, c.source, c.model)
    moved = np.linalg.norm(_solve(room, rig, dets, R, p, cals=cals) - p) / np.sqrt(3)
    assert want == pytest.approx(moved, rel=0.05)
    diag_only = ParameterCovariance(base.markers, base.rig, {"front": np.diag(v**2), "back": zero})
    assert _propagated(room, rig, R, p, dets, params=diag_only)["intrinsics"] != pytest.approx(
        want, rel=0.1
    )


def test_calibration_exposure_is_optional_and_checked():
    from annotator.errors import ConfigError
    from annotator.io.experiment import parse_calibration

    d = {
        "camera_matrix": [[600.0, 0, 480], [0, 601.0, 270], [0, 0, 1]],
        "image_width": 960,
        "image_height": 540,
        "distortion_coefficients": [0.0, 0.0, 0.0, 0.0, 0.0],
    }
    assert parse_calibration(d, "cam.yaml").exposure_s is None
    assert parse_calibration({**d, "exposure_s": 0.008}, "cam.yaml").exposure_s == 0.008
    with pytest.raises(ConfigError, match="exposure_s must be between"):
        parse_calibration({**d, "exposure_s": -0.001}, "cam.yaml")
    with pytest.raises(ConfigError, match="exposure_s must be a number"):
        parse_calibration({**d, "exposure_s": "fast"}, "cam.yaml")


def test_distortion_covariance_from_a_refined_record_is_propagated():
    """A record with distortion covariances (as refinement writes them): a k1 error of the front
    lens moves the pose as predicted; a record without them leaves distortion out."""
    from types import SimpleNamespace

    room, rig, R, p, dets = _scene()
    base = _params(room, rig)
    dk = 0.004
    dist_cov = np.zeros((5, 5))
    dist_cov[0, 0] = dk**2
    zero4 = np.zeros((4, 4))
    record = SimpleNamespace(
        markers=base.markers,
        rig=base.rig,
        intrinsics={"front": zero4, "back": zero4},
        distortion={"front": dist_cov},
        readout={},
    )
    want = _propagated(room, rig, R, p, dets, params=record)["intrinsics"]
    cals = {n: cam.calibration for n, cam in rig.items()}
    c = cals["front"]
    d = c.dist_coeffs.copy()
    d[0] += dk
    cals["front"] = CameraCalibration(c.camera_matrix, d, c.width, c.height, c.source, c.model)
    moved = np.linalg.norm(_solve(room, rig, dets, R, p, cals=cals) - p) / np.sqrt(3)
    assert moved > 1e-4
    assert want == pytest.approx(moved, rel=0.1)
    without = SimpleNamespace(
        markers=base.markers, rig=base.rig, intrinsics={"front": zero4, "back": zero4}
    )
    assert _propagated(room, rig, R, p, dets, params=without)["intrinsics"] == 0.0


def test_rows_sharing_a_cache_get_what_each_gets_alone():
    """Rows of one capture share a JacobianCache (views, covariance roots, moved lenses): each
    row's Jacobians are those it gets without one; the intrinsics columns are central differences
    of the undistortion under a camera matrix moved by a tenth of each sigma."""
    room, rig, R, p, dets = _scene()
    params = _params(room, rig)
    views = _views(room, rig, R, p, dets, np.array([0.1, -0.2, 0.3, 0.2, 0.1, -0.1]))
    rows = [views, views[:1], views[1:]]
    cache = JacobianCache()
    s = UncertaintySettings()
    for row in rows:
        shared = frame_jacobians(row, room, params, READOUT_SIGMA, s, cache)
        alone = frame_jacobians(row, room, params, READOUT_SIGMA, s)
        assert shared is not None
        assert alone is not None
        np.testing.assert_array_equal(shared.J, alone.J)
        for b in alone.B:
            np.testing.assert_array_equal(shared.B[b], alone.B[b])
            np.testing.assert_array_equal(shared.L[b], alone.L[b])
    assert len(cache.views) == 2  # each view worked out once
    assert cache.roots

    v = views[0]
    K = v.cal.camera_matrix
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    steps = np.sqrt(np.diag(params.intrinsics[v.camera])) * 0.1
    jac = frame_jacobians([v], room, params, READOUT_SIGMA, s)
    assert jac is not None
    for j, at in enumerate(((0, 0), (1, 1), (0, 2), (1, 2))):
        Kp, Km = K.copy(), K.copy()
        Kp[at] += steps[j]
        Km[at] -= steps[j]
        moved = [
            undistort_points(
                CameraCalibration(Kx, v.cal.dist_coeffs, v.cal.width, v.cal.height), v.pixels
            )
            for Kx in (Kp, Km)
        ]
        want = -focal * ((moved[0] - moved[1]) / (2 * steps[j])).reshape(-1)
        got = jac.B["intrinsics"][:, j]
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())


def test_rows_propagated_in_a_process_pool_get_what_one_process_gives():
    """``row_uncertainty`` with a pool splits the rows into runs for its processes: every column
    comes out exactly as in one process, with the priors (checked against the residuals over all
    rows) and with a refined joint record."""
    room, rig = make_room(), make_rig()
    t, pos, rot = make_path(120, 1 / 30)
    R = rot.as_matrix()
    rng = np.random.default_rng(3)
    frames = [
        SimpleNamespace(
            camera=n,
            t=t,
            detections=[project(room, cam, R[i], pos[i], 0.3, rng) for i in range(len(t))],
            frame_interval=1 / 30,
        )
        for n, cam in rig.items()
    ]
    exp = _experiment(room, rig)
    for record in (None, _map_record(room, rig, common_m=0.01, own_m=0.002)):
        alone = row_uncertainty(frames, exp, t, pos, R, record)
        with ProcessPoolExecutor(max_workers=2) as pool:
            pooled = row_uncertainty(frames, exp, t, pos, R, record, pool=pool, jobs=2)
        assert np.isfinite(alone.params_var).all(1).mean() > 0.9
        np.testing.assert_array_equal(pooled.params_var, alone.params_var)
        np.testing.assert_array_equal(pooled.smear_px, alone.smear_px)
        np.testing.assert_array_equal(pooled.blur_m, alone.blur_m)
        assert pooled.scales == alone.scales


def _map_record(room, rig, common_m: float, own_m: float) -> ParameterCovariance:
    """A refined-like record whose markers share one position error (the map's datum, common_m per
    axis) on top of their own (own_m): cross-covariances between every pair of markers."""
    ids = [int(i) for i in room.ids]
    n = len(ids)
    joint = np.zeros((6 * n, 6 * n))
    pos = np.concatenate([6 * k + np.arange(3, 6) for k in range(n)])
    joint[np.ix_(pos, pos)] = common_m**2 * np.tile(np.eye(3), (n, n))
    joint += np.diag(np.tile([np.radians(0.1) ** 2] * 3 + [own_m**2] * 3, n))
    zero = {name: np.zeros((6, 6)) for name in rig}
    return ParameterCovariance(
        markers={m: joint[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] for k, m in enumerate(ids)},
        rig=zero,
        intrinsics={name: np.zeros((4, 4)) for name in rig},
        joint=joint,
        joint_index={("markers", m): np.arange(6 * k, 6 * k + 6) for k, m in enumerate(ids)},
    )


def _map_sigma(room, rig, R, p, dets, record, joint: bool) -> float:
    jac = frame_jacobians(
        _views(room, rig, R, p, dets),
        room,
        record,
        0.0,
        UncertaintySettings(joint_covariance=joint),
    )
    var, *_ = propagate(jac)
    return float(np.sqrt(var.sum()))


def test_a_map_error_shared_by_every_marker_is_not_averaged_away():
    """The refinement's markers share the error of the map's datum (where the survey puts the map
    as a whole): the pose follows it in full, however many markers a frame sees. The joint record
    predicts the spread of real solves over maps drawn from it; the markers' marginals taken as
    independent do not (each marker's centimetre then also turns the pose, which a shared shift
    does not)."""
    room, rig, R, p, dets = _scene()
    record = _map_record(room, rig, common_m=0.01, own_m=0.002)
    want = _map_sigma(room, rig, R, p, dets, record, joint=True)
    rng = np.random.default_rng(5)
    errs = []
    for _ in range(N_DRAWS):
        d = rng.multivariate_normal(np.zeros(len(record.joint)), record.joint).reshape(-1, 6)
        Rs = Rotation.from_rotvec(d[:, :3]).as_matrix() @ room.R_world_marker
        ts = room.t_world_marker + d[:, 3:]
        corners = np.einsum("mij,kj->mki", Rs, marker_corners_local(room.length)) + ts[:, None]
        moved = MarkerRoom(room.ids, Rs, ts, corners, room.length)
        errs.append(_solve(moved, rig, dets, R, p) - p)
    spread = _per_axis(errs)
    assert want == pytest.approx(spread, rel=0.15)
    assert want > 0.009  # the shared centimetre, in full
    assert _map_sigma(room, rig, R, p, dets, record, joint=False) != pytest.approx(spread, rel=0.2)


def test_the_printed_size_s_uncertainty_moves_the_pose_as_a_misprinted_map_does():
    """A refined record whose markers' printed size is known to 0.3 %: the pose's sigma from it
    matches the spread of solves whose markers are all printed that much off (the corners move
    along each marker's own face, so the camera's distance to every marker changes; with markers
    on every side most of it cancels, leaving a tenth of a millimetre here). A record without
    the printed size's row leaves that part out."""
    room, rig, R, p, dets = _scene()
    base = _map_record(room, rig, common_m=0.0, own_m=1e-6)
    n = len(base.joint)
    joint = np.zeros((n + 1, n + 1))
    joint[:n, :n] = base.joint
    sigma_scale = 0.003
    joint[n, n] = sigma_scale**2
    index = dict(base.joint_index) | {PRINTED_SCALE: np.array([n])}
    record = ParameterCovariance(
        base.markers, base.rig, base.intrinsics, joint=joint, joint_index=index
    )
    want = _map_sigma(room, rig, R, p, dets, record, joint=True)
    rng = np.random.default_rng(11)
    errs = []
    for ds in sigma_scale * rng.standard_normal(N_DRAWS):
        length = room.length * (1 + ds)
        corners = (
            np.einsum("mij,kj->mki", room.R_world_marker, marker_corners_local(length))
            + room.t_world_marker[:, None]
        )
        printed = MarkerRoom(room.ids, room.R_world_marker, room.t_world_marker, corners, length)
        errs.append(_solve(printed, rig, dets, R, p) - p)
    spread = _per_axis(errs)
    assert spread > 5e-5  # not vacuous
    without = _map_sigma(room, rig, R, p, dets, base, joint=True)  # the markers' own 0.1 deg
    assert without < want
    assert np.sqrt(want**2 - without**2) == pytest.approx(spread, rel=0.15)


def test_a_rest_at_a_known_pose_takes_out_what_it_pins():
    """A still bundle whose pose is known to 1 mm / 0.1 deg (a jig) conditions the record: the map's
    datum, shared by every marker, is what it pins, so the pose's sigma at the rest drops from the
    datum's centimetre to about the jig's millimetre. Without a joint record nothing changes."""
    room, rig, R, p, dets = _scene()
    record = _map_record(room, rig, common_m=0.01, own_m=0.002)
    exp = _experiment(room, rig)
    t = np.arange(3) / 30.0  # three frames at 30 fps
    frames = [
        SimpleNamespace(camera=n, t=t, detections=[dets[n]] * 3, frame_interval=1 / 30) for n in rig
    ]
    rows = np.ones(3, bool)
    var = np.array([np.radians(0.1) ** 2] * 3 + [0.001**2] * 3)
    after = condition_on_rest(
        frames, exp, t, np.tile(p, (3, 1)), np.tile(R, (3, 1, 1)), record, rows, var
    )
    before_m = _map_sigma(room, rig, R, p, dets, record, joint=True)
    after_m = _map_sigma(room, rig, R, p, dets, after, joint=True)
    assert before_m > 0.009
    assert 0.0003 < after_m < 0.0012
    # The datum (the markers' common shift) is what went: each marker keeps its own 2 mm.
    own = np.sqrt(np.diag(after.joint)[3::6])
    assert np.all(own > 0.0015)
    assert np.all(own < np.sqrt(np.diag(record.joint)[3::6]))
    none = ParameterCovariance(record.markers, record.rig, record.intrinsics)
    pos, Rs = np.tile(p, (3, 1)), np.tile(R, (3, 1, 1))
    assert condition_on_rest(frames, exp, t, pos, Rs, none, rows, var) is none


def test_sigma_budget_summarises_the_posed_rows() -> None:
    nan = np.nan
    quality = {
        "sigma_m": np.array([0.005, 0.006, nan, 0.007, 0.010]),
        "sigma_params_m": np.array([0.004, 0.005, nan, 0.006, 0.009]),
        "sigma_smoother_m": np.array([0.002, 0.002, 0.5, 0.002, 0.003]),
        "markers": np.array([3, 3, 0, 4, 2]),
    }
    b = sigma_budget(quality)
    assert b is not None
    assert b.median_m == pytest.approx(0.0065)
    assert b.p95_m == pytest.approx(np.percentile([0.005, 0.006, 0.007, 0.010], 95))
    # Only the posed rows count (the unposed row's 0.5 m of smoother noise does not), and only
    # the parts the trajectory has.
    assert b.parts_m == pytest.approx({"sigma_params_m": 0.0055, "sigma_smoother_m": 0.002})
    assert b.largest == "sigma_params_m"
    assert sigma_budget({"sigma_m": np.full(3, nan)}) is None
    assert sigma_budget({"markers": np.ones(3)}) is None
