"""The rig's gauge from a rest on a jig: pure arrays, no I/O.

The video fixes every camera's pose in the room, and the cameras' poses relative to each other,
but not where the cameras sit on the bundle as a whole: a common turn or shift of every camera in
the bundle frame moves each bundle pose by the same rigid motion and leaves every image alike.
That gauge comes from rig.yaml, measured by hand (~1 deg, ~3 mm), and its error is the floor of
the bundle's orientation error. While the bundle rests at a known pose (a jig: a levelled plate
squared to a wall of the room) the tracked pose T_i of each row and the jig's pose T_jig give that
common correction C = T_i^-1 T_jig in the bundle frame; then every bundle pose becomes T C and
every camera's place on the bundle C^-1 T_bundle_camera, and the cameras' poses in the room stay
exactly as the video says. C's turn is the rig's; its shift is split (shift_shares) between the
rig, the map's datum (a shift of every marker and position in the room) and the jig's own error.
sigma_m is then conditioned on the rest (uncertainty.condition_on_rest, rows ``rest_rows``,
variance ``rest_variance``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.experiment import Experiment
from annotator.core.priors import Jig
from bgt_core.formats.markers import MarkerPose

# A rest whose tracked poses scatter more than this (deg, m) was not still; a correction beyond
# this (deg, m) is not a hand-measured rig's error but a wrong jig entry. Both only warn.
MAX_SCATTER = (0.3, 0.010)
MAX_CORRECTION = (5.0, 0.050)


@dataclass(frozen=True, eq=False)
class JigCorrection:
    """C: bundle-frame rotation ``R`` and shift ``t`` (m) that take a tracked pose to the true one."""

    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)
    rows: int  # trajectory rows on the jig that gave it
    spread_deg: float  # RMS scatter of the per-row corrections (how still the bundle sat)
    spread_m: float

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(Rotation.from_matrix(self.R).magnitude()))

    def problems(self) -> list[str]:
        """What looks wrong with the rest (for a warning each)."""
        out = []
        if self.spread_deg > MAX_SCATTER[0] or self.spread_m > MAX_SCATTER[1]:
            out.append(
                f"the bundle did not sit still on the jig (scatter {self.spread_deg:.2f} deg, "
                f"{1000 * self.spread_m:.1f} mm over {self.rows} rows): check the window"
            )
        shift = float(np.linalg.norm(self.t))
        if self.angle_deg > MAX_CORRECTION[0] or shift > MAX_CORRECTION[1]:
            out.append(
                f"a correction of {self.angle_deg:.1f} deg / {1000 * shift:.0f} mm is far beyond a "
                "hand-measured rig: check the jig's pose and window"
            )
        return out

    def record(self) -> dict[str, object]:
        """The correction as report.json's ``jig`` entry."""
        return {
            "rows": self.rows,
            "rotation_deg": round(self.angle_deg, 4),
            "rotation_vector_deg": np.round(
                np.degrees(Rotation.from_matrix(self.R).as_rotvec()), 4
            ).tolist(),
            "shift_m": np.round(self.t, 5).tolist(),
            "spread_deg": round(self.spread_deg, 4),
            "spread_m": round(self.spread_m, 5),
        }


def rest_rows(t: np.ndarray, position: np.ndarray, rotation: np.ndarray, jig: Jig) -> np.ndarray:
    """Mask of the posed rows within the jig's time window."""
    return (
        (t >= jig.start)
        & (t <= jig.end)
        & np.isfinite(position).all(axis=1)
        & np.isfinite(rotation.reshape(len(t), 9)).all(axis=1)
    )


def rest_variance(jig: Jig) -> np.ndarray:
    """(6,) per-axis variance of the jig's pose: rotation (rad^2), then position (m^2)."""
    return np.array([math.radians(jig.sigma_deg) ** 2] * 3 + [jig.sigma_m**2] * 3)


