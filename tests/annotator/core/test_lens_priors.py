"""Lens models and readout in calibrations; priors from experiment.yaml's refine: section."""

import math

import numpy as np
import pytest

from annotator.core.priors import ParameterCovariance, parse_priors
from annotator.errors import ConfigError
from annotator.io.experiment import parse_calibration
from annotator.vision.lens import project_points, undistort_points


def _cal(**extra):
    d = {
        "camera_matrix": [[600.0, 0, 480], [0, 601.0, 270], [0, 0, 1]],
        "image_width": 960,
        "image_height": 540,
        "distortion_coefficients": [-0.28, 0.07, 0.001, -0.001, 0.0],
    }
    d.update(extra)
    return parse_calibration(d, "cam.yaml")


@pytest.mark.parametrize(
    ("model", "dist"),
    [
        ("plumb_bob", [-0.28, 0.07, 0.001, -0.001, 0.0]),
        ("equidistant", [0.05, -0.01, 0.002, -0.0005]),
    ],
)
def test_project_then_undistort_returns_the_ray(model, dist):
    cal = _cal(distortion_model=model, distortion_coefficients=dist)
    rng = np.random.default_rng(1)
    pts = np.column_stack(
        [rng.uniform([-0.6, -0.4], [0.6, 0.4], (50, 2)), np.ones(50)]
    ) * rng.uniform(0.5, 4, (50, 1))
    px = project_points(cal, pts)
    assert np.all((px[:, 0] > 0) & (px[:, 0] < 960) & (px[:, 1] > 0) & (px[:, 1] < 540))
    xn = undistort_points(cal, px)
    np.testing.assert_allclose(xn, pts[:, :2] / pts[:, 2:], atol=1e-7)


def test_fisheye_and_readout_parsed_and_checked():
    cal = _cal(
        distortion_model="fisheye",
        distortion_coefficients=[0.1, 0, 0, 0],
        rolling_shutter_readout_s=0.015,
    )
    assert (cal.model, cal.readout_s) == ("fisheye", 0.015)
    assert _cal().model == "radtan"
    assert _cal().readout_s == 0.0
    with pytest.raises(ConfigError, match="fisheye model takes 4 values"):
        _cal(distortion_model="fisheye")
    with pytest.raises(ConfigError, match="rolling_shutter_readout_s must be between"):
        _cal(rolling_shutter_readout_s=-1)
    with pytest.raises(ConfigError, match="distortion_model 'kannala'"):
        _cal(distortion_model="kannala")


def test_priors_defaults_overrides_and_errors():
    p = parse_priors(None, "e.yaml")
    assert p.mode == "all"
    assert p.marker(3).sigma_m == 0.015
    p = parse_priors(
        {"mode": "map", "survey_sigma_m": 0.02, "markers": {3: {"sigma_m": 0.001}, 7: "unknown"}},
        "e.yaml",
    )
    assert p.mode == "map"
    assert p.marker(3).sigma_m == 0.001
    assert p.marker(3).sigma_deg == 1.0
    assert not p.marker(7).known
    assert p.marker(8).sigma_m == 0.02
    cov = ParameterCovariance.from_priors(p, [3, 7, 8], {"front": np.diag([600.0, 600.0, 1.0])})
    assert set(cov.markers) == {3, 8}
    assert math.isclose(cov.markers[8][3, 3], 0.02**2)
    assert math.isclose(cov.intrinsics["front"][0, 0], 9.0)
    for bad, msg in [
        ({"mode": "some"}, "refine.mode"),
        ({"rig_sigma_m": -1}, "refine.rig_sigma_m"),
        ({"survey_sigma": 1}, "unknown key"),
        ({"markers": {"x": "unknown"}}, "not a marker id"),
    ]:
        with pytest.raises(ConfigError, match=msg):
            parse_priors(bad, "e.yaml")
