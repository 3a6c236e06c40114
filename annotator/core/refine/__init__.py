"""Self-calibration from the capture: a bundle adjustment over keyframes of a first tracking pass.

Jointly refines, under a Huber loss on marker-corner reprojection residuals (pixels):

- the bundle pose at each keyframe (free);
- every marker's pose (the survey as a prior weighted by its sigma; markers the surveyor skipped,
  or marked ``unknown``, are free and start from frames where they are seen with surveyed ones);
- each camera's pose in the rig (the measured rig as a prior);
- each camera's intrinsics fx, fy, cx, cy and distortion (the calibration as a prior, plus a tight
  prior on fx/fy - the aspect ratio of a pixel is a property of the sensor, well known);
- each camera's rolling-shutter readout time (prior: the calibration's value).

A keyframe is one frame of the first camera plus the other cameras' nearest frames; those are
held to the keyframe's pose by the first pass's relative motion (known far better than absolute
poses over a few ms), and every corner is seen at its frame time + row / height x readout, with
the bundle moving at the first pass's velocity meanwhile.

All parameters are deltas from their starting values (rotations as world- or bundle-frame rotation
vectors, as in `annotator.core.priors`). The Jacobian is analytic, by the chain rule through the
projection's stages (`refine/jacobian.py`); each residual depends on one instance of each block only,
so each corner carries its own few dozen columns and the normal equations are summed over the
corners of each marker and camera. The solver is our own Levenberg-Marquardt with a Schur complement on the pose
blocks (6x6 each), so each step solves a dense system the size of the static parameters only;
the inverse of that reduced system is the covariance of the static parameters (what
`priors.ParameterCovariance` carries to the uncertainty propagation). See docs/annotator.md for
why not scipy's least_squares.

Gauge: a rotation or translation common to every camera of the rig, with the opposite change of
the bundle poses, moves no camera; the rig prior alone fixes it, so the bundle's orientation is
only as good as the rig's measurement (per camera 1 deg -> ~0.7 deg per axis for two cameras).

The package in four parts: ``model`` (settings, parameter blocks, projection, the corner model),
``solver`` (priors, Jacobian, Levenberg-Marquardt, gate, covariance), ``problem`` (a problem from
keyframe detections) and ``capture`` (keyframes of a first pass, the refined experiment, report).
"""

from annotator.core.refine.capture import (
    Refinement,
    blur_weight,
    camera_params,
    motion_at,
    predicted_smear_px,
    refine_capture,
    refinement_report,
    select_keyframes,
)
from annotator.core.refine.model import (
    CORNER_BIAS_SIGMA_PX,
    CameraParams,
    Observations,
    Problem,
    RefineSettings,
    Solution,
    distort_normalised,
    supported_lens,
)
from annotator.core.refine.problem import FrameView, Keyframe, build_problem, marker_views
from annotator.core.refine.solver import marker_floors, solve

__all__ = [
    "CORNER_BIAS_SIGMA_PX",
    "CameraParams",
    "FrameView",
    "Keyframe",
    "Observations",
    "Problem",
    "RefineSettings",
    "Refinement",
    "Solution",
    "blur_weight",
    "build_problem",
    "camera_params",
    "distort_normalised",
    "marker_floors",
    "marker_views",
    "motion_at",
    "predicted_smear_px",
    "refine_capture",
    "refinement_report",
    "select_keyframes",
    "solve",
    "supported_lens",
]