def jig_correction(
    t: np.ndarray, position: np.ndarray, rotation: np.ndarray, jig: Jig
) -> JigCorrection | None:
    """C from the posed rows within the jig's time window; None when none was posed there."""
    sel = rest_rows(t, position, rotation, jig)
    if not sel.any():
        return None
    R_i, p_i = rotation[sel], position[sel]
    rots = Rotation.from_matrix(np.swapaxes(R_i, 1, 2) @ jig.rotation)  # R_i^T R_jig
    shifts = np.einsum("nji,nj->ni", R_i, jig.position - p_i)  # R_i^T (p_jig - p_i)
    mean = rots.mean()
    shift = shifts.mean(axis=0)
    spread_deg = math.degrees(float(np.sqrt(np.mean((mean.inv() * rots).magnitude() ** 2))))
    spread_m = float(np.sqrt(np.mean(np.sum((shifts - shift) ** 2, axis=1))))
    return JigCorrection(mean.as_matrix(), shift, int(sel.sum()), spread_deg, spread_m)


def shift_shares(var_rig: float, var_datum: float, var_jig: float) -> tuple[float, float]:
    """How to split the jig's position discrepancy: (share for the rig, share for the map's datum),
    per axis.

    A rest at a known position cannot tell a rig shift (in the bundle frame: it turns with the
    bundle) from a shift of the whole map (the survey's mean error: in the room frame) or from the
    jig's own error; each is credited with its share of the variance (the best linear estimate).
    A rotation is all the rig's: the map's datum turns by hundredths of a degree.
    """
    total = var_rig + var_datum + var_jig
    if total <= 0:
        return 0.0, 0.0
    return var_rig / total, var_datum / total


def split_shift(
    c: JigCorrection, rig_share: float, datum_share: float, R_world_bundle: np.ndarray
) -> tuple[JigCorrection, np.ndarray]:
    """C with only the rig's share of its shift, and the map's share as a room-frame shift (m)
    (every position and marker moves by it), both taken at the jig's orientation R_world_bundle."""
    return replace(c, t=rig_share * c.t), datum_share * (R_world_bundle @ c.t)


def correct_poses(
    position: np.ndarray, rotation: np.ndarray, c: JigCorrection
) -> tuple[np.ndarray, np.ndarray]:
    """Every bundle pose T -> T C (rows without a pose stay NaN)."""
    return position + rotation @ c.t, rotation @ c.R


def correct_camera(
    R_bundle_camera: np.ndarray, t_bundle_camera: np.ndarray, c: JigCorrection
) -> tuple[np.ndarray, np.ndarray]:
    """A camera's place on the bundle T_bc -> C^-1 T_bc."""
    return c.R.T @ R_bundle_camera, c.R.T @ (t_bundle_camera - c.t)


def datum_variance(sigma_m: list[float] | np.ndarray) -> float:
    """Per-axis variance of where the map sits: the mean survey variance of the surveyed markers
    the walk saw over their count (0 without any)."""
    s = np.asarray(sigma_m, float)
    return float(np.mean(s**2)) / len(s) if len(s) else 0.0


def correct_experiment(
    exp: Experiment,
    position: np.ndarray,
    rotation: np.ndarray,
    c: JigCorrection,
    var_datum: float,
) -> tuple[Experiment, np.ndarray, np.ndarray, dict[str, object]]:
    """The experiment (rig and map), the poses and report.json's ``jig`` record after the jig:
    the rotation and the rig's share of the shift in the bundle frame, the map's share in the
    room (``var_datum``: see datum_variance; shift_shares splits)."""
    pr = exp.priors
    assert pr.jig is not None
    rig_share, datum_share = shift_shares(
        pr.rig_sigma_m**2 / len(exp.rig.cameras), var_datum, pr.jig.sigma_m**2
    )
    record = c.record()
    c, world = split_shift(c, rig_share, datum_share, pr.jig.rotation)
    cams = {}
    for name, cam in exp.rig.cameras.items():
        R_bc, t_bc = correct_camera(cam.R_bundle_camera, cam.t_bundle_camera, c)
        cams[name] = replace(cam, R_bundle_camera=R_bc, t_bundle_camera=t_bc)
    markers = {
        i: MarkerPose.from_values(i, np.add(m.position, world), m.euler_xyz)
        for i, m in exp.markers.markers.items()
    }
    exp = replace(
        exp,
        rig=replace(exp.rig, cameras=cams),
        markers=replace(exp.markers, markers=markers),
    )
    position, rotation = correct_poses(position, rotation, c)
    record.update(rig_shift_share=round(rig_share, 3), map_shift_m=np.round(world, 5).tolist())
    return exp, position + world, rotation, record
