"""Pull-up / push-over terrain avoidance (seed 000, section III; derivation in docs/avoidance.md).

Along the horizontal direction of travel, every mapped cell within the miss distance imposes a lower bound
on the climb rate now: the least climb rate from which a vertical profile with acceleration
``+-a_c`` (and the climb-rate limit) still reaches ``h_i + h_c`` by the time the vehicle comes
within the miss distance of the cell, arriving with zero vertical speed (a smooth pull-up). The
command is the largest of these bounds and of the nominal-altitude command, clipped to the
vehicle's climb and descent limits. Signs: altitude ``h`` and climb rate ``w`` are up-positive.

The height the law takes for each cell (:func:`law_heights`) reads the map's evidence as such: a
risk quantile of the height of the surface the cell belongs to (:func:`local_surface`), never
above the free space a line of sight proved above the cell, never below the least a feature not
yet converged says the terrain there reaches.

Functions in derivation order: :func:`time_to_go` (Delta t_i), :func:`height_restriction`
(eq. 18), :func:`minimum_climb_rate` (eqs. 19-20 completed with the push-over and the climb-rate
limit), :func:`nominal_climb_rate` (return to the nominal altitude), :func:`margin_height` (a cell
as high as its estimate plus k sigma), :func:`fill_unknown`, :func:`local_surface` (a cell estimated
with the surface it belongs to), :func:`law_heights`, the speed limit for a late obstacle
(:func:`climb_time`, :func:`brake_speed`, :func:`climb_speed_limit`), the speed limit for what the
camera cannot see yet (:func:`view_distance`, :func:`view_speed_limit`) and how far beyond it lines of
sight have proven the way low (:func:`known_horizon`), then :class:`PullUpLaw`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from companion.config import AvoidanceConfig
from companion.method.terrain.grid import Corridor, TerrainGrid


def entry_distance(along_m: np.ndarray, cross_m: np.ndarray, radius_m: float) -> np.ndarray:
    """Distance (m) along track before the vehicle, flying straight, first comes within
    ``radius_m`` of each cell centre (``along``/``cross`` relative to its track); <= 0 if it already
    is. All arrays (K,)."""
    return along_m - np.sqrt(np.maximum(radius_m * radius_m - cross_m * cross_m, 0.0))


def time_to_go(along_m: np.ndarray, cross_m: np.ndarray, radius_m: float, speed_mps: float) -> np.ndarray:
    """Delta t_i (s): time until the vehicle, flying straight at ``speed_mps``, first comes within
    ``radius_m`` of each cell centre (``along``/``cross`` relative to its track), 0 if already
    within it. At hover speed nothing ahead ever arrives: infinity, except cells already within
    reach (0). All arrays (K,)."""
    entry = entry_distance(along_m, cross_m, radius_m)
    if speed_mps <= 0.0:
        return np.where(entry <= 0.0, 0.0, np.inf)
    return np.maximum(entry, 0.0) / speed_mps


def height_restriction(h_cell: np.ndarray, clearance_m: float, accel: float, dt: np.ndarray) -> np.ndarray:
    """Eq. 18: ``h_min_i = h_i + h_c - a_c dt_i^2 / 2``, the lowest altitude from which a climb
    starting level now at ``a_c`` still clears cell i by ``h_c`` when it arrives. (K,) arrays."""
    return h_cell + clearance_m - 0.5 * accel * dt * dt


def minimum_climb_rate(gain_m: np.ndarray, dt: np.ndarray, accel: float, max_climb: float = math.inf) -> np.ndarray:
    """Least climb rate now (m/s, up) that still reaches ``gain_m = h_i + h_c - h`` above the current
    altitude by ``dt`` with zero vertical speed, under acceleration ``+-accel`` and climb rate at
    most ``max_climb``. (K,) arrays; ``dt`` may be inf (never arrives: no bound, -inf).

    With ``s = a dt`` (docs/avoidance.md):

    * ``H <= -s^2/(2a)``, far above: push-over bound ``w = -sqrt(2 a |H|)`` (descend no faster
      than can be arrested at ``h_i + h_c``).
    * ``-s^2/(2a) < H <= s^2/(2a)``: bang-bang pull-up, eq. 19, ``w = s - sqrt(2 s^2 - 4 a H)``,
      whose peak climb rate is ``(s + w)/2``; when that exceeds ``max_climb`` the profile cruises
      at the limit and ``w = W - sqrt(2 a (W dt - H) - W^2)``.
    * Otherwise the smooth pull-up is no longer possible (eq. 20): ``w = sqrt(2 a H)``, the climb
      rate that stops exactly at the restriction. Eq. 20's ``w = a dt`` is the same value on the
      boundary but falls to zero as ``dt -> 0``, which would stop a vehicle still below the
      restriction from climbing when it is over the obstacle.
    """
    h, dt = np.broadcast_arrays(np.asarray(gain_m, dtype=np.float64), np.asarray(dt, dtype=np.float64))
    a = float(accel)
    never = ~np.isfinite(dt)
    t = np.where(never, 0.0, dt)
    s = a * t
    reach = s * s / (2.0 * a)
    # All three branches on the whole batch, then pick: fewer passes than masked assignment.
    w = np.where(
        h <= -reach,
        -np.sqrt(np.maximum(-2.0 * a * h, 0.0)),  # push-over braking curve
        np.where(
            h > reach,
            np.sqrt(np.maximum(2.0 * a * h, 0.0)),  # saturated: climb that stops at the restriction
            s - np.sqrt(np.maximum(2.0 * s * s - 4.0 * a * h, 0.0)),  # eq. 19, bang-bang
        ),
    )
    capped = (np.abs(h) <= reach) & (0.5 * (s + w) > max_climb)
    if capped.any():
        W = max_climb
        hc, tc = h[capped], t[capped]
        disc = 2.0 * a * (W * tc - hc) - W * W
        # Accelerate to the limit, cruise, brake; beyond its reach the climb is saturated.
        w[capped] = np.where(disc >= 0.0, W - np.sqrt(np.maximum(disc, 0.0)),
                             np.maximum(np.sqrt(2.0 * a * np.maximum(hc, 0.0)), W))
    w[never] = -np.inf
    return w


def nominal_climb_rate(error_m: float, accel: float, time_constant_s: float) -> float:
    """Climb rate towards the nominal altitude (``error = h_nom - h``, m): the braking curve
    ``sign(e) (sqrt(2 a |e| + (a tau)^2) - a tau)``, which needs at most ``a`` to follow (no
    overshoot from an acceleration-limited vehicle) and is linear, ``e / tau``, near the target."""
    at = accel * time_constant_s
    return math.copysign(math.sqrt(2.0 * accel * abs(error_m) + at * at) - at, error_m)


@dataclass(frozen=True, slots=True)
class AvoidanceCommand:
    """One output of the law (altitudes up, local frame).

    climb_rate_mps: commanded climb rate, clipped to [-max_descent, max_climb].
    nominal_climb_mps: what the nominal-altitude command alone asks.
    limiting_cell_ne: centre (north, east) of the cell that set the command, None if nominal did.
    limiting_height_m: the height the law took for that cell (:func:`law_heights`); NaN if none.
    time_to_go_s: Delta t of that cell (NaN if none).
    required_alt_m: eq. 18, h_min of that cell (NaN if none).
    engaged: an obstacle demands more than the nominal command.
    unknown_cells_ahead: corridor cells with no evidence and no mapped cell near enough to stand in.
    holding_over_unknown: a descent held because the ground below is unseen, or seen (lines of
        sight, the ground flown over) no lower than the clearance below the vehicle.
    speed_limit_mps: the horizontal speed the vehicle must not exceed: the least of
        :func:`climb_speed_limit` (mapped terrain ahead) and :func:`view_speed_limit` (inf: none,
        both off, or hovering).
    view_distance_m: how far ahead the camera sees all terrain that would need a climb
        (:func:`view_distance`; inf: the view reaches the horizon, or unknown).
    view_speed_limit_mps: the speed from which the vehicle can still stop for terrain first seen
        ``view_distance_m`` ahead, or before ``known_horizon_m`` where that is farther
        (:func:`view_speed_limit`; inf: none, off, or hovering).
    limiting_source_ne: when the limiting cell is unmapped, the centre (north, east) of the mapped
        cell it stands in for (docs/avoidance.md, "Unmapped cells"); None when the limiting cell is
        mapped, or counts at its own floor or ceiling.
    known_horizon_m: how far along track the vehicle can fly before it comes within the miss
        distance of terrain beyond the view that no line of sight has proven low
        (:func:`known_horizon`); the view speed limit stops before the farther of it and the view
        distance. NaN: not computed (the option or the view limit off, hovering, no view).
    ground_reference_m: the ground the nominal altitude stood on (:func:`ground_reference`; 0: the
        local frame's zero); the nominal command aimed at it + the nominal altitude.
    """

    climb_rate_mps: float
    nominal_climb_mps: float
    limiting_cell_ne: tuple[float, float] | None
    limiting_height_m: float
    time_to_go_s: float
    required_alt_m: float
    engaged: bool
    unknown_cells_ahead: int
    holding_over_unknown: bool = False
    speed_limit_mps: float = math.inf
    view_distance_m: float = math.inf
    view_speed_limit_mps: float = math.inf
    limiting_source_ne: tuple[float, float] | None = None
    known_horizon_m: float = math.nan
    ground_reference_m: float = 0.0


def stand_in_source(along_m: np.ndarray, height_m: np.ndarray, mapped: np.ndarray, i: int, fill_m: float,
                    cell_m: float, hover: bool) -> int:
    """The mapped cell an unmapped cell ``i`` stands in for (:func:`fill_unknown`): the index of the
    highest of ``height_m`` among the ``mapped`` cells within ``fill_m`` along track of it (by the
    same cells of ``cell_m`` along track), or among all of them at hover; -1 when there is none.
    along_m, height_m, mapped: (K,) sorted along track."""
    candidates = mapped.copy()
    if not hover:
        bins, reach = fill_window(along_m, fill_m, cell_m)
        candidates &= np.abs(bins - bins[i]) <= reach
    if not candidates.any():
        return -1
    idx = np.flatnonzero(candidates)
    return int(idx[np.argmax(height_m[idx])])


def ground_below(grid: TerrainGrid, position_ne: np.ndarray, radius_m: float,
                 direction_ne: np.ndarray | None = None) -> tuple[float, float, float]:
    """What the map knows of the cells below the vehicle: those whose centre lies within ``radius_m``
    of it (hover), or, moving along the unit ``direction_ne``, those of the ground it has just flown
    over (``radius_m`` back along track, ``radius_m`` either side). Looking back and not around: at
    the far edge of a plain roof the mapped ground ahead would otherwise fill the disc before the
    vehicle has left the roof.

    Returns ``(mapped, seen, top)``: the fraction of those cells holding evidence; the fraction
    holding evidence or crossed by a line of sight (a ceiling); and the highest ceiling of the cells
    crossed but not mapped (-inf when none): the most the terrain there may hold."""
    if direction_ne is None:
        disc = grid.corridor(position_ne, np.array([1.0, 0.0]), 0.0, radius_m)
        inside = np.hypot(disc.north_m - position_ne[0], disc.east_m - position_ne[1]) <= radius_m
    else:
        disc = grid.corridor(position_ne, -np.asarray(direction_ne, dtype=np.float64), radius_m, radius_m)
        inside = (disc.along_m >= -0.5 * grid.cell_size_m) & (disc.along_m <= radius_m)
    total = int(np.count_nonzero(inside))
    if not total:
        return 0.0, 0.0, -math.inf
    mapped = inside & np.isfinite(disc.height_m)
    ceiling = disc.ceiling_m if disc.ceiling_m is not None else np.full(len(inside), np.inf)
    crossed = inside & ~mapped & np.isfinite(ceiling)
    top = float(ceiling[crossed].max()) if crossed.any() else -math.inf
    return (float(np.count_nonzero(mapped)) / total, float(np.count_nonzero(mapped | crossed)) / total, top)


def margin_height(height_m: np.ndarray, variance: np.ndarray, k: float) -> np.ndarray:
    """The risk quantile of each cell's height: ``h + k sqrt(variance)`` per cell (K,) (NaN stays
    NaN). The clearance is meant above the true terrain, and the map only estimates it: a cell
    known to +-0.6 m is, with k = 2, taken 1.2 m higher (the true height lies below with about 98 %
    probability for a Gaussian estimate). Disputed cells (points far below the top, which widen the
    variance: docs/terrain.md) get more margin, well-observed ground less."""
    if k <= 0.0:
        return height_m
    with np.errstate(invalid="ignore"):
        return height_m + k * np.sqrt(variance)


def fill_window(along_m: np.ndarray, fill_m: float, cell_m: float) -> tuple[np.ndarray, int]:
    """The along-track window an unmapped cell takes its stand-in from (:func:`fill_unknown`,
    :func:`stand_in_source`): each cell's bin of ``cell_m`` along track from the first (K,), and
    how many bins either side ``fill_m`` reaches. along_m (K,) sorted along track."""
    return np.floor((along_m - along_m[0]) / cell_m).astype(np.int64), int(math.ceil(fill_m / cell_m))


def fill_unknown(along_m: np.ndarray, height_m: np.ndarray, fill_m: float, cell_m: float, hover: bool) -> np.ndarray:
    """Heights with unmapped cells (NaN) assumed as high as the highest mapped cell within
    ``fill_m`` along track (a gap between two points of a roof is roof, not ground at zero); at
    hover, as high as the highest mapped cell around. NaN stays where nothing mapped is near.
    along_m, height_m: (K,) sorted along track."""
    h = height_m.copy()
    unknown = np.isnan(h)
    if not unknown.any() or unknown.all():
        return h
    if hover:
        h[unknown] = np.max(h[~unknown])
        return h
    bins, reach = fill_window(along_m, fill_m, cell_m)
    n_bins = int(bins[-1]) + 1
    peak = np.full(n_bins, -np.inf)
    np.maximum.at(peak, bins[~unknown], h[~unknown])
    padded = np.concatenate([np.full(reach, -np.inf), peak, np.full(reach, -np.inf)])
    window = peak.copy()
    for k in range(2 * reach + 1):
        np.maximum(window, padded[k : k + n_bins], out=window)
    stand_in = window[bins[unknown]]
    h[unknown] = np.where(np.isfinite(stand_in), stand_in, np.nan)
    return h


@functools.lru_cache(maxsize=8)
def disc_offsets(r: int) -> tuple[np.ndarray, np.ndarray]:
    """The cell offsets (rows, columns) of a disc of radius ``r`` cells, ``di^2 + dj^2 <= r^2``, row by
    row (the order :func:`local_surface` adds them in). Read-only arrays."""
    di, dj = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    inside = di * di + dj * dj <= r * r
    di, dj = di[inside], dj[inside]
    di.flags.writeable = dj.flags.writeable = False
    return di, dj


def local_surface(north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray, variance: np.ndarray,
                  cell_m: float, radius_m: float, outlier_sigma: float, min_cells: int = 3,
                  max_step_m: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each mapped cell's height estimated together with the mapped cells within ``radius_m``
    around it, as far as they are one surface (docs/avoidance.md, "The surface a cell belongs to").

    A cell with one point knows its height to its point's sigma (0.8 m at convergence); its
    neighbours on the same surface know theirs as well, and the law, which takes the highest of a
    thousand cells ahead, would otherwise fly over the noisiest of them. But a surface is not
    flat: tree crowns, rubble, a roof's edge differ from cell to cell by more than their sigmas say.
    The disc ``D`` of ``n`` mapped cells (the cell included) is modelled as ``h_j = m + r_j + e_j``:
    a common height ``m``, the cell's own relief ``r_j ~ N(0, tau^2)`` and its estimate's error
    ``e_j ~ N(0, v_j)``. The relief is estimated from the disc's scatter (DerSimonian-Laird):
    with ``w_j = 1 / v_j``, ``Q = sum w_j (h_j - m_w)^2`` (``m_w`` their weighted mean) and
    ``C = sum w_j - sum w_j^2 / sum w_j``::

        tau^2 = max(0, (Q - (n - 1)) / C)

    The neighbours alone (``j != i``) then give ``m_-`` = their mean weighted by
    ``1 / (v_j + tau^2)`` with the variance ``V_- = 1 / sum 1 / (v_j + tau^2)``, a prior on the
    cell of mean ``m_-`` and variance ``tau^2 + V_-``, which the cell's own estimate updates::

        1 / v' = 1 / v_i + 1 / (tau^2 + V_-),    h' = v' (h_i / v_i + m_- / (tau^2 + V_-))

    Where the scatter is what the sigmas explain (``tau = 0``) that is the information-weighted mean
    of the disc, variance ``1 / sum w_j``; where the relief dominates (``tau^2 >> v_i``) the cell
    keeps about its own ``h_i``, ``v_i``. A cell that stands out of its neighbours,
    ``|h_i - m_-| > outlier_sigma sqrt(v_i + tau^2 + V_-)`` (a mast, a wall's top, an obstacle's
    first point), keeps its own height and variance; so does a cell more than ``max_step_m`` from
    ``m_-`` however uncertain it is (the first point of an obstacle is uncertain too), and a cell
    with fewer than ``min_cells`` mapped cells in its disc.

    north_m, east_m: (K,) cell centres on the grid of ``cell_m``; height_m (K,) NaN unmapped;
    variance (K,). Returns (height, variance, fused) (K,): the fused cells' ``h'`` and ``v'``, the
    others' own values, and which were fused."""
    h = np.asarray(height_m, dtype=np.float64)
    v = np.asarray(variance, dtype=np.float64)
    k = len(h)
    fused = np.zeros(k, dtype=bool)
    known = np.isfinite(h) & np.isfinite(v) & (v > 0)
    r = int(math.floor(radius_m / cell_m + 1e-9)) if radius_m > 0 else 0
    if r < 1 or np.count_nonzero(known) < min_cells:
        return h, v, fused
    i = np.rint((north_m - north_m.min()) / cell_m).astype(np.int64) + r
    j = np.rint((east_m - east_m.min()) / cell_m).astype(np.int64) + r
    rows, cols = int(i.max()) + r + 1, int(j.max()) + r + 1
    hk, vk = h[known], v[known]
    # Each mapped cell's disc as flat indices into the corridor's bounding box padded by r, then as
    # rows of the mapped cells' tables: only the mapped cells are read (a diagonal corridor's
    # bounding box is mostly empty), and a disc's sum adds its offsets one after the other.
    at = i[known] * cols + j[known]
    di, dj = disc_offsets(r)
    shifts = di * cols + dj
    discs = at[None, :] + shifts[:, None]  # (offsets, mapped cells)
    w_k = 1.0 / vk
    wh_k = w_k * hk
    # Row m of the tables is mapped cell m; their last row, of no weight, stands for unmapped cells.
    row = np.full(rows * cols, len(at))
    row[at] = np.arange(len(at))
    disc_rows = row.take(discs)
    # The disc's fixed-effect sums, for the relief: n, sum w, sum w h, sum w h^2, sum w^2.
    terms = np.zeros((len(at) + 1, 5))
    terms[:-1] = np.stack([np.ones_like(hk), w_k, wh_k, wh_k * hk, w_k * w_k], axis=1)
    s_n, s_w, s_wh, s_whh, s_ww = terms.take(disc_rows, axis=0).sum(axis=0).T
    q = np.maximum(s_whh - s_wh * s_wh / s_w, 0.0)
    c = s_w - s_ww / s_w
    with np.errstate(invalid="ignore", divide="ignore"):
        tau2 = np.where(c > 0, np.maximum((q - (s_n - 1.0)) / c, 0.0), 0.0)
    # The neighbours alone, weighted by 1 / (v_j + tau^2) of the cell's own disc.
    hv = np.empty((len(at) + 1, 2))
    hv[:-1, 0], hv[:-1, 1], hv[-1] = hk, vk, (0.0, np.inf)
    others = hv.take(disc_rows[shifts != 0], axis=0)  # (offsets but the centre, mapped cells, 2): h, v
    wn = 1.0 / (others[..., 1] + tau2)
    a0, a1 = wn.sum(axis=0), (wn * others[..., 0]).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m_others = a1 / a0
        prior_v = tau2 + 1.0 / a0
        agrees = (s_n >= min_cells) & (a0 > 0) & ((hk - m_others) ** 2 <= outlier_sigma**2 * (vk + prior_v))
        agrees &= np.abs(hk - m_others) <= max_step_m
        v_post = 1.0 / (1.0 / vk + 1.0 / prior_v)
        h_post = v_post * (hk / vk + m_others / prior_v)
    out_h, out_v = h.copy(), v.copy()
    idx = np.flatnonzero(known)[agrees]
    out_h[idx] = h_post[agrees]
    out_v[idx] = v_post[agrees]
    fused[idx] = True
    return out_h, out_v, fused


