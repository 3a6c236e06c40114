"""The console's live position estimate of each beacon: the grid-HMM baseline of the annotator
(annotator.core.localize.GridHmmFilter) on a radio map, stepped once a second with the last RSSI
of the beacon at every sensor that heard it in that second. Needs the annotator extra."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bgt_core.control_messages import CollectorStatus


class LivePositions:
    """One forward filter per beacon of the radio map (the ``top`` most mapped, or ``beacons``)."""

    def __init__(
        self,
        radiomap: str | Path,
        beacons: Sequence[str] = (),
        *,
        step_s: float = 1.0,
        speed_mps: float = 1.0,
        top: int = 8,
    ) -> None:
        try:  # the annotator extra: an optional part of the console
            import numpy

            from annotator.core.localize import GridHmmFilter
            from annotator.io.localize import (
                radiomap_arrays,
                radiomap_beacons,
                read_radiomap_grids,
            )
        except ImportError as e:
            raise ModuleNotFoundError(
                f"--radiomap needs the annotator extra ({e.name} is missing)", name=e.name
            ) from None

        self._np = numpy

        grids = read_radiomap_grids(radiomap)
        mapped = radiomap_beacons(grids)
        which = list(beacons) or [b for b, _ in mapped.most_common(top)]
        unknown = [b for b in which if b not in mapped]
        if unknown:
            raise ValueError(f"radio map {radiomap}: no cell for beacon(s) {', '.join(unknown)}")
        self.filters = {
            b: GridHmmFilter(radiomap_arrays(grids, b), step_s=step_s, speed_mps=speed_mps)
            for b in which
        }

    def update(self, status: CollectorStatus) -> dict[str, dict[str, Any]]:
        """Step every filter with this second's readings; {beacon: {x, y, sigma_m}} of those
        estimated so far (the site frame, metres)."""
        out: dict[str, dict[str, Any]] = {}
        for beacon, f in self.filters.items():
            index = {mac: i for i, mac in enumerate(f.m.sensors)}
            sensors, rssi = [], []
            for agent in status.agents.values():
                for mac, s in agent.sensors.items():
                    value = s.beacon_rssi.get(beacon)
                    if value is not None and mac in index:
                        sensors.append(index[mac])
                        rssi.append(value)
            np = self._np
            f.step(np.asarray(sensors, dtype=int), f.bins(np.asarray(rssi, dtype=float)))
            xy, spread = f.estimate()
            if math.isfinite(spread):
                out[beacon] = {
                    "x": round(float(xy[0]), 3),
                    "y": round(float(xy[1]), 3),
                    "sigma_m": round(spread, 3),
                    "sensors": len(sensors),
                }
        return out
