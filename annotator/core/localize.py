"""Two baseline BLE localizers on a radio map, as pure array code, so that scores on the
annotated data have something to be compared with.

Both work on one beacon's readings ``(t, sensor index, rssi)`` and a radio map: for every free
grid cell ``c`` and sensor ``s`` an RSSI histogram ``H[c, s, :]`` over 1-dB bins (NaN where the
map has none).

* ``knn``: weighted k-nearest neighbours on mean RSSI. Every ``step_s`` the readings of the last
  ``window_s`` seconds give a mean RSSI per sensor heard; the ``k`` cells whose mean map RSSI is
  nearest (root-mean-square difference over the sensors heard and mapped) are averaged with
  weights ``1 / (d + 1 dB)``. The estimate is stamped at the window's centre.
* ``grid-hmm``: a forward filter (hidden Markov model) on the grid, in the spirit of Daniş,
  Ersoy and Cemgil (Performance Evaluation 162, 2023). State: the free cells. Motion between
  steps: Gaussian in the distance between cell centres (sigma ``speed_mps * step_s``, at least
  half a cell). Observation: each reading's probability is the histogram bin of its RSSI in the
  cell's map for that sensor, mixed with a uniform floor (``floor``) so no single reading can
  veto a cell. The estimate after each step is the posterior mean, stamped at the step's end
  (it uses no reading after that time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist


@dataclass(frozen=True, slots=True)
class RadioMapArrays:
    centres: np.ndarray  # (C, 2) cell centres, metres
    sensors: tuple[str, ...]  # MACs, the second axis of hist
    edges: np.ndarray  # (K + 1,) bin edges, dBm
    hist: np.ndarray  # (C, S, K) probabilities; NaN rows where the map has no histogram
    cell: float

    @property
    def mean_rssi(self) -> np.ndarray:
        centres = 0.5 * (self.edges[:-1] + self.edges[1:])
        return self.hist @ centres  # (C, S), NaN where missing


@dataclass(frozen=True, slots=True)
class Readings:
    t: np.ndarray  # (N,) Unix seconds, sorted
    sensor: np.ndarray  # (N,) index into RadioMapArrays.sensors (-1: not in the map)
    rssi: np.ndarray  # (N,) dBm


@dataclass(frozen=True, slots=True)
class Estimates2D:
    t: np.ndarray
    xy: np.ndarray  # (M, 2); NaN where nothing could be estimated


def _steps(t: np.ndarray, step_s: float) -> np.ndarray:
    """Step end times: the steps ``[end - step, end)`` tile the readings from the first on."""
    if not len(t):
        return np.zeros(0)
    n = int(np.floor((t[-1] - t[0]) / step_s)) + 1
    return t[0] + step_s * np.arange(1, n + 1)


def knn(
    m: RadioMapArrays, r: Readings, *, k: int = 4, window_s: float = 2.0, step_s: float = 0.5
) -> Estimates2D:
    """Weighted k-nearest cells on mean RSSI; see the module docstring."""
    ends = _steps(r.t, step_s)
    mean_map = m.mean_rssi  # (C, S)
    s_count = len(m.sensors)
    keep = r.sensor >= 0
    t, s, v = r.t[keep], r.sensor[keep], r.rssi[keep].astype(float)
    lo = np.searchsorted(t, ends - window_s, side="left")
    hi = np.searchsorted(t, ends, side="left")
    xy = np.full((len(ends), 2), np.nan)
    k = max(1, min(k, len(m.centres)))
    for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
        if b <= a:
            continue
        sums = np.bincount(s[a:b], weights=v[a:b], minlength=s_count)
        cnt = np.bincount(s[a:b], minlength=s_count)
        heard = cnt > 0
        obs = sums[heard] / cnt[heard]
        diff = mean_map[:, heard] - obs
        ok = np.isfinite(diff)
        n_ok = ok.sum(axis=1)
        d = np.sqrt(np.where(ok, diff * diff, 0.0).sum(axis=1) / np.maximum(n_ok, 1))
        d[n_ok == 0] = np.inf
        if not np.isfinite(d).any():
            continue
        idx = np.argpartition(d, k - 1)[:k] if k < len(d) else np.arange(len(d))
        idx = idx[np.isfinite(d[idx])]
        w = 1.0 / (d[idx] + 1.0)
        xy[i] = (m.centres[idx] * w[:, None]).sum(axis=0) / w.sum()
    return Estimates2D(ends - window_s / 2, xy)


def transition_matrix(centres: np.ndarray, sigma_m: float) -> np.ndarray:
    """Row-stochastic (C, C): Gaussian in the distance between cell centres."""
    d2 = cdist(centres, centres, "sqeuclidean")
    a = np.exp(-0.5 * d2 / (sigma_m * sigma_m))
    return a / a.sum(axis=1, keepdims=True)


def reading_likelihoods(m: RadioMapArrays, floor: float = 0.05) -> np.ndarray:
    """(C, S, K) probability of a reading in each bin, mixed with a uniform floor; a cell with no
    histogram for a sensor gets the uniform value (it neither helps nor vetoes)."""
    k = m.hist.shape[2]
    h = np.where(np.isfinite(m.hist), m.hist, 1.0 / k)
    return (1.0 - floor) * h + floor / k


class GridHmmFilter:
    """The grid-HMM's forward filter, one step at a time (``grid_hmm`` runs it over a recording;
    the operator console runs it live): ``step`` predicts by the motion model, then weighs the
    step's readings (sensor indices, RSSI) by the map."""

    def __init__(
        self, m: RadioMapArrays, *, step_s: float = 0.5, speed_mps: float = 1.0, floor: float = 0.05
    ) -> None:
        self.m = m
        self.trans = transition_matrix(m.centres, max(speed_mps * step_s, m.cell / 2))
        self.loglik = np.log(reading_likelihoods(m, floor))  # (C, S, K)
        self.belief = np.full(len(m.centres), 1.0 / len(m.centres))
        self.seen = False  # nothing to say before the first reading

    def bins(self, rssi: np.ndarray) -> np.ndarray:
        """Histogram bin of each RSSI (-1 outside the map's range)."""
        k, edges = self.loglik.shape[2], self.m.edges
        v = np.asarray(rssi, dtype=float)
        b = np.searchsorted(edges, v, side="right") - 1
        b = np.where(v == edges[-1], k - 1, b)
        return np.where((b >= 0) & (b < k), b, -1)

    def step(self, sensors: np.ndarray, bins: np.ndarray) -> None:
        self.belief = self.belief @ self.trans
        ok = (np.asarray(sensors) >= 0) & (np.asarray(bins) >= 0)
        if ok.any():
            ll = self.loglik[:, np.asarray(sensors)[ok], np.asarray(bins)[ok]].sum(axis=1)
            post = np.log(np.maximum(self.belief, 1e-300)) + ll
            post = np.exp(post - post.max())
            self.belief = post / post.sum()
            self.seen = True

    def estimate(self) -> tuple[np.ndarray, float]:
        """Posterior mean (x, y) and its spread (rms distance of the belief from it), metres;
        NaN before the first reading."""
        if not self.seen:
            return np.full(2, np.nan), float("nan")
        mean = self.belief @ self.m.centres
        d2 = ((self.m.centres - mean) ** 2).sum(axis=1)
        return mean, float(np.sqrt(self.belief @ d2))


def grid_hmm(
    m: RadioMapArrays,
    r: Readings,
    *,
    step_s: float = 0.5,
    speed_mps: float = 1.0,
    floor: float = 0.05,
) -> Estimates2D:
    """Forward filter on the radio-map grid; see the module docstring."""
    ends = _steps(r.t, step_s)
    f = GridHmmFilter(m, step_s=step_s, speed_mps=speed_mps, floor=floor)
    keep = r.sensor >= 0
    t, s = r.t[keep], r.sensor[keep]
    b = f.bins(r.rssi[keep])
    inb = b >= 0
    t, s, b = t[inb], s[inb], b[inb]
    starts = np.searchsorted(t, ends - step_s, side="left")
    stops = np.searchsorted(t, ends, side="left")
    xy = np.full((len(ends), 2), np.nan)
    for i, (a, z) in enumerate(zip(starts, stops, strict=True)):
        f.step(s[a:z], b[a:z])
        if f.seen:
            xy[i] = f.estimate()[0]
    return Estimates2D(ends, xy)