def law_heights(along_m: np.ndarray, corridor: Corridor, k_sigma: float, fill_m: float, cell_m: float,
                hover: bool, local_radius_m: float = 0.0, local_outlier_sigma: float = 2.0,
                local_max_step_m: float = math.inf) -> np.ndarray:
    """The height the law keeps its clearance above, per corridor cell (K,), sorted along track
    (docs/avoidance.md, "What a cell may hold"):

    * a mapped cell: its risk quantile ``h + k sigma`` (:func:`margin_height`, with the variance of
      the surface height its evidence gives, ``Corridor.height_variance``), but never above its
      ceiling (the lowest height a line of sight crossed it at: the terrain is below) nor below
      its estimate ``h``: ``max(h, min(h + k sigma, ceiling))``;
    * an unmapped cell: the highest mapped cell within ``fill_m`` along track stands in
      (:func:`fill_unknown`), never above the cell's own ceiling; NaN where nothing mapped is near;
    * every cell: at least its floor (the least the terrain reaches, from features not yet
      converged): ``max(., floor)``; an unmapped cell with a floor and nothing near counts at it.

    With ``local_radius_m > 0`` a mapped cell's ``h`` and variance are first those of the surface
    it belongs to (:func:`local_surface`, never across a step of more than ``local_max_step_m``).
    """
    h = corridor.height_m
    var = corridor.height_variance if corridor.height_variance is not None else corridor.variance
    n = len(h)
    ceiling = corridor.ceiling_m if corridor.ceiling_m is not None else np.full(n, np.inf)
    floor = corridor.floor_m if corridor.floor_m is not None else np.full(n, -np.inf)
    known = (corridor.count > 0) & np.isfinite(h)
    if local_radius_m > 0:
        h, var, _ = local_surface(corridor.north_m, corridor.east_m, np.where(known, h, np.nan), var, cell_m,
                                  local_radius_m, local_outlier_sigma, max_step_m=local_max_step_m)
    with np.errstate(invalid="ignore"):
        taken = np.where(known, np.fmax(h, np.fmin(margin_height(h, var, k_sigma), ceiling)), np.nan)
        taken = fill_unknown(along_m, taken, fill_m, cell_m, hover)
        taken = np.where(known | np.isnan(taken), taken, np.fmin(taken, ceiling))
    return np.fmax(taken, np.where(np.isfinite(floor), floor, np.nan))


