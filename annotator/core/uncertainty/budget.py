"""The total: every part of a row's sigma_m in quadrature, its budget by part, and the sync's
share of a labelled reading's sigma."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from annotator.core.uncertainty.records import RowUncertainty, UncertaintySettings, VideoClock

if TYPE_CHECKING:
    pass


def total_sigma(
    smoother_m: np.ndarray, u: RowUncertainty, settings: UncertaintySettings | None = None
) -> dict[str, np.ndarray]:
    """The trajectory's sigma columns: sigma_m (all parts in quadrature) and each part."""
    s = settings or UncertaintySettings()
    sm = np.asarray(smoother_m, float)
    params = u.params_m
    blur = np.nan_to_num(u.blur_m, nan=0.0)
    floor = np.full(len(sm), s.unmodelled_m)
    total = np.sqrt(sm**2 + np.nan_to_num(params, nan=0.0) ** 2 + blur**2 + floor**2)
    total[~np.isfinite(sm)] = np.nan
    out = {
        "sigma_m": total,
        "sigma_smoother_m": sm,
        "sigma_params_m": params,
        "sigma_blur_m": u.blur_m,
        "sigma_unmodelled_m": np.where(np.isfinite(sm), floor, np.nan),
        "smear_px": u.smear_px,
    }
    return out


# sigma_m's parts (total_sigma's columns) in the words a user reads them in.
SIGMA_PARTS = {
    "sigma_params_m": "map, rig and lenses",
    "sigma_smoother_m": "frame noise",
    "sigma_blur_m": "motion blur",
    "sigma_unmodelled_m": "unmodelled",
}


@dataclass(frozen=True, slots=True)
class SigmaBudget:
    """What sigma_m says of a trajectory: its median and p95 over the posed rows, and the median
    of each part (per-axis 1-sigma, m)."""

    median_m: float
    p95_m: float
    parts_m: dict[str, float]  # SIGMA_PARTS' columns present in the trajectory

    @property
    def largest(self) -> str:
        """The column of the part that weighs most."""
        return max(self.parts_m, key=lambda k: self.parts_m[k])

    def as_dict(self) -> dict[str, object]:
        return {"median": self.median_m, "p95": self.p95_m, "parts_median": dict(self.parts_m)}


def sigma_budget(quality: Mapping[str, np.ndarray]) -> SigmaBudget | None:
    """sigma_m's median, p95 and parts over the rows where it is finite; None without any."""
    if "sigma_m" not in quality:
        return None
    total = np.asarray(quality["sigma_m"], float)
    ok = np.isfinite(total)
    if not ok.any():
        return None
    parts = {
        col: float(np.nanmedian(np.asarray(quality[col], float)[ok]))
        for col in SIGMA_PARTS
        if col in quality and np.isfinite(np.asarray(quality[col], float)[ok]).any()
    }
    return SigmaBudget(float(np.median(total[ok])), float(np.percentile(total[ok], 95)), parts)


def sync_time_sigma(clocks: Mapping[str, VideoClock], t_rssi: np.ndarray) -> np.ndarray:
    """1-sigma uncertainty (s) of each RSSI time against the video clock: the worst camera's clock
    map at that time (``annotator.core.sync.ClockMap.sigma_at``); 0 where no camera states one (manual
    sync states none)."""
    t = np.asarray(t_rssi, dtype=float)
    out = np.zeros(t.shape)
    for cm in clocks.values():
        sig = np.asarray(cm.sigma_at(cm.to_video(t)), dtype=float)
        out = np.fmax(out, np.broadcast_to(sig, t.shape))
    return out
