"""Pull-up / push-over terrain avoidance (seed 000, section III; derivation in docs/avoidance.md).

Along the horizontal velocity, every mapped cell within the miss distance imposes a lower bound
on the climb rate now: the least climb rate from which a vertical profile with acceleration
``+-a_c`` (and the climb-rate limit) still reaches ``h_i + h_c`` by the time the vehicle comes
within the miss distance of the cell, arriving with zero vertical speed (a smooth pull-up). The
command is the largest of these bounds and of the nominal-altitude command, clipped to the
vehicle's climb and descent limits. Signs: altitude ``h`` and climb rate ``w`` are up-positive.

Functions in derivation order: :func:`time_to_go` (Delta t_i), :func:`height_restriction`
(eq. 18), :func:`minimum_climb_rate` (eqs. 19-20 completed with the push-over and the climb-rate
limit), :func:`nominal_climb_rate` (return to the nominal altitude), :func:`margin_height` (a cell
as high as its estimate plus k sigma), then :class:`PullUpLaw`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import AvoidanceConfig
from companion.method.terrain.grid import TerrainGrid


def time_to_go(along_m: np.ndarray, cross_m: np.ndarray, radius_m: float, speed_mps: float) -> np.ndarray:
    """Delta t_i (s): time until the vehicle, flying straight at ``speed_mps``, first comes within
    ``radius_m`` of each cell centre (``along``/``cross`` relative to its track), 0 if already
    within it. At hover speed nothing ahead ever arrives: infinity, except cells already within
    reach (0). All arrays (K,)."""
    entry = along_m - np.sqrt(np.maximum(radius_m * radius_m - cross_m * cross_m, 0.0))
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
    limiting_height_m: that cell's height plus its uncertainty margin (``margin_height``; or the height
        assumed for it when unmapped); NaN if none.
    time_to_go_s: Delta t of that cell (NaN if none).
    required_alt_m: eq. 18, h_min of that cell (NaN if none).
    engaged: an obstacle demands more than the nominal command.
    unknown_cells_ahead: corridor cells with no evidence and no mapped cell near enough to stand in.
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


def known_fraction_below(grid: TerrainGrid, position_ne: np.ndarray, radius_m: float,
                         direction_ne: np.ndarray | None = None) -> float:
    """Fraction of the cells below the vehicle that hold evidence: the cells whose centre lies within
    ``radius_m`` of it (hover), or, moving along the unit ``direction_ne``, those of the ground it has
    just flown over (``radius_m`` back along track, ``radius_m`` either side). Looking back and not
    around: at the far edge of a plain roof the mapped ground ahead would otherwise fill the disc
    before the vehicle has left the roof."""
    if direction_ne is None:
        disc = grid.corridor(position_ne, np.array([1.0, 0.0]), 0.0, radius_m)
        inside = np.hypot(disc.north_m - position_ne[0], disc.east_m - position_ne[1]) <= radius_m
    else:
        disc = grid.corridor(position_ne, -np.asarray(direction_ne, dtype=np.float64), radius_m, radius_m)
        inside = (disc.along_m >= -0.5 * grid.cell_size_m) & (disc.along_m <= radius_m)
    total = int(np.count_nonzero(inside))
    return float(np.count_nonzero(inside & np.isfinite(disc.height_m))) / total if total else 0.0


def margin_height(height_m: np.ndarray, variance: np.ndarray, k: float) -> np.ndarray:
    """The height the law keeps its clearance above: ``h + k sqrt(variance)`` per cell (K,) (NaN
    stays NaN). The clearance is meant above the true terrain, and the map only estimates it: a cell
    known to +-0.6 m (a few points, each carrying the 0.8 m vertical navigation error of its pass)
    is, with k = 2, taken 1.2 m higher. Disputed cells (points far below the top, which widen the
    variance: docs/terrain.md) get more margin, well-observed ground less."""
    if k <= 0.0:
        return height_m
    with np.errstate(invalid="ignore"):
        return height_m + k * np.sqrt(variance)


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
    bins = np.floor((along_m - along_m[0]) / cell_m).astype(np.int64)
    n_bins = int(bins[-1]) + 1
    peak = np.full(n_bins, -np.inf)
    np.maximum.at(peak, bins[~unknown], h[~unknown])
    reach = int(math.ceil(fill_m / cell_m))
    padded = np.concatenate([np.full(reach, -np.inf), peak, np.full(reach, -np.inf)])
    window = peak.copy()
    for k in range(2 * reach + 1):
        np.maximum(window, padded[k : k + n_bins], out=window)
    stand_in = window[bins[unknown]]
    h[unknown] = np.where(np.isfinite(stand_in), stand_in, np.nan)
    return h


class PullUpLaw:
    """The avoidance law of seed 000, section III, on a :class:`TerrainGrid`."""

    def __init__(self, cfg: AvoidanceConfig) -> None:
        self.cfg = cfg

    def command(
        self, position_ned, velocity_ned, grid: TerrainGrid, nominal_alt_m: float | None = None
    ) -> AvoidanceCommand:
        """Climb-rate command for a vehicle at ``position_ned`` (3,) moving at ``velocity_ned`` (3,).

        ValueError on non-finite state (the caller must not command on it)."""
        cfg = self.cfg
        p = np.asarray(position_ned, dtype=np.float64).reshape(3)
        v = np.asarray(velocity_ned, dtype=np.float64).reshape(3)
        if not (np.isfinite(p).all() and np.isfinite(v).all()):
            raise ValueError("PullUpLaw.command: position and velocity must be finite")
        nominal = cfg.nominal_alt_m if nominal_alt_m is None else float(nominal_alt_m)
        alt = -p[2]
        a = cfg.accel_mps2
        w_nom = nominal_climb_rate(nominal - alt, a, cfg.nominal_time_constant_s)

        # The zone of a cell: within the miss distance of any point of the cell (half diagonal).
        radius = cfg.miss_distance_m + grid.cell_size_m * math.sqrt(0.5)
        speed = float(np.hypot(v[0], v[1]))
        hover = speed < max(cfg.hover_speed_mps, 1e-9)
        fill = cfg.unknown_fill_m
        # The corridor starts `fill` behind the vehicle (and the hover disc is `fill` wider) so
        # that mapped cells just outside the zone can stand in for unmapped ones inside it.
        if hover:
            direction, speed_used = np.array([1.0, 0.0]), 0.0
            corr = grid.corridor(p[:2], direction, 0.0, radius + fill)
            along = corr.along_m
            zone = np.hypot(corr.north_m - p[0], corr.east_m - p[1]) <= radius
        else:
            direction, speed_used = v[:2] / speed, speed
            corr = grid.corridor(p[:2] - fill * direction, direction, cfg.lookahead_m + fill, radius)
            along = corr.along_m - fill
            zone = (along >= 0.0) | (along * along + corr.cross_m * corr.cross_m <= radius * radius)
        heights = fill_unknown(along, margin_height(corr.height_m, corr.variance, cfg.height_margin_sigma),
                               fill, grid.cell_size_m, hover)[zone]
        along, cross = along[zone], corr.cross_m[zone]
        north, east = corr.north_m[zone], corr.east_m[zone]
        considered = np.isfinite(heights)
        unknown_left = int(len(heights) - np.count_nonzero(considered))

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
        # mapped terrain is below again (docs/avoidance.md, "Unmapped cells").
        holding = cmd < 0.0 and known_fraction_below(grid, p[:2], radius, None if hover else direction) < cfg.descend_known_fraction
        if holding:
            cmd = 0.0
        if idx is None or not engaged:
            return AvoidanceCommand(cmd, w_nom, None, math.nan, math.nan, math.nan, False, unknown_left, holding)
        h_i = float(heights[idx])
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
        )


def stopping_time(gain_m: float, accel: float, max_climb: float = math.inf) -> float:
    """Shortest time (s) to climb ``gain_m`` from level flight to level flight with acceleration
    ``+-accel`` and climb rate at most ``max_climb``: the time to go at which the law's bound for a
    level vehicle is exactly zero. Times the horizontal speed (plus the miss distance) it is the
    stopping distance: an obstacle mapped at least that far ahead is cleared."""
    if gain_m <= 0:
        return 0.0
    if max_climb * max_climb >= accel * gain_m:
        return 2.0 * math.sqrt(gain_m / accel)
    return gain_m / max_climb + max_climb / accel