def climb_time(gain_m: np.ndarray, climb_now_mps: float, accel: float, max_climb: float) -> np.ndarray:
    """Shortest time (s) until the altitude has risen by ``gain_m`` (K,), from the climb rate
    ``climb_now_mps``, with acceleration ``+-accel``, climb rate at most ``max_climb``, ending level
    (docs/avoidance.md, "Slowing for a late obstacle"); 0 where ``gain_m <= 0``. From level flight it
    is :func:`stopping_time`.

    Bang-bang from ``w0``: the peak rate ``w_p = sqrt(a H + w0^2 / 2)`` (the gain
    ``(w_p^2 - w0^2)/(2a) + w_p^2/(2a) = H``), reached in ``(w_p - w0)/a`` and lost in ``w_p/a``;
    above ``max_climb`` the profile cruises at the limit. A vehicle already climbing so fast that its
    braking distance ``w0^2/(2a)`` exceeds ``H`` passes ``H`` while braking, at
    ``(w0 - sqrt(w0^2 - 2 a H)) / a`` (it overshoots). A vehicle descending first stops: ``w0 < 0``
    costs the gain ``w0^2 / (2a)`` back and ``|w0|/a``."""
    h = np.asarray(gain_m, dtype=np.float64)
    a, w_max = float(accel), float(max_climb)
    w0 = min(float(climb_now_mps), w_max)
    extra_t = 0.0
    if w0 < 0.0:  # brake the descent first: lose w0^2/(2a) more, spend |w0|/a
        h = h + w0 * w0 / (2.0 * a)
        extra_t, w0 = -w0 / a, 0.0
    if w_max <= 0.0:
        return np.where(h > 0, np.inf, 0.0)
    wp = np.sqrt(np.maximum(a * h + 0.5 * w0 * w0, 0.0))
    free = (wp - w0) / a + wp / a
    with np.errstate(invalid="ignore"):  # an unlimited climb rate: the capped branch is never taken
        capped = (w_max - w0) / a + w_max / a + (h - (2.0 * w_max * w_max - w0 * w0) / (2.0 * a)) / w_max
    braking = (w0 - np.sqrt(np.maximum(w0 * w0 - 2.0 * a * h, 0.0))) / a
    t = np.where(w0 * w0 >= 2.0 * a * h, braking, np.where(wp <= w_max, free, capped)) + extra_t
    return np.where(np.asarray(gain_m) > 0, t, 0.0)


