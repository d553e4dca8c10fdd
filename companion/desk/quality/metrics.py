"""The pilot's figures of one flight: pure functions of its record (definitions in docs/quality.md).

Nothing is excused: every lap counts, the first included, and every obstacle in each lap.

Inputs (a :class:`companion.quality.engine.FlightRecord` or the same arrays): the true trajectory
``t`` (T,), ``ne`` (T, 2), ``alt`` (T,) from the first time the vehicle reached its nominal
altitude; the law's output per control step; the maps at the laps' ends; the world's truth as
``terrain_fn(north, east) -> altitude`` and its obstacles (footprint polygon, height, textured
height). Altitudes are up, metres; times simulated seconds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.desk import report
from companion.method.avoidance import stopping_time
from companion.config import AvoidanceConfig

TerrainFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

FLAT_TOLERANCE_M = 0.25   # terrain within this of the ground datum counts as flat ground
# Where flat ground is looked for about a cell (cells from its centre, each way): the cell and one
# cell around it, so that a cell beside a face is not flat ground, for the map's figures and the
# false climbs alike.
FLAT_NEIGHBOURHOOD_CELLS = (-1.0, -0.5, 0.0, 0.5, 1.0)
FALSE_CELL_M = 2.0        # a cell this far above flat true ground is false (the false-climb rule)
RETURN_TIME_CONSTANTS = 3.0  # the return to the nominal altitude counts as done after this many time constants


@dataclass(frozen=True, slots=True)
class ObstacleTruth:
    """name; footprint_ne_m (K, 2) polygon; height_m (top); textured_height_m (what a texture-tracking
    mapper can see)."""

    name: str
    footprint_ne_m: np.ndarray
    height_m: float
    textured_height_m: float


def _num(x: Any, digits: int = 3) -> float | None:
    """JSON-safe number: None for NaN / inf / None."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


# --------------------------------------------------------------------------------------------
# Where the figures apply
# --------------------------------------------------------------------------------------------


def climb_distance_m(obstacle: ObstacleTruth, law: AvoidanceConfig, speed_mps: float) -> float:
    """Distance before an obstacle over which the law may legitimately be climbing for it: the
    shortest climb from the nominal altitude to obstacle height + clearance
    (:func:`stopping_time`), flown at ``speed_mps``, plus the miss distance."""
    gain = max(0.0, obstacle.height_m + law.clearance_m - law.nominal_alt_m)
    return law.miss_distance_m + speed_mps * stopping_time(gain, law.accel_mps2, law.max_climb_mps)


def return_distance_m(obstacle: ObstacleTruth, law: AvoidanceConfig, speed_mps: float) -> float:
    """Distance after an obstacle over which the law may legitimately still be coming down: the
    descent from obstacle height + clearance to the nominal altitude at the descent limit, then
    ``RETURN_TIME_CONSTANTS`` time constants of the exponential return, flown at ``speed_mps``,
    plus the miss distance."""
    gain = max(0.0, obstacle.height_m + law.clearance_m - law.nominal_alt_m)
    t = gain / max(law.max_descent_mps, 1e-9) + RETURN_TIME_CONSTANTS * law.nominal_time_constant_s
    return law.miss_distance_m + speed_mps * t


def flat_far_mask(ne: np.ndarray, terrain_fn: TerrainFn, obstacles: Sequence[ObstacleTruth],
                  law: AvoidanceConfig, speed_mps: float) -> np.ndarray:
    """(T,) samples over flat ground far from obstacles: the true terrain below is flat (within
    ``FLAT_TOLERANCE_M`` of the ground datum) and, along the path actually flown, no sample over an
    obstacle's footprint grown by the miss distance lies within :func:`climb_distance_m` ahead
    or :func:`return_distance_m` behind."""
    ne = np.asarray(ne, float).reshape(-1, 2)
    flat = np.abs(terrain_fn(ne[:, 0], ne[:, 1])) <= FLAT_TOLERANCE_M
    if len(ne) == 0:
        return flat
    s = report.path_length(ne)
    far = np.ones(len(ne), bool)
    for o in obstacles:
        near = report.points_in_polygon(ne, o.footprint_ne_m) | (
            report.distance_to_polygon_edges(ne, o.footprint_ne_m) <= law.miss_distance_m)
        if not near.any():
            continue
        s_near = s[near]
        ahead, behind = climb_distance_m(o, law, speed_mps), return_distance_m(o, law, speed_mps)
        # for each sample: the next near sample along the path, and the last one before it
        i_next = np.searchsorted(s_near, s, side="left")
        next_s = np.where(i_next < len(s_near), s_near[np.minimum(i_next, len(s_near) - 1)], np.inf)
        i_prev = np.searchsorted(s_near, s, side="right") - 1
        prev_s = np.where(i_prev >= 0, s_near[np.maximum(i_prev, 0)], -np.inf)
        far &= (next_s - s > ahead) & (s - prev_s > behind)
    return flat & far


