"""The rig's gauge from a rest on a jig (annotator.core.jig) and its experiment.yaml entry."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotator.core.jig import (
    correct_camera,
    correct_poses,
    datum_variance,
    jig_correction,
    shift_shares,
    split_shift,
)
from annotator.core.priors import Jig, parse_priors
from annotator.errors import ConfigError

EYE = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]


def _scene(rng: np.random.Generator, n: int = 60, rest: int = 15):
    """True bundle poses (the first ``rest`` rows still), a true rig of two cameras, the rig as
    measured (off by one common bundle-frame motion G: its gauge) and the bundle poses a tracker
    computes from exact camera poses with the measured rig."""
    R_true = Rotation.random(n, random_state=7).as_matrix()
    p_true = rng.normal(size=(n, 3))
    R_true[:rest], p_true[:rest] = R_true[0], p_true[0]
    rig = [
        (Rotation.random(random_state=k).as_matrix(), rng.normal(scale=0.05, size=3))
        for k in (1, 2)
    ]
    G_R = Rotation.from_rotvec(np.radians([0.8, -0.6, 0.9])).as_matrix()
    G_t = np.array([0.003, -0.002, 0.004])
    measured = [(G_R @ R, G_R @ t + G_t) for R, t in rig]
    # One camera's world pose (both give the same bundle pose: the error is common).
    R_wc = R_true @ rig[0][0]
    p_wc = p_true + R_true @ rig[0][1]
    R_est = R_wc @ measured[0][0].T
    p_est = p_wc - R_est @ measured[0][1]
    return np.arange(n) * 0.1, R_true, p_true, rig, measured, R_est, p_est


def test_a_rest_at_a_known_pose_recovers_the_rig_and_every_pose() -> None:
    t, R_true, p_true, rig, measured, R_est, p_est = _scene(np.random.default_rng(0))
    assert np.degrees(Rotation.from_matrix(R_est[0].T @ R_true[0]).magnitude()) > 1.0
    jig = Jig(t[0], t[14], p_true[0], R_true[0])
    c = jig_correction(t, p_est, R_est, jig)
    assert c is not None
    assert c.rows == 15
    assert c.spread_deg < 1e-9
    assert c.spread_m < 1e-12
    p, R = correct_poses(p_est, R_est, c)
    assert np.abs(R - R_true).max() < 1e-12
    assert np.abs(p - p_true).max() < 1e-12
    for (R_bc, t_bc), (R_m, t_m) in zip(rig, measured, strict=True):
        R_new, t_new = correct_camera(R_m, t_m, c)
        assert np.abs(R_new - R_bc).max() < 1e-12
        assert np.abs(t_new - t_bc).max() < 1e-12


def test_no_posed_row_in_the_window_gives_no_correction() -> None:
    t, R_true, p_true, _, _, R_est, p_est = _scene(np.random.default_rng(1))
    p_est[:15] = np.nan
    assert jig_correction(t, p_est, R_est, Jig(t[0], t[14], p_true[0], R_true[0])) is None


def test_a_bundle_that_moved_on_the_jig_shows_in_the_spread() -> None:
    t, R_true, p_true, _, _, R_est, p_est = _scene(np.random.default_rng(2))
    p_est[5] += [0.01, 0, 0]
    c = jig_correction(t, p_est, R_est, Jig(t[0], t[14], p_true[0], R_true[0]))
    assert c is not None
    assert 0.002 < c.spread_m < 0.01


def test_the_shift_is_split_by_variance_between_rig_map_and_jig() -> None:
    rig, datum, jig = 0.003**2 / 2, 0.015**2 / 20, 0.001**2
    to_rig, to_map = shift_shares(rig, datum, jig)
    total = rig + datum + jig
    assert to_rig == pytest.approx(rig / total)
    assert to_map == pytest.approx(datum / total)
    assert shift_shares(0.0, 0.0, 0.0) == (0.0, 0.0)
    t, R_true, p_true, _, _, R_est, p_est = _scene(np.random.default_rng(3))
    c = jig_correction(t, p_est, R_est, Jig(t[0], t[14], p_true[0], R_true[0]))
    assert c is not None
    part, world = split_shift(c, 0.25, 0.5, R_true[0])
    assert np.allclose(part.t, 0.25 * c.t)
    assert np.allclose(part.R, c.R)
    # The map's share is the same displacement, in the room frame at the jig's orientation.
    assert np.allclose(world, 0.5 * R_true[0] @ c.t)


def test_experiment_yaml_jig_entry() -> None:
    jig = parse_priors(
        {
            "jig": {
                "from": 10,
                "to": 12.5,
                "position": [1, 2, 1.5],
                "R_world_bundle": EYE,
                "sigma_deg": 0.2,
            }
        },
        "e.yaml",
    ).jig
    assert jig is not None
    assert (jig.start, jig.end, jig.sigma_m, jig.sigma_deg) == (10.0, 12.5, 0.001, 0.2)
    assert np.allclose(jig.position, [1, 2, 1.5])
    assert np.allclose(jig.rotation, np.eye(3))
    assert parse_priors(None, "e.yaml").jig is None


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        (3, "refine.jig: must be a mapping"),
        ({"from": 1}, "refine.jig: missing R_world_bundle, position, to"),
        ({"from": 2, "to": 1, "position": [0, 0, 0], "R_world_bundle": EYE}, "must come after"),
        ({"from": 1, "to": 2, "position": [0, 0], "R_world_bundle": EYE}, "position: must be 3"),
        ({"from": "x", "to": 2, "position": [0, 0, 0], "R_world_bundle": EYE}, "from: must be a"),
        ({"from": 1, "to": 2, "position": [0, 0, 0], "R_world_bundle": 2 * np.eye(3)}, "not a rot"),
        (
            {"from": 1, "to": 2, "position": [0, 0, 0], "R_world_bundle": EYE, "at": 1},
            "unknown key 'refine.jig.at'",
        ),
        (
            {"from": 1, "to": 2, "position": [0, 0, 0], "R_world_bundle": EYE, "sigma_m": -1},
            "sigma_m: must be a positive",
        ),
    ],
)
def test_a_bad_jig_entry_is_one_clear_error(entry: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        parse_priors({"jig": entry}, "e.yaml")
    assert "\n" not in str(err.value)
    assert str(err.value).startswith("e.yaml: ")
    assert "refine.jig" in str(err.value)


def test_a_restless_bundle_or_a_wrong_jig_pose_is_named() -> None:
    t, R_true, p_true, _, _, R_est, p_est = _scene(np.random.default_rng(4))
    jig = Jig(t[0], t[14], p_true[0], R_true[0])
    c = jig_correction(t, p_est, R_est, jig)
    assert c is not None
    assert c.problems() == []  # a 1.4 deg, 5 mm rig error on a still bundle
    p_est[3:6] += [0.03, 0, 0]
    c = jig_correction(t, p_est, R_est, jig)
    assert c is not None
    assert [p.split(" (")[0] for p in c.problems()] == ["the bundle did not sit still on the jig"]
    turned = Rotation.from_rotvec([0, 0, np.radians(10)]).as_matrix() @ R_true[0]
    c = jig_correction(t, p_est, R_est, Jig(t[0], t[14], p_true[0], turned))
    assert c is not None
    assert any("far beyond a hand-measured rig" in p for p in c.problems())


def test_the_datum_variance_is_the_mean_survey_variance_over_the_count() -> None:
    assert datum_variance([0.015] * 9) == pytest.approx(0.015**2 / 9)
    assert datum_variance([0.01, 0.02]) == pytest.approx((0.01**2 + 0.02**2) / 2 / 2)
    assert datum_variance([]) == 0.0