def brake_speed(distance_m: np.ndarray, decel: float, reaction_s: float) -> np.ndarray:
    """The highest horizontal speed (m/s) from which the vehicle stops within ``distance_m``: it
    flies on for ``reaction_s`` then brakes at ``decel``, ``v tau + v^2 / (2 a) = d``, so
    ``v = a (sqrt(tau^2 + 2 d / a) - tau)``; 0 where ``d <= 0``."""
    d = np.maximum(np.asarray(distance_m, dtype=np.float64), 0.0)
    a, tau = float(decel), float(reaction_s)
    return a * (np.sqrt(tau * tau + 2.0 * d / a) - tau)


def climb_speed_limit(entry_m: np.ndarray, height_m: np.ndarray, alt_m: float, climb_now_mps: float,
                      cfg: AvoidanceConfig) -> float:
    """The speed limit for mapped terrain the law cannot climb over in time (docs/avoidance.md,
    "Slowing for a late obstacle"): for every cell ahead whose height ``height_m`` (K,; the law's,
    :func:`law_heights`) + (1 - ``speed_limit_shortfall``) of the clearance lies above the vehicle,
    the vehicle must either make that climb before it comes within the miss distance of the cell,
    ``v <= entry / climb_time`` (``entry_m`` (K,): the distance along track to that point), or be
    able to stop first, ``v <= brake_speed(entry)``; the limit is the least over the cells of the
    larger of the two. A cell already within reach (entry <= 0) stops the vehicle until the climb is
    made. inf where nothing limits. Shortfalls within the tolerance are the law's to make up as it
    flies: the vehicle never brakes for a few centimetres of noise."""
    with np.errstate(invalid="ignore"):
        gain = height_m + cfg.clearance_m * (1.0 - cfg.speed_limit_shortfall) - alt_m
        tall = np.isfinite(gain) & (gain > 0.0)
    if not tall.any():
        return math.inf
    d = np.maximum(entry_m[tall], 0.0)
    t = climb_time(gain[tall], climb_now_mps, cfg.accel_mps2, cfg.max_climb_mps)
    with np.errstate(divide="ignore", invalid="ignore"):
        by_climb = np.where(t > 0, d / t, np.inf)
    return float(np.min(np.maximum(by_climb, brake_speed(d, cfg.brake_accel_mps2, cfg.reaction_time_s))))