def engaged_episodes(engaged: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True in ``engaged`` (T,): [(first, last)] inclusive indices."""
    e = np.asarray(engaged, bool).astype(np.int8)
    if not len(e):
        return []
    d = np.diff(np.concatenate([[0], e, [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), ends.tolist()))


def _column(values: np.ndarray, sl: slice) -> np.ndarray | None:
    """A lap's steps of a per-step column of a flight record, or None when the record does not hold
    that column (it is empty)."""
    return values[sl] if len(values) else None


def false_climbs(climb: np.ndarray, engaged: np.ndarray, limiting_ne: np.ndarray, limiting_map_h: np.ndarray,
                 terrain_fn: TerrainFn, cell_m: float, frame_offset_m: np.ndarray, source_ne: np.ndarray | None = None,
                 source_map_h: np.ndarray | None = None, limiting_law_h: np.ndarray | None = None) -> int:
    """Climbs caused by false cells: engaged episodes in which, at the step of the largest commanded
    climb, the limiting cell lies on flat true ground (the cell and one cell around it within
    ``FLAT_TOLERANCE_M`` of the datum, as :func:`flat_cells` judges the map) and its mapped height
    is more than ``FALSE_CELL_M`` above that ground in the navigation's frame of that step: the true
    ground plus ``frame_offset_m`` (T,), the estimate's altitude minus the true one. The map is
    built from the estimate's poses, so a cell that holds the ground where the vehicle believes it
    is, is a true cell however far the estimate has drifted (the altitude figures judge that drift).
    An unmapped limiting cell standing in for a mapped one (``source_ne``, ``source_map_h``: NaN
    where none) is judged by that mapped cell: the cell the climb was for. An unmapped limiting cell
    with no such source was held at a bound of its own (a floor from features not yet converged, or
    its ceiling) and is judged by the height the law took for it (``limiting_law_h``)."""
    count = 0
    for a, b in engaged_episodes(engaged):
        k = a + int(np.argmax(climb[a:b + 1]))
        n, e = limiting_ne[k]
        map_h = limiting_map_h[k]
        if not math.isfinite(map_h):
            if source_ne is not None and source_map_h is not None and math.isfinite(source_map_h[k]):
                n, e = source_ne[k]
                map_h = source_map_h[k]
            elif limiting_law_h is not None:
                map_h = limiting_law_h[k]
        if not (math.isfinite(n) and math.isfinite(e) and math.isfinite(map_h)):
            continue
        offs = np.asarray(FLAT_NEIGHBOURHOOD_CELLS) * cell_m
        nn, ee = np.meshgrid(n + offs, e + offs)
        truth = terrain_fn(nn.ravel(), ee.ravel())
        ground = float(np.max(truth)) + float(frame_offset_m[k])
        if np.all(np.abs(truth) <= FLAT_TOLERANCE_M) and map_h - ground > FALSE_CELL_M:
            count += 1
    return count


# --------------------------------------------------------------------------------------------
# Per lap
# --------------------------------------------------------------------------------------------


def first_held_time(held: np.ndarray, law: AvoidanceConfig) -> float:
    """First time (s) the map held the obstacle high enough to need a climb: some footprint cell, as
    the law takes it, plus the clearance above the nominal altitude. ``held`` (K, 2) [t, height];
    inf if never."""
    held = np.asarray(held, float).reshape(-1, 2)
    need = held[:, 1] + law.clearance_m > law.nominal_alt_m
    return float(held[np.argmax(need), 0]) if need.any() else math.inf


def obstacle_lap_figures(t: np.ndarray, ne: np.ndarray, alt: np.ndarray, terrain_fn: TerrainFn,
                         obstacle: ObstacleTruth, law: AvoidanceConfig, t_held: float, speed_mps: float,
                         lap_map: report.MapRaster | None) -> dict[str, Any]:
    """One obstacle in one lap: least clearance over its footprint (fraction of the configured
    clearance), the time the vehicle reached it, the warning the map gave and the time the law
    needed, and the height the map held at the lap's end."""
    inside = report.points_in_polygon(ne, obstacle.footprint_ne_m)
    needed = stopping_time(max(0.0, obstacle.height_m + law.clearance_m - law.nominal_alt_m), law.accel_mps2,
                           law.max_climb_mps)
    out: dict[str, Any] = {"name": obstacle.name, "reached": bool(inside.any()), "needed_s": _num(needed, 2)}
    if inside.any():
        clearance = alt[inside] - terrain_fn(ne[inside, 0], ne[inside, 1])
        t_reach = float(t[np.argmax(inside)])
        out.update(min_clearance_m=_num(clearance.min()), min_clearance_fraction=_num(clearance.min() / law.clearance_m),
                   reached_t_s=_num(t_reach, 2), held_before=bool(t_held <= t_reach),
                   warning_s=_num(t_reach - t_held, 2) if math.isfinite(t_held) else None)
    else:
        out.update(min_clearance_m=None, min_clearance_fraction=None, reached_t_s=None, held_before=None, warning_s=None)
    if lap_map is not None:
        ground = report.ground_around(obstacle.footprint_ne_m, terrain_fn)
        mh = report.mapped_height_over_footprint(lap_map, obstacle.footprint_ne_m, ground_m=ground)
        out.update(mapped_height_m=_num(mh.height_m), mapped_fraction_of_textured=_num(
            mh.height_m / obstacle.textured_height_m if obstacle.textured_height_m > 0 else math.nan))
    return out


def lap_figures(rec, terrain_fn: TerrainFn, obstacles: Sequence[ObstacleTruth], law: AvoidanceConfig) -> list[dict[str, Any]]:
    """The figures of every lap of a record (first included). A lap = the record's samples up to its
    end (the first from the start of the record); an unfinished last lap is reported too, marked."""
    t, ne, alt = rec.t_s, rec.truth_ne_m, rec.truth_alt_m
    if not len(t):
        return []
    speed = float(law_speed(rec))
    far = flat_far_mask(ne, terrain_fn, obstacles, law, speed)
    held_t = {o.name: first_held_time(rec.held.get(o.name, np.zeros((0, 2))), law) for o in obstacles}
    bounds = [0] + [e + 1 for e in rec.lap_ends]
    if bounds[-1] < len(t):
        bounds.append(len(t))
    laps = []
    cell = rec.cfg.terrain.cell_size_m
    for k in range(len(bounds) - 1):
        sl = slice(bounds[k], bounds[k + 1])
        clearance = alt[sl] - terrain_fn(ne[sl, 0], ne[sl, 1])
        ff = far[sl]
        excess = alt[sl][ff] - law.nominal_alt_m
        lap_map = rec.lap_maps[k] if k < len(rec.lap_maps) else None
        obs = [obstacle_lap_figures(t[sl], ne[sl], alt[sl], terrain_fn, o, law, held_t[o.name], speed, lap_map)
               for o in obstacles]
        reached = [o for o in obs if o["reached"]]
        # The lap's warning: the obstacle with the least margin (warning - needed); never held = no warning.
        worst = min(reached, key=lambda o: -math.inf if o["warning_s"] is None else o["warning_s"] - o["needed_s"],
                    default=None)
        laps.append({
            "lap": k + 1,
            "complete": k < len(rec.lap_ends),
            "start_t_s": _num(t[sl][0], 2), "end_t_s": _num(t[sl][-1], 2),
            "min_clearance_fraction": _num(clearance.min() / law.clearance_m),
            "min_clearance_m": _num(clearance.min()),
            "warning_s": None if worst is None else worst["warning_s"],
            "needed_s": None if worst is None else worst["needed_s"],
            "warning_obstacle": None if worst is None else worst["name"],
            "cruise_excess_median_m": _num(np.median(excess)) if len(excess) else None,
            "cruise_excess_p95_m": _num(np.percentile(excess, 95)) if len(excess) else None,
            "flat_far_s": _num(np.count_nonzero(ff) * _step_s(t), 1),
            "engaged_flat_fraction": _num(np.mean(rec.engaged[sl][ff])) if ff.any() else None,
            "false_climbs": false_climbs(rec.climb_mps[sl], rec.engaged[sl], rec.limiting_ne_m[sl],
                                         rec.limiting_map_height_m[sl], terrain_fn, cell,
                                         rec.nav_alt_m[sl] - alt[sl],
                                         *(_column(c, sl) for c in (rec.limiting_source_ne_m, rec.limiting_source_map_height_m,
                                                                    rec.limiting_law_height_m))),
            "speed_flown_mps": _num(_mean_speed(t[sl], ne[sl]), 2),
            "obstacles": obs,
        })
    return laps


def _step_s(t: np.ndarray) -> float:
    return float(np.median(np.diff(t))) if len(t) > 1 else 0.0


def _mean_speed(t: np.ndarray, ne: np.ndarray) -> float:
    """Path length over time (m/s) of a stretch of trajectory."""
    if len(t) < 2 or t[-1] <= t[0]:
        return math.nan
    return float(report.path_length(ne)[-1] / (t[-1] - t[0]))


def law_speed(rec) -> float:
    """The speed the figures' distances use: the configured cruise speed (the law's own)."""
    return float(rec.cfg.control.cruise_speed_mps)


# --------------------------------------------------------------------------------------------
# The map
# --------------------------------------------------------------------------------------------


def flat_cells(raster: report.MapRaster, terrain_fn: TerrainFn) -> np.ndarray:
    """(H, W) bool: cells whose true terrain is flat ground over the cell and one cell around it
    (sampled at ``FLAT_NEIGHBOURHOOD_CELLS`` about the centre: the centre, the corners and the
    neighbours' centres), so wall edges are not flat."""
    n, e = raster.cell_centres()
    nn, ee = np.broadcast_arrays(n, e)
    flat = np.ones(raster.shape, bool)
    c = raster.cell_m
    for dn in FLAT_NEIGHBOURHOOD_CELLS:
        for de in FLAT_NEIGHBOURHOOD_CELLS:
            flat &= np.abs(terrain_fn(nn + dn * c, ee + de * c)) <= FLAT_TOLERANCE_M
    return flat


def error_stats(err: np.ndarray) -> dict[str, Any]:
    err = np.asarray(err, float)
    if not len(err):
        return {"cells": 0, "bias_m": None, "rmse_m": None, "within_1m": None, "p95_abs_m": None, "max_abs_m": None}
    a = np.abs(err)
    return {"cells": int(len(err)), "bias_m": _num(err.mean()), "rmse_m": _num(np.sqrt(np.mean(err * err))),
            "within_1m": _num(np.mean(a <= 1.0)), "p95_abs_m": _num(np.percentile(a, 95)), "max_abs_m": _num(a.max())}


def map_figures(raster: report.MapRaster, terrain_fn: TerrainFn, obstacles: Sequence[ObstacleTruth],
                swath_cells: np.ndarray, frame_m: float = 0.0) -> dict[str, Any]:
    """The map against the truth: over flat ground (bias, RMSE, within 1 m, coverage of the flat
    cells the camera saw), per obstacle (cells of its footprint: bias and RMSE against the true top,
    mapped height as the 95th percentile of cells with >= 2 points against the textured and the true
    height, coverage), and over every mapped cell (RMSE). ``frame_m``: the truth raised by this much
    first (the navigation's vertical error when the map was taken: the map in the frame the
    vehicle flies in; docs/quality.md)."""
    out: dict[str, Any] = {"flat": error_stats([]), "obstacles": {}, "all": error_stats([])}
    if raster.shape[0] == 0 or raster.shape[1] == 0:
        for o in obstacles:
            out["obstacles"][o.name] = {"cells": 0, "mapped_height_m": None}
        out["flat"]["coverage"] = 0.0 if len(swath_cells) else None
        return out
    known = raster.count > 0
    n, e = raster.cell_centres()
    nn, ee = np.broadcast_arrays(n, e)
    err = np.full(raster.shape, np.nan)
    err[known] = raster.height[known] - report.cell_top_truth(raster, terrain_fn, known) - frame_m
    out["all"] = error_stats(err[known])
    flat = flat_cells(raster, terrain_fn)
    out["flat"] = error_stats(err[known & flat])
    # Coverage: of the flat cells the camera saw, those the map holds.
    c = raster.cell_m
    i0, j0 = int(round(raster.north0_m / c)), int(round(raster.east0_m / c))
    sw = np.asarray(swath_cells, np.int64).reshape(-1, 2)
    ci, cj = sw[:, 0] - i0, sw[:, 1] - j0
    inside = (ci >= 0) & (ci < raster.shape[0]) & (cj >= 0) & (cj < raster.shape[1])
    seen_flat = np.zeros(len(sw), bool)
    seen_flat[inside] = flat[ci[inside], cj[inside]]
    # swath cells outside the raster are flat if the truth says so (the map holds none of them)
    if (~inside).any():
        cn, ce = (sw[~inside, 0] + 0.5) * c, (sw[~inside, 1] + 0.5) * c
        seen_flat[~inside] = np.abs(terrain_fn(cn, ce)) <= FLAT_TOLERANCE_M
    mapped = np.zeros(len(sw), bool)
    mapped[inside] = known[ci[inside], cj[inside]]
    n_seen = int(np.count_nonzero(seen_flat))
    out["flat"]["coverage"] = _num(np.count_nonzero(seen_flat & mapped) / n_seen) if n_seen else None
    for o in obstacles:
        foot = report.points_in_polygon(np.stack([nn.ravel(), ee.ravel()], axis=1), o.footprint_ne_m).reshape(raster.shape)
        stats = error_stats(err[known & foot])
        ground = report.ground_around(o.footprint_ne_m, terrain_fn)
        mh = report.mapped_height_over_footprint(raster, o.footprint_ne_m, ground_m=ground)
        mapped_m = mh.height_m - frame_m if mh.cells else mh.height_m  # none mapped: the ground
        n_foot = int(np.count_nonzero(foot))
        stats.update(height_m=_num(o.height_m), textured_height_m=_num(o.textured_height_m),
                     mapped_height_m=_num(mapped_m),
                     mapped_fraction_of_textured=_num(mapped_m / o.textured_height_m) if o.textured_height_m > 0 else None,
                     coverage=_num(np.count_nonzero(known & foot) / n_foot) if n_foot else None)
        out["obstacles"][o.name] = stats
    return out


# --------------------------------------------------------------------------------------------
# One run
# --------------------------------------------------------------------------------------------


def obstacles_of(world) -> list[ObstacleTruth]:
    return [ObstacleTruth(o.name, np.asarray(o.footprint_ne_m, float), float(o.height_m), float(o.textured_height_m))
            for o in world.obstacles]


def run_figures(rec, world) -> dict[str, Any]:
    """The ``runs[]`` entry of quality.json for one flight record over ``world``."""
    law = rec.cfg.avoidance
    obstacles = obstacles_of(world)
    laps = lap_figures(rec, world.terrain_height, obstacles, law)
    done = [lap for lap in laps if lap["complete"]]
    speeds = [lap["speed_flown_mps"] for lap in done if lap["speed_flown_mps"] is not None]
    frame_end = float(rec.nav_alt_m[-1] - rec.truth_alt_m[-1]) if len(rec.t_s) else 0.0
    return {
        "scenario": rec.scenario,
        "seed": rec.seed,
        "parameterisation": rec.parameterisation,
        "complete": bool(rec.complete and len(done) >= rec.laps_requested),
        "problem": rec.problem,
        "laps_requested": rec.laps_requested,
        "speed_flown_mps": _num(np.mean(speeds), 2) if speeds else None,
        "speed_commanded_mps": _num(rec.cfg.control.cruise_speed_mps, 2),
        "cruise_reached_ne_m": [_num(v, 1) for v in rec.truth_ne_m[0]] if len(rec.t_s) else None,
        "clearance_m": _num(law.clearance_m, 2),
        "nominal_alt_m": _num(law.nominal_alt_m, 2),
        "laps": laps,
        "map": map_figures(rec.final_map, world.terrain_height, obstacles, rec.swath_cells),
        # The map in the navigation's frame at the end of the flight, when it was taken.
        "nav_frame_error_end_m": _num(frame_end, 3),
        "map_nav_frame": map_figures(rec.final_map, world.terrain_height, obstacles, rec.swath_cells, frame_end),
    }
