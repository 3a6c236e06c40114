"""The renderer's conditions beyond the field errors (issue 29): markers as printed, what a real
camera adds to the picture, and how the bundle is carried."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from annotator.render import LoopTrajectory, default_cameras
from annotator.render.camera import camera_pose
from annotator.render.conditions import IMAGING_PRESETS, resolve_imaging
from annotator.render.effects import CameraImaging, Imaging
from annotator.render.experiment import printed_scales
from annotator.render.frames import FrameRenderer
from annotator.render.trajectory import MOTION_PROFILES, PRESET_PATHS, PolylineTrajectory
from bgt_core.formats.markers import read_marker_map
from bgt_core.sites import site_dir
from tests.annotator.render.test_render import detect, make_detector

T0 = 1_700_000_000.0


def _sides(found: dict[int, np.ndarray]) -> dict[int, float]:
    return {
        m: float(np.mean(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1))) for m, c in found.items()
    }


def test_markers_printed_larger_look_larger_by_that_much() -> None:
    """A 2 % larger print makes every detected square 2 % larger (the camera cannot tell it
    from a marker 2 % nearer: what the files' `length` must be corrected for)."""
    markers = read_marker_map(site_dir() / "marker_positions.dat")
    cam = default_cameras()["front"]
    exact = FrameRenderer(cam, markers, 0.298, "DICT_6X6_50", noise_sigma=0.0, seed=1)
    scales = printed_scales(markers, 1.02, 0.0, seed=0)
    assert scales is not None
    assert set(scales.values()) == {1.02}
    large = FrameRenderer(
        cam, markers, 0.298, "DICT_6X6_50", noise_sigma=0.0, seed=1, marker_scales=scales
    )
    det = make_detector()
    ratios = []
    for t in T0 + np.arange(0.0, 30.0, 3.0):
        pos, rot = LoopTrajectory(t0=T0)(np.array([t]))
        r_wc, c_w = camera_pose(rot[0], pos[0], "front")
        a = _sides(detect(det, exact.render(r_wc.as_matrix(), c_w)))
        b = _sides(detect(det, large.render(r_wc.as_matrix(), c_w)))
        ratios += [b[m] / a[m] for m in a if m in b and a[m] > 40]
        expected = large.scene.expected_corners(cam, r_wc.as_matrix(), c_w)
        nominal = exact.scene.expected_corners(cam, r_wc.as_matrix(), c_w)
        for m in set(expected) & set(nominal):  # the projected squares: 2 % about the centre
            ce, cn = expected[m].mean(axis=0), nominal[m].mean(axis=0)
            np.testing.assert_allclose(
                np.linalg.norm(expected[m] - ce, axis=1),
                1.02 * np.linalg.norm(nominal[m] - cn, axis=1),
                rtol=0.01,
            )
    assert len(ratios) >= 5
    assert abs(np.median(ratios) - 1.02) < 0.004
    assert printed_scales(markers, 1.0, 0.0, seed=0) is None
    spread = printed_scales(markers, 1.0, 0.01, seed=0)
    assert spread is not None
    assert 0.005 < np.std(list(spread.values())) < 0.015
    with pytest.raises(ValueError, match="print scale"):
        printed_scales(markers, 3.0, 0.0, seed=0)


def test_imaging_darkens_the_corners_and_changes_with_time() -> None:
    im = CameraImaging(Imaging(vignetting=0.4), 960, 540, seed=0)
    gain = np.asarray(im.gain(0.0))
    assert gain.shape == (540, 960)
    assert gain[270, 480] == pytest.approx(1.0, abs=1e-3)
    assert gain[0, 0] == pytest.approx(0.6, abs=0.01)
    drift = CameraImaging(Imaging(light_change=0.1), 64, 48, seed=0)
    levels = [float(drift.gain(t)) for t in np.arange(0, 10, 0.1)]
    assert max(levels) == pytest.approx(1.1, abs=0.005)
    assert min(levels) == pytest.approx(0.9, abs=0.005)
    steps = CameraImaging(Imaging(exposure_steps=0.08), 64, 48, seed=0)
    per_slot = [float(steps.gain(t)) for t in (0.1, 2.9, 3.1, 5.9, 6.1)]
    assert per_slot[0] == per_slot[1]  # constant within a 3 s slot
    assert per_slot[2] == per_slot[3]
    assert len({per_slot[0], per_slot[2], per_slot[4]}) == 3
    assert all(0.92 <= g <= 1.08 for g in per_slot)


def test_real_imaging_blurs_and_compresses() -> None:
    rng = np.random.default_rng(0)
    img = np.zeros((96, 128), np.uint8)
    img[:, 64:] = 200
    im = CameraImaging(Imaging(defocus_px=1.5), 128, 96, seed=0)
    edge = im.optics(img, 0.0)[48, 58:70].astype(float)
    assert 0 < edge[5] < 200  # the step is spread over a few pixels
    assert np.count_nonzero((edge > 10) & (edge < 190)) >= 4
    noisy = cv2.cvtColor(
        np.clip(img + rng.normal(0, 5, img.shape), 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR
    )
    jpeg = CameraImaging(Imaging(jpeg_quality=30), 128, 96, seed=0).compress(noisy)
    assert jpeg.shape == noisy.shape
    assert 0 < np.abs(jpeg.astype(float) - noisy).mean() < 10
    assert not Imaging().active
    assert IMAGING_PRESETS["real"].active
    assert resolve_imaging("real", defocus_px=0.5).defocus_px == 0.5
    with pytest.raises(ValueError, match="expected one of"):
        resolve_imaging("blurry")
    with pytest.raises(ValueError, match="vignetting"):
        Imaging(vignetting=1.5)


def test_motion_profiles() -> None:
    t = T0 + np.arange(0.0, 30.0, 0.02)
    rectangle = PRESET_PATHS["rectangle"]
    cart = PolylineTrajectory(rectangle, t0=T0, dwell=2.5, **MOTION_PROFILES["cart"])  # type: ignore[arg-type]
    pos, rot = cart(t)
    assert np.ptp(pos[:, 2]) < 1e-9  # level: constant height
    ypr = rot.as_euler("ZYX", degrees=True)
    assert np.abs(ypr[:, 1:]).max() < 1e-6  # no pitch, no roll
    yaw_rate = np.abs(np.diff(np.unwrap(np.radians(ypr[:, 0])))) / 0.02
    # turns in place at the corners, at up to (pi / 2) x 90 deg / 2.5 s = 56.5 deg/s
    assert 50 < np.degrees(yaw_rate.max()) < 60
    hand = LoopTrajectory(t0=T0, **MOTION_PROFILES["hand"])  # type: ignore[arg-type]
    walk = LoopTrajectory(t0=T0)
    zh, zw = hand(t)[0][:, 2], walk(t)[0][:, 2]

    # the bounce: what is left of the height after a 1 s moving average (the slow swing)
    def fast(z: np.ndarray) -> float:
        return float(np.std((z - np.convolve(z, np.ones(50) / 50, "same"))[50:-50]))

    assert 0.01 < fast(zh) < 0.02
    assert fast(zw) < 0.004