def view_distance(depression_rad: float, cfg: AvoidanceConfig) -> float:
    """How far ahead (m, horizontally from the camera) the camera sees every terrain point high
    enough to need a climb (docs/avoidance.md, "What the camera can see"). The image's top row looks
    ``depression_rad`` below the horizontal, so at a distance d the camera sees terrain only up to
    ``h_cam - d tan(depression)``; terrain that needs a climb reaches above
    ``h - (1 - speed_limit_shortfall) h_c``, all of it in view while
    ``d <= (1 - s) h_c / tan(depression)``. inf when the top row looks level or up (NaN: unknown)."""
    if not math.isfinite(depression_rad) or depression_rad <= 0.0:
        return math.inf
    return cfg.clearance_m * (1.0 - cfg.speed_limit_shortfall) / math.tan(min(depression_rad, 0.5 * math.pi - 1e-9))


def view_speed_limit(view_distance_m: float, cfg: AvoidanceConfig) -> float:
    """The highest speed (m/s) from which terrain first seen ``view_distance_m`` ahead can still be
    stopped for (docs/avoidance.md, "What the camera can see"): the map holds it ``map_latency_s``
    after it enters the view, the vehicle flies on for ``reaction_time_s``, then brakes at
    ``brake_accel_mps2`` and must stop before it comes within the miss distance:
    :func:`brake_speed` of ``view_distance_m - miss_distance_m`` with the latency added to the
    reaction time. inf for an infinite distance; 0 when the camera sees less than the miss distance."""
    if not math.isfinite(view_distance_m):
        return math.inf
    return float(brake_speed(np.array([view_distance_m - cfg.miss_distance_m]), cfg.brake_accel_mps2,
                             cfg.reaction_time_s + cfg.map_latency_s)[0])


