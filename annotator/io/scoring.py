"""The file side of scoring: estimates CSV in, ground truth from an annotated run or a published
track, score.json out. The metrics themselves live in annotator.core.scoring."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.core.scoring import Score, Truth
from annotator.errors import AnnotatorError, NoDataError
from annotator.io.outputs import POINT_TRAJECTORY

ESTIMATE_COLUMNS = ("t", "x", "y")  # then an optional z; other columns are ignored


@dataclass(frozen=True, slots=True)
class Estimates:
    t: np.ndarray  # (M,) Unix seconds, sorted
    position: np.ndarray  # (M, 3); z NaN when the file has no z column
    has_z: bool
    source: str = ""


def read_estimates(path: str | Path) -> Estimates:
    """``t,x,y[,z]`` CSV with a header (extra columns ignored). Rows are sorted by t; a row with
    an empty or NaN x/y is an estimate the localizer did not give (not scored)."""
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_csv(path, skipinitialspace=True)
    except FileNotFoundError:
        raise AnnotatorError(f"cannot read estimates {path}: no such file") from None
    except (OSError, ValueError, pd.errors.ParserError) as e:
        raise AnnotatorError(f"cannot read estimates {path}: {str(e).splitlines()[0]}") from None
    df.columns = [str(c).strip().lower() for c in df.columns]
    missing = [c for c in ESTIMATE_COLUMNS if c not in df.columns]
    if missing:
        raise AnnotatorError(
            f"{path}: header lacks column(s) {', '.join(missing)}; expected 't,x,y' or 't,x,y,z'"
        )
    has_z = "z" in df.columns
    cols = [*ESTIMATE_COLUMNS, *(["z"] if has_z else [])]
    try:
        data = df[cols].apply(pd.to_numeric, errors="raise").to_numpy(dtype=float)
    except (ValueError, TypeError):
        bad = next(
            i
            for i, row in enumerate(df[cols].itertuples(index=False))
            if not all(_is_number(v) for v in row)
        )
        raise AnnotatorError(
            f"{path}:{bad + 2}: t, x, y{', z' if has_z else ''} must be numbers"
        ) from None
    if not len(data):
        raise NoDataError(f"{path}: no estimates")
    if not np.isfinite(data[:, 0]).all():
        bad = int(np.flatnonzero(~np.isfinite(data[:, 0]))[0])
        raise AnnotatorError(f"{path}:{bad + 2}: t must be a finite time (Unix seconds)")
    pos = np.full((len(data), 3), np.nan)
    pos[:, : data.shape[1] - 1] = data[:, 1:]
    order = np.argsort(data[:, 0], kind="stable")
    return Estimates(data[order, 0], pos[order], has_z, str(path))


def _is_number(v: object) -> bool:
    try:
        float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False
    return True


def write_estimates(path: str | Path, t: np.ndarray, position: np.ndarray) -> Path:
    """``t,x,y,z`` CSV (the score's input format), or ``t,x,y`` when ``position`` is (M, 2);
    NaN coordinates are written as empty cells (an estimate not given)."""
    path = Path(path)
    pos = np.asarray(position, dtype=float)
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", encoding="utf-8", newline="\n") as f:
        f.write("t,x,y,z\n" if pos.shape[1] == 3 else "t,x,y\n")
        for ti, p in zip(np.asarray(t, dtype=float), pos, strict=True):
            cells = ["" if not math.isfinite(v) else f"{v:.4f}" for v in p]
            f.write(f"{float(ti)!r},{','.join(cells)}\n")  # t: shortest exact spelling
    tmp.replace(path)
    return path


def _truth_from_mbd(paths: list[Path], source: str) -> Truth:
    from bgt_core.formats.tables import load_mbd

    df = load_mbd(paths)
    if "x" not in df.columns:
        raise AnnotatorError(
            f"{source}: rows carry no positions; the truth must be an annotated "
            "track (ts,sensor,beacon,rssi,x,y,z,...)"
        )
    if not len(df):
        raise NoDataError(f"{source}: no rows")
    pos = df[["x", "y", "z"]].to_numpy(dtype=float)
    return Truth.from_samples(df["t_ns"].to_numpy() / 1e9, pos, None, source)


def _truth_from_trajectory(path: Path) -> Truth:
    from annotator.io.trajectory import read_trajectory

    traj = read_trajectory(path)
    sigma = traj.quality.get("sigma_m")
    pos = np.where(traj.valid[:, None], traj.position, np.nan)
    return Truth.from_samples(traj.t, pos, sigma, str(path))


def read_truth(path: str | Path) -> Truth:
    """Ground truth from: an annotated run directory (the path of the antenna its readings were
    labelled at: receiver_trajectory.csv in receiver mode, beacon_trajectory.csv when the beacon
    is off the bundle's origin, else trajectory.csv, whose sigma_m column is the truth's 1-sigma;
    else its annotated/all_sensors.mbd), a trajectory.csv, a published track file
    (``*_all_sensors.mbd`` or one sensor's ``.mbd``) or a published track folder."""
    path = Path(path)
    if path.is_dir():
        named = [path / name for name in POINT_TRAJECTORY.values()]
        for cand in (*named, path / "trajectory.csv", path / "annotated" / "all_sensors.mbd"):
            if cand.is_file():
                return read_truth(cand)
        merged = sorted(path.glob("*all_sensors.mbd"))
        files = merged[:1] or sorted(path.glob("*.mbd"))
        if not files:
            raise NoDataError(
                f"{path}: neither trajectory.csv, annotated/all_sensors.mbd nor "
                "track .mbd files in it"
            )
        return _truth_from_mbd(files, str(path))
    if not path.is_file():
        raise AnnotatorError(f"cannot read truth {path}: no such file or directory")
    if path.suffix == ".csv":
        return _truth_from_trajectory(path)
    return _truth_from_mbd([path], str(path))


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def write_score(out_dir: str | Path, s: Score, *, estimates: str, truth: str, has_z: bool) -> Path:
    """``out_dir/score.json``: blocks error_2d_m and error_3d_m (mean, median, rmse, ce50, ce75,
    ce95, max, n), the truth's sigma, coverage and the latency estimate."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    body = {"estimates": estimates, "truth": truth, **s.report()}
    if not has_z:
        body["error_3d_note"] = "the estimates carry no z: only the 2-D error is defined"
    path = out / "score.json"
    tmp = out / ".score.json.tmp"
    tmp.write_text(json.dumps(_json_safe(body), indent=2, allow_nan=False) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path
