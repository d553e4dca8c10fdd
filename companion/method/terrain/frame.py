"""The map's vertical frame kept on the navigation's (docs/terrain.md, "The navigation's frame").

The map lives in the frame of the autopilot's estimate, and the estimate's altitude wanders: a
barometer drifts, an EKF's vertical error moves by a metre over a minute (0.8 m sigma, 60 s in the
simulator's ``ekf`` model). A cell made on one pass holds the ground in the frame of that pass;
seen again a lap later, its ground comes back shifted by the change of the navigation's error in
between, the same shift for every cell, and the top-surface rule takes a shift upwards as a higher
surface (two points above a cell raise it) and ignores one downwards (a wall's face). The map
then holds the highest frame it was ever seen in, and the vehicle flies that much too high.

A shift shared by every old cell is what the points say when they fall on cells made long enough
ago for the navigation to have moved. For each such pair (a point and a cell with evidence,
updated at least ``min_age_s`` before), the residual ``rho = h_point - h_cell`` is the frame's
change plus the pair's noise (and, near a wall or a roof's edge, the difference of two surfaces).
Over the pairs of the last ``window_s`` seconds the weighted median ``m`` (each pair weighted by
its share of its point, so a point counts once) estimates the change: the median ignores a
minority of pairs on another surface however far off they are, which a mean would not. Once the
pairs hold ``min_points`` points and ``|m|`` exceeds ``deadband_m``, the whole map is moved by
``m`` (heights, pending heights, ceilings and floors alike: the whole map is one frame), and the
residuals kept in the window are re-expressed against the moved map.

Pairs further apart than ``max_offset_m`` are not the frame (the navigation does not move by that
much between two looks at a cell): they are left out. Cells made within ``min_age_s`` are in the
frame of the moment by construction: their residuals would say "no shift", and any bias of the
points against their own recent cells would walk the map away; they are left out too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The smallest value at which the cumulative weight (values sorted) reaches half the total:
    the minimiser of ``sum w_i |x - v_i|``. NaN for no positive weight."""
    v = np.asarray(values, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    total = w.sum()
    if len(v) == 0 or not total > 0:
        return float("nan")
    order = np.argsort(v, kind="stable")
    cum = np.cumsum(w[order])
    return float(v[order][np.searchsorted(cum, 0.5 * total)])


@dataclass
class FrameTracker:
    """Windowed weighted median of the residuals of points against old cells; says when and how
    far to move the map. Pure: the grid gives it the pairs and applies the shift it returns."""

    min_age_s: float = 20.0
    window_s: float = 3.0
    min_points: float = 10.0
    max_offset_m: float = 3.0
    deadband_m: float = 0.05
    shift_m: float = 0.0  # total the map has been moved by (m, up)
    shifts: int = 0  # how many times
    _t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _a: np.ndarray = field(default_factory=lambda: np.zeros(0))  # residual + shift_m at the time
    _w: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def update(self, t_s: float, residual_m: np.ndarray, weight: np.ndarray) -> float:
        """Take this batch's residuals (M,) of old pairs (already selected by age) with their
        weights (M,), at time ``t_s``; return the shift (m, up) to move the map by now, 0 if none."""
        r = np.asarray(residual_m, dtype=np.float64)
        w = np.asarray(weight, dtype=np.float64)
        keep = np.isfinite(r) & (np.abs(r) <= self.max_offset_m) & (w > 0)
        keep_old = self._t >= t_s - self.window_s
        self._t = np.concatenate([self._t[keep_old], np.full(np.count_nonzero(keep), float(t_s))])
        self._a = np.concatenate([self._a[keep_old], r[keep] + self.shift_m])
        self._w = np.concatenate([self._w[keep_old], w[keep]])
        if self._w.sum() < self.min_points:
            return 0.0
        m = weighted_median(self._a, self._w) - self.shift_m
        if not abs(m) > self.deadband_m:
            return 0.0
        self.shift_m += m
        self.shifts += 1
        return m