GROUND_MIN_CELLS = 10
"""The fewest mapped cells :func:`ground_reference` takes a median of."""


def ground_reference(height_m: np.ndarray, mapped: np.ndarray, distance_m: np.ndarray, radius_m: float,
                     limit_m: float, min_cells: int = GROUND_MIN_CELLS) -> float:
    """The height of the ground around the vehicle, local frame (docs/avoidance.md, "The ground the
    nominal altitude stands on"): the median of ``height_m`` (K,) over the ``mapped`` (K,) cells whose
    centres lie within ``radius_m`` of the vehicle (``distance_m`` (K,)), clipped to
    ``[-limit_m, limit_m]``. 0 (the local frame's zero, the ground the nominal altitude is given
    above) when ``radius_m`` or ``limit_m`` is 0 or fewer than ``min_cells`` such cells are mapped.
    The law takes the cells within ``radius_m`` of the vehicle's cell (:func:`disc_offsets`): ahead,
    behind and to the sides, one lookup of the grid.

    The map is built from the navigation's poses, so its ground carries the navigation's vertical
    error: where the altitude reads 1 m high, the ground is mapped 1 m high too, and the nominal
    altitude above the map's ground is the commanded height above the true ground. The median is
    the ground's, not an obstacle's, while obstacles cover less than half of the cells."""
    if radius_m <= 0.0 or limit_m <= 0.0:
        return 0.0
    near = np.asarray(mapped, dtype=bool) & (np.asarray(distance_m) <= radius_m)
    n = int(np.count_nonzero(near))
    if n < min_cells:
        return 0.0
    middle = np.partition(np.asarray(height_m, dtype=np.float64)[near], [(n - 1) // 2, n // 2])  # the median, without np.median's overhead
    return float(np.clip(0.5 * (middle[(n - 1) // 2] + middle[n // 2]), -limit_m, limit_m))


def ground_flown_over(grid: TerrainGrid, position_ne: np.ndarray, direction_ne: np.ndarray | None, radius_m: float,
                      min_cells: int = GROUND_MIN_CELLS) -> float | None:
    """The highest mapped cell of the ground just flown over (docs/avoidance.md, "Unmapped cells"):
    among the cells within ``radius_m`` behind the vehicle moving along the unit ``direction_ne``
    (a half disc; at hover, None, the disc around it), the largest height of those mapped; None when
    fewer than ``min_cells`` are, or ``radius_m`` is 0. Where the cells right below are too sparsely
    mapped to descend on, the ground flown over stands in for them, as the highest mapped cell
    within ``unknown_fill_m`` along track stands in for an unmapped cell of the corridor."""
    if radius_m <= 0.0:
        return None
    p = np.asarray(position_ne, dtype=np.float64).reshape(2)
    if direction_ne is None:
        disc = grid.corridor(p, np.array([1.0, 0.0]), 0.0, radius_m)
        inside = np.hypot(disc.north_m - p[0], disc.east_m - p[1]) <= radius_m
    else:
        disc = grid.corridor(p, -np.asarray(direction_ne, dtype=np.float64), radius_m, radius_m)
        inside = (disc.along_m >= -0.5 * grid.cell_size_m) & (np.hypot(disc.along_m, disc.cross_m) <= radius_m)
    mapped = inside & (disc.count > 0) & np.isfinite(disc.height_m)
    if np.count_nonzero(mapped) < min_cells:
        return None
    return float(disc.height_m[mapped].max())


def ground_band(cfg: AvoidanceConfig) -> float:
    """The band ``b`` (m) of :func:`soften_near_ground`: ``ground_band_m``, at most
    ``speed_limit_shortfall`` of the clearance (the shortfall the law already leaves to itself)."""
    return max(min(cfg.ground_band_m, cfg.speed_limit_shortfall * cfg.clearance_m), 0.0)


def soften_near_ground(height_m: np.ndarray, ground_m: float, band_m: float) -> np.ndarray:
    """The height the law keeps its clearance above, for terrain near the ground reference ``g``
    (docs/avoidance.md, "The ground the nominal altitude stands on"), with ``x = h - g``:

        h - b              x <= b        (the ground and its noise: one band lower)
        g + 2 (x - b)      b < x < 2 b   (a ramp: continuous at both ends)
        h                  x >= 2 b      (an obstacle: in full)

    The law's clearance over a cell falls short by ``b`` up to one band above the ground, by
    ``2 b - x`` on the ramp and by nothing from two bands up: at most ``b`` anywhere. NaN stays NaN;
    (K,) -> (K,)."""
    h = np.asarray(height_m, dtype=np.float64)
    if band_m <= 0.0:
        return h
    x = h - ground_m
    with np.errstate(invalid="ignore"):
        return np.where(x <= band_m, h - band_m, np.where(x < 2.0 * band_m, ground_m + 2.0 * (x - band_m), h))


def known_horizon(along_m: np.ndarray, cross_m: np.ndarray, ceiling_m: np.ndarray, radius_m: float, cell_m: float,
                  view_distance_m: float, danger_m: float, lookahead_m: float,
                  mapped_height_m: np.ndarray | None = None) -> float:
    """How far (m, along track) the vehicle can fly before it comes within ``radius_m`` of terrain
    that may need a climb and that the camera does not see now (docs/avoidance.md, "The known
    horizon"). Within ``view_distance_m`` the camera sees every such terrain (:func:`view_distance`);
    beyond it, a cell a line of sight crossed below ``danger_m`` (its ``ceiling_m``: the terrain
    there is lower) holds none, nor, given ``mapped_height_m`` (K,; NaN unmapped), a mapped cell
    the law takes at most ``danger_m`` high (its risk quantile: the map's evidence holds it low,
    and the law already stakes the clearance on that height). The horizon is the entry distance
    (:func:`entry_distance`) of the nearest cell reaching beyond the view (its centre within half a
    diagonal of ``cell_m`` of it, or past it) that neither proves, or of the corridor's end
    (``lookahead_m - radius_m``) when there is none. Corridor cells (K,): ``along_m`` and
    ``cross_m`` relative to the vehicle and its direction, ``ceiling_m`` (inf: no line of sight)."""
    beyond = along_m > view_distance_m - cell_m * math.sqrt(0.5)
    with np.errstate(invalid="ignore"):
        proven = ceiling_m <= danger_m
        if mapped_height_m is not None:
            proven |= mapped_height_m <= danger_m
        unproven = beyond & ~proven
    if not unproven.any():
        return max(lookahead_m - radius_m, 0.0)
    return max(float(entry_distance(along_m[unproven], cross_m[unproven], radius_m).min()), 0.0)


class PullUpLaw:
    """The avoidance law of seed 000, section III, on a :class:`TerrainGrid`."""

    def __init__(self, cfg: AvoidanceConfig) -> None:
        self.cfg = cfg

    def command(
        self, position_ned, velocity_ned, grid: TerrainGrid, nominal_alt_m: float | None = None,
        direction_ne=None, view_depression_rad: float | None = None,
    ) -> AvoidanceCommand:
        """Climb-rate command for a vehicle at ``position_ned`` (3,) moving at ``velocity_ned`` (3,).
        ``direction_ne`` (2,): the direction the vehicle means to fly (its route's leg), along which
        the corridor looks, at the speed over ground in that direction; None = along the velocity
        (below ``hover_speed_mps`` the look-ahead is then a disc around the vehicle).
        ``view_depression_rad``: how far below the horizontal the camera's highest line of sight
        ahead looks (:func:`companion.method.geometry.view_depression`); None = unknown: no view
        limit.

        ValueError on non-finite state (the caller must not command on it)."""
        cfg = self.cfg
        p = np.asarray(position_ned, dtype=np.float64).reshape(3)
        v = np.asarray(velocity_ned, dtype=np.float64).reshape(3)
        if not (np.isfinite(p).all() and np.isfinite(v).all()):
            raise ValueError("PullUpLaw.command: position and velocity must be finite")
        alt = -p[2]
        a = cfg.accel_mps2

        # The zone of a cell: within the miss distance of any point of the cell (half diagonal).
        radius = cfg.miss_distance_m + grid.cell_size_m * math.sqrt(0.5)
        speed = float(np.hypot(v[0], v[1]))
        intent = None
        if direction_ne is not None:
            d = np.asarray(direction_ne, dtype=np.float64).reshape(2)
            norm = float(np.hypot(d[0], d[1]))
            intent = d / norm if norm > 0 and math.isfinite(norm) else None
        hover = intent is None and speed < max(cfg.hover_speed_mps, 1e-9)
        fill = cfg.unknown_fill_m
        # The corridor starts `fill` behind the vehicle (and the hover disc is `fill` wider) so
        # that mapped cells just outside the zone can stand in for unmapped ones inside it.
        if hover:
            direction, speed_used = np.array([1.0, 0.0]), 0.0
            corr = grid.corridor(p[:2], direction, 0.0, radius + fill)
            corridor_along = corr.along_m
            zone = np.hypot(corr.north_m - p[0], corr.east_m - p[1]) <= radius
        else:
            direction = intent if intent is not None else v[:2] / speed
            speed_used = max(float(v[:2] @ direction), 0.0)  # the speed over ground along the intent
            corr = grid.corridor(p[:2] - fill * direction, direction, cfg.lookahead_m + fill, radius)
            corridor_along = corr.along_m - fill
            zone = (corridor_along >= 0.0) | (corridor_along * corridor_along + corr.cross_m * corr.cross_m <= radius * radius)
        ground = 0.0
        if cfg.ground_reference_radius_m > 0.0 and cfg.ground_reference_max_m > 0.0:
            c = grid.cell_size_m
            di, dj = disc_offsets(int(cfg.ground_reference_radius_m // c))
            centre = (np.floor(p[:2] / c) + 0.5) * c  # the vehicle's cell
            h_disc, _, count_disc = grid.height_at(centre[0] + di * c, centre[1] + dj * c)
            ground = ground_reference(h_disc, (count_disc > 0) & np.isfinite(h_disc), np.hypot(di, dj) * c,
                                      cfg.ground_reference_radius_m, cfg.ground_reference_max_m)
        nominal_above = cfg.nominal_alt_m if nominal_alt_m is None else float(nominal_alt_m)
        nominal = nominal_above + ground
        w_nom = nominal_climb_rate(nominal - alt, a, cfg.nominal_time_constant_s)
        corridor_heights = law_heights(corridor_along, corr, cfg.height_margin_sigma, fill, grid.cell_size_m, hover,
                                       cfg.local_radius_m, cfg.local_outlier_sigma, cfg.speed_limit_shortfall * cfg.clearance_m)
        band = ground_band(cfg)
        with np.errstate(invalid="ignore"):
            # Within a band of the ground and a nominal altitude at least the clearance above it:
            # the nominal command's to follow, never an obstacle (docs/avoidance.md).
            nominal_ground = (corridor_heights - ground <= band) if band > 0.0 and nominal_above >= cfg.clearance_m \
                else np.zeros(len(corridor_heights), bool)
        law_h = corridor_heights  # as the law takes each cell before the ground band: the known horizon's
        corridor_heights = soften_near_ground(corridor_heights, ground, band)
        heights = corridor_heights[zone]
        along, cross = corridor_along[zone], corr.cross_m[zone]
        north, east = corr.north_m[zone], corr.east_m[zone]
        unknown_left = int(len(heights) - np.count_nonzero(np.isfinite(heights)))
        considered = np.isfinite(heights) & ~nominal_ground[zone]

        best_w, idx, dt_i = -math.inf, None, math.nan
        if considered.any():
            sel = np.flatnonzero(considered)
            dt = time_to_go(along[sel], cross[sel], radius, speed_used)
            w = minimum_climb_rate(heights[sel] + cfg.clearance_m - alt, dt, a, cfg.max_climb_mps)
            k = int(np.argmax(w))
            best_w, idx, dt_i = float(w[k]), int(sel[k]), float(dt[k])
        engaged = best_w > w_nom
        cmd = min(max(max(w_nom, best_w), -cfg.max_descent_mps), cfg.max_climb_mps)
        # Push over only into terrain the map has seen: after a building whose roof has no texture,
        # the cells under the vehicle are unknown (not ground at zero), so hold the altitude until
        # mapped terrain is below again, or descend only as far as the free space seen below
        # proves clear (docs/avoidance.md, "Unmapped cells").
        holding = False
        if cmd < 0.0:
            mapped, seen, top = ground_below(grid, p[:2], radius, None if hover else direction)
            if mapped < cfg.descend_known_fraction:
                # What may stand below, by the evidence there is: the highest ceiling of the cells
                # below (lines of sight crossed them lower), or the highest cell of the ground flown
                # over; the vehicle descends to the clearance above the lower of the two.
                bounds = [top] if seen >= cfg.descend_known_fraction else []
                flown = ground_flown_over(grid, p[:2], None if hover else direction, cfg.descend_ground_radius_m)
                if flown is not None:
                    bounds.append(float(soften_near_ground(np.array([flown]), ground, band)[0]))
                if not bounds:
                    holding, cmd = True, 0.0
                elif math.isfinite(min(bounds)):
                    cmd = max(cmd, min(nominal_climb_rate(min(bounds) + cfg.clearance_m - alt, a, cfg.nominal_time_constant_s), 0.0))
                    holding = cmd >= 0.0
        limit = math.inf
        if cfg.speed_limit and not hover:
            ahead = considered & (along > 0.0)
            entry = entry_distance(along[ahead], cross[ahead], radius)
            limit = climb_speed_limit(entry, heights[ahead], alt, -v[2], cfg)
        view_m = math.inf if view_depression_rad is None else view_distance(view_depression_rad, cfg)
        view_limit, horizon = math.inf, math.nan
        if cfg.view_speed_limit and not hover:
            reach_m = view_m
            if cfg.known_horizon and math.isfinite(view_m) and corr.ceiling_m is not None:
                # Beyond the view, stop only before what neither a line of sight nor the map has
                # proven low (docs/avoidance.md, "The known horizon").
                ahead_all = corridor_along >= 0.0
                mapped_h = None
                if cfg.known_horizon_mapped:
                    mapped_h = np.where((corr.count > 0) & np.isfinite(corr.height_m), law_h, np.nan)[ahead_all]
                horizon = known_horizon(corridor_along[ahead_all], corr.cross_m[ahead_all], corr.ceiling_m[ahead_all],
                                        radius, grid.cell_size_m, view_m,
                                        alt - cfg.clearance_m * (1.0 - cfg.speed_limit_shortfall),
                                        cfg.lookahead_m, mapped_h)
                reach_m = max(view_m, horizon + cfg.miss_distance_m)
            view_limit = view_speed_limit(reach_m, cfg)
            limit = min(limit, view_limit)
        if idx is None or not engaged:
            return AvoidanceCommand(cmd, w_nom, None, math.nan, math.nan, math.nan, False, unknown_left, holding, limit,
                                    view_m, view_limit, known_horizon_m=horizon, ground_reference_m=ground)
        h_i = float(heights[idx])
        source = None
        j = int(np.flatnonzero(zone)[idx])  # the limiting cell in the corridor
        own_bound = (corr.floor_m is not None and h_i == corr.floor_m[j]) or (corr.ceiling_m is not None and h_i == corr.ceiling_m[j])
        if not (corr.count[j] > 0 and math.isfinite(corr.height_m[j])) and not own_bound:
            mapped = (corr.count > 0) & np.isfinite(corr.height_m)
            src = stand_in_source(corridor_along, corridor_heights, mapped, j, fill, grid.cell_size_m, hover)
            if src >= 0:
                source = (float(corr.north_m[src]), float(corr.east_m[src]))
        return AvoidanceCommand(
            climb_rate_mps=cmd,
            nominal_climb_mps=w_nom,
            limiting_cell_ne=(float(north[idx]), float(east[idx])),
            limiting_height_m=h_i,
            time_to_go_s=dt_i,
            required_alt_m=h_i + cfg.clearance_m - 0.5 * a * dt_i * dt_i,  # eq. 18
            engaged=True,
            unknown_cells_ahead=unknown_left,
            holding_over_unknown=holding,
            speed_limit_mps=limit,
            view_distance_m=view_m,
            view_speed_limit_mps=view_limit,
            limiting_source_ne=source,
            known_horizon_m=horizon,
            ground_reference_m=ground,
        )


def stopping_time(gain_m: float, accel: float, max_climb: float = math.inf) -> float:
    """Shortest time (s) to climb ``gain_m`` from level flight to level flight with acceleration
    ``+-accel`` and climb rate at most ``max_climb``: the time to go at which the law's bound for a
    level vehicle is exactly zero (:func:`climb_time` from a climb rate of 0: ``2 sqrt(H/a)``, or
    ``H/W + W/a`` at the climb limit). Times the horizontal speed (plus the miss distance) it is the
    stopping distance: an obstacle mapped at least that far ahead is cleared."""
    return float(climb_time(np.array([float(gain_m)]), 0.0, accel, max_climb)[0])
