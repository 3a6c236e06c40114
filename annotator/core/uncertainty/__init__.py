"""How good each pose is: the parts of a trajectory row's ``sigma_m`` beyond the smoother's noise.

The smoother treats every frame's corner noise as independent, so its sigma shrinks as frames
are averaged. Errors of the static inputs (marker map, rig, intrinsics, rolling-shutter readout)
do not average out: a marker surveyed 1.5 cm off moves every frame that sees it the same way.
This module propagates the parameters' covariance into each pose, linearised per frame:

    pose error  d = -(J^T W J)^-1 J^T W B dtheta,   Cov(d) = A Sigma A^T,  A = (J^T W J)^-1 J^T W B

with J the corners' pixel residuals' Jacobian w.r.t. the bundle pose (world-frame rotation,
position), B their Jacobian w.r.t. the parameters (analytic for markers and rig, numeric for the
intrinsics, from the bundle's motion for the readout) and W the robust weights, all at the
smoothed pose. Parameter errors stay correlated from frame to frame, so the smoothed pose keeps
them: each row's parameter variance is a short kernel average of its neighbours' (an upper bound
of the variance of the averaged pose).

``scale_priors``: the stated priors may be too pessimistic or too optimistic. The residuals left
after a per-frame fit measure the part of the parameter errors that the frame sees as
inconsistency between markers and cameras; a regression of their energy on the corner noise and
on each block's predicted energy over the whole capture gives each block a scale. The upper end
of its 2-sigma confidence range is used (never below ``min_scale``, never above ``max_scale``),
so a block the capture cannot check keeps its prior.

Motion blur: the smear of a frame is the corners' image speed (from the smoothed motion) times
the exposure; frames smearing more than ``max_smear_px`` are down-weighted (dropped beyond three
times that). The time within the exposure at which the detector places a smeared corner is
unknown: a time error of exposure / sqrt(12) (uniform over the exposure), which moves the pose
along the direction of motion only. Per axis, as every other part of sigma_m (the rms over x, y
and z), that is ``sigma_blur_m`` = speed x exposure / sqrt(12) / sqrt(3) = speed x exposure / 6.

With a refinement's record (``ParameterCovariance.joint``), A Sigma A^T runs over every block at
once (markers, rig, intrinsics and distortion, readout, the detector's corner bias and the markers'
printed size when the refinement estimated it), with the
refinement's cross-covariances: the surveyed markers fix where the map sits in the room together,
so that error is common to every marker and a frame that sees many markers keeps all of it, while
a principal point shift and a turn of that camera in the rig, fitted to the same corners, largely
cancel. Each block's column is its share of the joint total. Without a joint record (priors) the
blocks are independent.

``sigma_unmodelled_m`` is a floor for what no model here covers (the detector's corner bias on
small markers, the renderer's or a real lens's residual distortion), added in quadrature.

The package: ``records`` (blocks, settings, the per-row result), ``views`` (each frame at the
smoothed pose and twist of its time), ``propagation`` (Jacobians and A Sigma A^T per frame),
``rows`` (per trajectory row, with the prior scales), ``blur`` (the smear)
and ``budget`` (the total, its parts, the sync's share).
"""

from annotator.core.uncertainty.blur import image_speed, row_smear, smear_weights
from annotator.core.uncertainty.budget import (
    SIGMA_PARTS,
    SigmaBudget,
    sigma_budget,
    sync_time_sigma,
    total_sigma,
)
from annotator.core.uncertainty.propagation import (
    FrameJacobians,
    JacobianCache,
    condition_on_rest,
    frame_jacobians,
    parameter_covariance,
    propagate,
)
from annotator.core.uncertainty.records import (
    BLOCKS,
    RowUncertainty,
    UncertaintySettings,
    VideoClock,
    VideoFrames,
)
from annotator.core.uncertainty.rows import row_uncertainty
from annotator.core.uncertainty.views import FrameView, trajectory_twist

__all__ = [
    "BLOCKS",
    "SIGMA_PARTS",
    "FrameJacobians",
    "FrameView",
    "JacobianCache",
    "RowUncertainty",
    "SigmaBudget",
    "UncertaintySettings",
    "VideoClock",
    "VideoFrames",
    "condition_on_rest",
    "frame_jacobians",
    "image_speed",
    "parameter_covariance",
    "propagate",
    "row_smear",
    "row_uncertainty",
    "sigma_budget",
    "smear_weights",
    "sync_time_sigma",
    "total_sigma",
    "trajectory_twist",
]
