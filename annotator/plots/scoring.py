"""Plots of a score, for a paper: error CDF, error over time, and estimates with the truth on
the floor plan (the built-in tetam plan when the positions fall inside it). matplotlib's
object API, files only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.core.scoring import Score, Truth
from annotator.plots.scale import metre_scale_bar


def _site_plan():  # -> (MapParams, png path) or None
    from bgt_core.formats.devices import read_par
    from bgt_core.sites import site_dir

    d = site_dir("tetam")
    return read_par(d / "tetam.par"), d / "tetam.png"


def plot_cdf(path: Path, s: Score) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4.2), layout="constrained")
    ax = fig.subplots()
    for err, label, colour in ((s.error_2d, "2-D", "tab:blue"), (s.error_3d, "3-D", "tab:orange")):
        e = np.sort(err[np.isfinite(err)])
        if e.size:
            ax.step(e, np.arange(1, e.size + 1) / e.size, where="post", label=label, color=colour)
    summ = s.summary_2d
    for q, v in ((0.5, summ.ce50), (0.75, summ.ce75), (0.95, summ.ce95)):
        if np.isfinite(v):
            ax.axvline(v, color="0.6", lw=0.8, ls=":")
            ax.text(v, q, f" CE{int(q * 100)} {v:.2f} m", fontsize=8, va="bottom")
    sig = s.truth_sigma[np.isfinite(s.truth_sigma)]
    if sig.size:
        ax.axvspan(0, float(np.median(sig)), color="0.85", label="truth 1-sigma (median)")
    ax.set(
        xlabel="position error (m)",
        ylabel="fraction of estimates",
        ylim=(0, 1.02),
        title="error CDF",
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.savefig(path, dpi=120)
    return path


def plot_error_over_time(path: Path, s: Score) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.6), layout="constrained")
    ax = fig.subplots()
    ok = np.isfinite(s.error_2d)
    t0 = s.t[ok][0] if ok.any() else (s.t[0] if len(s.t) else 0.0)
    ax.plot(s.t[ok] - t0, s.error_2d[ok], ".-", ms=2, lw=0.6, label="2-D error")
    ok3 = np.isfinite(s.error_3d)
    if ok3.any():
        ax.plot(s.t[ok3] - t0, s.error_3d[ok3], lw=0.6, alpha=0.6, label="3-D error")
    ax.set(
        xlabel="time since the first scored estimate (s)",
        ylabel="error (m)",
        title="error over time",
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")
    fig.savefig(path, dpi=120)
    return path


def plot_floor(path: Path, s: Score, est_position: np.ndarray, truth: Truth) -> Path:
    """Truth track and estimates, each estimate joined to the truth at its time by a thin line."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    params, png = _site_plan()
    est = np.asarray(est_position, dtype=float)
    tp = np.asarray(truth.position, dtype=float)
    pts = np.concatenate([est[:, :2], tp[:, :2]])
    pts = pts[np.isfinite(pts).all(axis=1)]
    x0, y0, x1, y1 = params.limits
    on_plan = (
        pts.size
        and (pts[:, 0] >= x0 - 1).all()
        and (pts[:, 0] <= x1 + 1).all()
        and (pts[:, 1] >= y0 - 1).all()
        and (pts[:, 1] <= y1 + 1).all()
    )

    def xy(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return params.world_to_pixel(p[:, 0], p[:, 1]) if on_plan else (p[:, 0], p[:, 1])

    fig = Figure(figsize=(7, 7.5), layout="constrained")
    ax = fig.subplots()
    if on_plan:
        import matplotlib.image

        img = matplotlib.image.imread(str(png))
        ax.imshow(img, zorder=0)
        metre_scale_bar(ax, params.parity, img.shape[1], img.shape[0])
    else:
        ax.set(xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ok = np.isfinite(s.error_2d)
    if ok.any():
        ex, ey = xy(est[ok])
        tx, ty = xy(s.truth_at_estimates[ok])
        segs = np.stack([np.column_stack([ex, ey]), np.column_stack([tx, ty])], axis=1)
        ax.add_collection(
            LineCollection(list(segs), colors="tab:red", linewidths=0.4, alpha=0.4, zorder=1)
        )
    gx, gy = xy(tp)
    ax.plot(gx, gy, color="black", lw=2, zorder=2, label="ground truth")
    fe = np.isfinite(est[:, :2]).all(axis=1)
    if fe.any():
        ex, ey = xy(est[fe])
        ax.plot(ex, ey, ".", ms=3, color="tab:blue", zorder=3, label="estimates")
    ax.set_title("estimates and ground truth" + (" on the floor plan" if on_plan else ""))
    ax.legend(loc="best", fontsize="small")
    fig.savefig(path, dpi=110)
    return path


def write_score_plots(
    out_dir: Path, s: Score, est_position: np.ndarray, truth: Truth
) -> dict[str, Path]:
    out_dir = Path(out_dir)
    return {
        "error_cdf": plot_cdf(out_dir / "error_cdf.png", s),
        "error_over_time": plot_error_over_time(out_dir / "error_over_time.png", s),
        "floor_plan": plot_floor(out_dir / "estimates_on_floor_plan.png", s, est_position, truth),
    }
