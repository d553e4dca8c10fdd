"""Depth prior for new features (seed 000, eq. 16 and section II.D).

The paper initialises the inverse depth "such that the database point is initialised at the best
estimate of the altitude of the terrain under the vehicle": ``rho = |h_z^i| / |p_z|`` (eq. 16), the
inverse range along the unit NED ray ``h^i`` to flat ground at altitude 0. Here the ground
altitude is a parameter (``TerrainConfig.default_ground_alt_m``) and the terrain map may supply a
better prior through a :data:`DepthPrior` callable (a ray cast into the map).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

DepthPrior = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``prior(origin_ned (3,), unit_rays_ned (N, 3)) -> range_m (N,)`` along each ray; NaN = unknown."""


def flat_ground_ranges(
    origin_ned: np.ndarray, rays_ned: np.ndarray, ground_alt_m: float, min_range_m: float, max_range_m: float
) -> np.ndarray:
    """Range along unit rays (N, 3) from ``origin_ned`` (3,) to the plane ``h = ground_alt_m`` -> (N,).

    Generalises eq. 16: ``range = (h_cam - h_ground) / ray_down``. Rays that do not reach the ground
    (pointing at or above the horizon, or a camera at or below the ground) get ``max_range_m`` (a
    far, weak prior); every range is clipped to ``[min_range_m, max_range_m]``.
    """
    rays_ned = np.asarray(rays_ned, dtype=float).reshape(-1, 3)
    height = -float(origin_ned[2]) - ground_alt_m
    down = rays_ned[:, 2]
    ranges = np.divide(height, down, out=np.full(len(down), float(max_range_m)), where=(down > 1e-9) & (height > 0.0))
    return np.clip(ranges, min_range_m, max_range_m)


def prior_ranges(
    prior: DepthPrior | None,
    origin_ned: np.ndarray,
    rays_ned: np.ndarray,
    ground_alt_m: float,
    min_range_m: float,
    max_range_m: float,
) -> tuple[np.ndarray, int]:
    """Ranges (N,) along unit rays (N, 3) from the prior, falling back to flat ground.

    Returns the ranges and how many rays used the fallback. The prior is an input from another part
    of the service: if it raises, returns the wrong shape, or gives NaN / non-positive values, the
    affected rays use :func:`flat_ground_ranges` (a fault in the terrain map must not stop mapping).
    ``+inf`` from the prior means "nothing along this ray" and becomes ``max_range_m``.
    """
    rays_ned = np.asarray(rays_ned, dtype=float).reshape(-1, 3)
    fallback = flat_ground_ranges(origin_ned, rays_ned, ground_alt_m, min_range_m, max_range_m)
    if prior is None or len(rays_ned) == 0:
        return fallback, 0
    try:
        ranges = np.asarray(prior(np.asarray(origin_ned, float).copy(), rays_ned.copy()), dtype=float)
    except Exception:  # noqa: BLE001 - any fault in the prior degrades to the flat-ground prior
        return fallback, len(rays_ned)
    if ranges.shape != (len(rays_ned),):
        return fallback, len(rays_ned)
    ranges = np.where(np.isposinf(ranges), max_range_m, ranges)
    bad = ~np.isfinite(ranges) | (ranges <= 0.0)
    ranges = np.where(bad, fallback, np.clip(ranges, min_range_m, max_range_m))
    return ranges, int(bad.sum())
