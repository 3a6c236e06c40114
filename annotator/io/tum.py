"""TUM trajectory files (``t x y z qx qy qz qw``, space separated, one pose per line) so that
standard tools such as evo (``evo_ape tum ref.tum est.tum``) work on our trajectories, on
published tracks and on any localizer's estimates."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from annotator.core.trajectory import Trajectory, blend, bracket
from annotator.errors import AnnotatorError, NoDataError

log = logging.getLogger(__name__)


def _rotations(rot: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, 3, 3) matrices projected to the nearest rotation (published tracks hold matrices that
    are not rotations); matrices with no nearby rotation (det <= 0, NaN) become identity.
    Returns the rotations and how many were replaced."""
    out = np.tile(np.eye(3), (len(rot), 1, 1))
    ok = np.isfinite(rot).all(axis=(1, 2))
    ok[ok] = np.linalg.det(rot[ok]) > 1e-6
    if ok.any():
        out[ok] = Rotation.from_matrix(rot[ok]).as_matrix()
    return out, int((~ok).sum())


def read_poses(path: str | Path) -> Trajectory:
    """A trajectory.csv (full pose), an annotated run directory (its trajectory.csv), a track
    .mbd file or folder (pose of each timestamp), or an estimates CSV ``t,x,y[,z]`` (identity
    orientation, z 0 when absent). Rows without a position are gaps (not written); every row's
    rotation is a proper rotation."""
    from annotator.io.scoring import read_estimates

    path = Path(path)
    if path.is_dir() and (path / "trajectory.csv").is_file():
        path = path / "trajectory.csv"
    if path.is_file() and path.suffix == ".csv":
        with path.open(encoding="utf-8") as f:
            header = [h.strip() for h in f.readline().split(",")]
        if "r11" in header:
            from annotator.io.trajectory import read_trajectory

            traj = read_trajectory(path)
            rot, bad = _rotations(traj.rotation)
            pos = np.where(traj.valid[:, None], traj.position, np.nan)
            return Trajectory(traj.t, pos, rot)
        est = read_estimates(path)
        pos = est.position.copy()
        if not est.has_z:
            pos[:, 2] = np.where(np.isfinite(pos[:, :2]).all(axis=1), 0.0, np.nan)
        return Trajectory(est.t, pos, np.tile(np.eye(3), (len(est.t), 1, 1)))
    from annotator.io.radio_data import annotated_files
    from bgt_core.formats.tables import load_mbd

    files = annotated_files([path])
    merged = [f for f in files if f.name.endswith("all_sensors.mbd")]
    df = load_mbd(merged[:1] or files)
    if "x" not in df.columns:
        raise AnnotatorError(f"{path}: rows carry no positions (not an annotated track)")
    df = df.sort_values("t_ns", kind="stable").drop_duplicates("t_ns")
    rot = df[["r11", "r12", "r13", "r21", "r22", "r23", "r31", "r32", "r33"]].to_numpy(float)
    rot, bad = _rotations(rot.reshape(-1, 3, 3))
    if bad:
        log.warning("%s: %d orientations are not near any rotation; written as identity", path, bad)
    return Trajectory(df["t_ns"].to_numpy() / 1e9, df[["x", "y", "z"]].to_numpy(float), rot)


def format_tum(p: Trajectory, *, flat: bool = False) -> str:
    """TUM lines for the rows with a position; ``flat`` writes z = 0 (for 2-D comparisons)."""
    lines = []
    has = np.isfinite(p.position).all(axis=1)
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(p.t), 1))
    if has.any():
        quats[has] = Rotation.from_matrix(_rotations(p.rotation[has])[0]).as_quat()
    for t, xyz, q, ok in zip(p.t, p.position, quats, has, strict=True):
        if not ok:
            continue
        z = 0.0 if flat else xyz[2]
        lines.append(
            f"{float(t)!r} {float(xyz[0])!r} {float(xyz[1])!r} {float(z)!r} "
            + " ".join(repr(float(v)) for v in q)
            + "\n"
        )
    return "".join(lines)


def write_tum(path: str | Path, p: Trajectory, *, flat: bool = False) -> int:
    text = format_tum(p, flat=flat)
    if not text:
        raise NoDataError(f"{path}: no pose to write")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return text.count("\n")


def resample(p: Trajectory, t: np.ndarray, *, max_gap_s: float) -> Trajectory:
    """Positions interpolated at ``t`` as `annotator score` does (never extrapolated, no bridging
    of gaps); orientations by slerp between the same two samples (core.trajectory's bracket and
    blend). Unscored times are gaps."""
    from annotator.core.scoring import Truth, interpolate_truth

    t = np.asarray(t, dtype=float)
    truth = Truth.from_samples(p.t, p.position)
    pos, _ = interpolate_truth(truth, t, max_gap_s=max_gap_s)
    rot = np.tile(np.eye(3), (len(t), 1, 1))
    ok = np.isfinite(pos).all(axis=1)
    known = p.compact()  # the rows with a pose, one per time
    if ok.any() and len(known.t):
        lo, hi, w = bracket(known.t, np.clip(t[ok], known.t[0], known.t[-1]))
        rot[ok] = blend(known.position, known.rotation, lo, hi, w)[1]
    return Trajectory(t, pos, rot)
