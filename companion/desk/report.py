"""Metrics and figures of a closed-loop run (``companion demo``): pure functions of arrays.

Inputs are what the demo records, never processes or sockets:

* the true trajectory (the simulator's SIM_STATE truth): times ``t_s`` (N,), horizontal
  positions ``ne`` (N, 2) north/east (m, local NED frame) and altitudes ``alt_m`` (N,) (m, up);
* the terrain map as the ground station received it: a :class:`MapRaster` (heights, evidence
  counts) built from the tiles with :func:`raster_from_tiles`;
* the world's truth as a callable ``terrain_fn(north, east) -> altitude`` (``World.terrain_height``)
  and the obstacle's footprint polygon (K, 2).

What is measured (docs/demo.md):

* laps: :func:`split_laps` cuts the trajectory each time it comes back to the first waypoint
  after visiting the others in order (each within ``radius_m``);
* clearance: :func:`min_clearance_over_footprint`, the least height above the true terrain
  while the vehicle is over the obstacle's footprint (``min_clearance_m``);
* mapped obstacle height: :func:`mapped_height_over_footprint`, a high quantile (95th
  percentile) of the mapped heights of the footprint's cells that hold at least two points, so
  that one wild cell does not make the building taller; the maximum is reported beside it. A
  lap whose map holds no such cell shows the obstacle at the ground (:func:`ground_around`);
* map error: :func:`map_error`, RMSE (and robust companions) of every observed cell against the
  true terrain at the cell centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping

import numpy as np

TerrainFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

# The seed paper (section IV, figs. 2-3): the 40 ft structure was mapped at about 30 ft.
PAPER_MAPPED_FRACTION = 0.75


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------


def points_in_polygon(ne: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd rule: which of the points ``ne`` (N, 2) lie inside ``polygon`` (K, 2) -> (N,) bool.

    Batched over the points; the loop runs over the K edges (a footprint has a handful)."""
    p = np.asarray(ne, float).reshape(-1, 2)
    poly = np.asarray(polygon, float).reshape(-1, 2)
    if len(poly) < 3:
        raise ValueError(f"a polygon needs at least 3 vertices, got {len(poly)}")
    inside = np.zeros(len(p), bool)
    x, y = p[:, 1], p[:, 0]  # east as x, north as y: the rule does not care, but be explicit
    for (n0, e0), (n1, e1) in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (n0 > y) != (n1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            e_at = e0 + (y - n0) * (e1 - e0) / (n1 - n0)
        inside ^= crosses & (x < e_at)
    return inside


def distance_to_polygon_edges(ne: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Distance (m) from each point ``ne`` (N, 2) to the nearest edge of ``polygon`` (K, 2) -> (N,)."""
    p = np.asarray(ne, float).reshape(-1, 1, 2)
    a = np.asarray(polygon, float).reshape(1, -1, 2)
    b = np.roll(a, -1, axis=1)
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=2), 1e-12), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.min(np.linalg.norm(p - closest, axis=2), axis=1)


def path_length(ne: np.ndarray) -> np.ndarray:
    """Cumulative horizontal distance (m) along a path ``ne`` (N, 2) -> (N,), starting at 0."""
    ne = np.asarray(ne, float).reshape(-1, 2)
    if len(ne) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ne, axis=0), axis=1))])


# --------------------------------------------------------------------------------------------
# Laps
# --------------------------------------------------------------------------------------------


class LapCounter:
    """Online lap splitting over a growing trajectory.

    A lap ends at the first sample within ``radius_m`` of waypoint 0 after the vehicle has come
    within ``radius_m`` of waypoints 1, 2, ... in order. The first lap starts at the first sample
    (the demo takes off at waypoint 0). ``boundaries`` holds the index of each lap's end, which
    is also the next lap's start. Feed samples with :meth:`update` in order; the work per call
    is batched over the new samples (one search per waypoint event, not one step per sample).
    """

    def __init__(self, waypoints_ne_m, radius_m: float = 10.0):
        wp = np.asarray(waypoints_ne_m, float).reshape(-1, 2)
        if len(wp) < 2 or not np.all(np.isfinite(wp)):
            raise ValueError("lap splitting needs at least two finite waypoints")
        if not radius_m > 0:
            raise ValueError(f"radius_m must be positive, got {radius_m}")
        self.waypoints = wp
        self.radius_m = float(radius_m)
        self.next_wp = 1
        self.count = 0  # samples seen
        self.boundaries: list[int] = []

    @property
    def laps(self) -> int:
        return len(self.boundaries)

    def update(self, ne: np.ndarray) -> list[int]:
        """Consume the next samples ``ne`` (M, 2); returns the indices of laps completed by them."""
        ne = np.asarray(ne, float).reshape(-1, 2)
        done: list[int] = []
        start = 0
        while start < len(ne):
            d = np.linalg.norm(ne[start:] - self.waypoints[self.next_wp], axis=1)
            hit = np.flatnonzero(d <= self.radius_m)
            if len(hit) == 0:
                break
            k = start + int(hit[0])
            if self.next_wp == 0:
                self.boundaries.append(self.count + k)
                done.append(self.count + k)
            self.next_wp = (self.next_wp + 1) % len(self.waypoints)
            start = k + 1
        self.count += len(ne)
        return done


def split_laps(ne: np.ndarray, waypoints_ne_m, radius_m: float = 10.0) -> list[tuple[int, int]]:
    """Complete laps of a trajectory ``ne`` (N, 2) as index ranges ``[start, stop)``
    (:class:`LapCounter`'s rule; an unfinished last lap is not listed)."""
    counter = LapCounter(waypoints_ne_m, radius_m)
    counter.update(ne)
    starts = [0] + counter.boundaries[:-1]
    return [(s, e + 1) for s, e in zip(starts, counter.boundaries)]


# --------------------------------------------------------------------------------------------
# Clearance
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Crossing:
    """The vehicle over a footprint: least clearance (m), where it happened and when it first
    entered (the time of the first sample inside). NaN everything when it never was over it."""

    min_clearance_m: float
    at_ne_m: tuple[float, float] | None
    at_t_s: float
    entered_t_s: float
    samples: int


def min_clearance_over_footprint(t_s: np.ndarray, ne: np.ndarray, alt_m: np.ndarray, polygon: np.ndarray,
                                 terrain_fn: TerrainFn) -> Crossing:
    """Least height above the true terrain, ``min(alt - terrain(n, e))``, over the samples that lie
    inside ``polygon``. t_s, alt_m (N,), ne (N, 2)."""
    t_s, alt_m = np.asarray(t_s, float).reshape(-1), np.asarray(alt_m, float).reshape(-1)
    ne = np.asarray(ne, float).reshape(-1, 2)
    if not (len(t_s) == len(ne) == len(alt_m)):
        raise ValueError(f"t_s, ne and alt_m must have the same length, got {len(t_s)}, {len(ne)}, {len(alt_m)}")
    inside = np.flatnonzero(points_in_polygon(ne, polygon)) if len(ne) else np.zeros(0, int)
    if len(inside) == 0:
        return Crossing(math.nan, None, math.nan, math.nan, 0)
    clearance = alt_m[inside] - np.asarray(terrain_fn(ne[inside, 0], ne[inside, 1]), float)
    k = int(np.argmin(clearance))
    i = int(inside[k])
    return Crossing(float(clearance[k]), (float(ne[i, 0]), float(ne[i, 1])), float(t_s[i]), float(t_s[inside[0]]),
                    int(len(inside)))


# --------------------------------------------------------------------------------------------
# The map
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MapRaster:
    """The terrain map on one regular grid.

    height: (H, W) altitude (m, up), NaN where no evidence; row i north, column j east, row 0 the
        southern edge. count: (H, W) evidence count (0 = unknown).
    north0_m, east0_m: south-west corner of cell [0, 0]; cell_m: cell edge (m).
    """

    height: np.ndarray
    count: np.ndarray
    north0_m: float
    east0_m: float
    cell_m: float

    @classmethod
    def empty(cls, cell_m: float = 1.0) -> "MapRaster":
        return cls(np.full((0, 0), np.nan), np.zeros((0, 0), np.int64), 0.0, 0.0, cell_m)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height.shape  # type: ignore[return-value]

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """North (H, 1) and east (1, W) coordinates of the cell centres."""
        rows, cols = self.shape
        n = self.north0_m + (np.arange(rows) + 0.5)[:, None] * self.cell_m
        e = self.east0_m + (np.arange(cols) + 0.5)[None, :] * self.cell_m
        return n, e

    def crop(self, north_lo_m: float, north_hi_m: float, east_lo_m: float, east_hi_m: float) -> "MapRaster":
        """The cells that overlap ``[north_lo, north_hi] x [east_lo, east_hi]`` (on this raster's
        lattice; unknown cells pad the part the map does not cover)."""
        c = self.cell_m
        i0, i1 = math.floor((north_lo_m - self.north0_m) / c), math.ceil((north_hi_m - self.north0_m) / c)
        j0, j1 = math.floor((east_lo_m - self.east0_m) / c), math.ceil((east_hi_m - self.east0_m) / c)
        if i1 <= i0 or j1 <= j0:
            raise ValueError("crop: empty window")
        height = np.full((i1 - i0, j1 - j0), np.nan)
        count = np.zeros((i1 - i0, j1 - j0), np.int64)
        rows, cols = self.shape
        si0, si1, sj0, sj1 = max(i0, 0), min(i1, rows), max(j0, 0), min(j1, cols)
        if si1 > si0 and sj1 > sj0:
            height[si0 - i0:si1 - i0, sj0 - j0:sj1 - j0] = self.height[si0:si1, sj0:sj1]
            count[si0 - i0:si1 - i0, sj0 - j0:sj1 - j0] = self.count[si0:si1, sj0:sj1]
        return MapRaster(height, count, self.north0_m + i0 * c, self.east0_m + j0 * c, c)

    def observed_cells(self) -> int:
        return int(np.count_nonzero((self.count > 0) & np.isfinite(self.height)))

    def sample(self, ne: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Height and count of the cells containing the points ``ne`` (N, 2); NaN / 0 outside."""
        ne = np.asarray(ne, float).reshape(-1, 2)
        h = np.full(len(ne), np.nan)
        c = np.zeros(len(ne), np.int64)
        rows, cols = self.shape
        if rows == 0 or cols == 0 or len(ne) == 0:
            return h, c
        i = np.floor((ne[:, 0] - self.north0_m) / self.cell_m).astype(np.int64)
        j = np.floor((ne[:, 1] - self.east0_m) / self.cell_m).astype(np.int64)
        ok = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
        h[ok] = self.height[i[ok], j[ok]]
        c[ok] = self.count[i[ok], j[ok]]
        return h, c


def raster_from_tiles(tiles: Iterable) -> MapRaster:
    """One :class:`MapRaster` from terrain tiles (objects with ``tx, ty, height, count,
    cell_size_m``, as ``companion.method.terrain.tile.Tile``): the bounding box of the tiles, unknown
    where no tile or no evidence."""
    tiles = list(tiles.values() if isinstance(tiles, Mapping) else tiles)
    if not tiles:
        return MapRaster.empty()
    t = tiles[0].height.shape[0]
    cell = float(tiles[0].cell_size_m)
    for tile in tiles:
        if tile.height.shape[0] != t or not math.isclose(float(tile.cell_size_m), cell):
            raise ValueError(f"tiles of different sizes: ({tile.tx}, {tile.ty}) has {tile.height.shape[0]} cells of "
                             f"{tile.cell_size_m} m, the first {t} of {cell} m")
    tx0, ty0 = min(tile.tx for tile in tiles), min(tile.ty for tile in tiles)
    rows = (max(tile.tx for tile in tiles) - tx0 + 1) * t
    cols = (max(tile.ty for tile in tiles) - ty0 + 1) * t
    height = np.full((rows, cols), np.nan)
    count = np.zeros((rows, cols), np.int64)
    for tile in tiles:
        i0, j0 = (tile.tx - tx0) * t, (tile.ty - ty0) * t
        c = np.asarray(tile.count, np.int64)
        count[i0:i0 + t, j0:j0 + t] = c
        height[i0:i0 + t, j0:j0 + t] = np.where(c > 0, tile.height, np.nan)
    return MapRaster(height, count, tx0 * t * cell, ty0 * t * cell, cell)


@dataclass(frozen=True, slots=True)
class MappedHeight:
    """The obstacle as the map holds it (m, altitude up): ``height_m`` is the 95th percentile of
    the supported cells (evidence count >= ``min_count``) over the (grown) footprint, ``max_m``
    their maximum; NaN when no cell there is supported. ``cells`` supported / ``footprint_cells``."""

    height_m: float
    max_m: float
    cells: int
    footprint_cells: int


def footprint_cells(raster: MapRaster, polygon: np.ndarray, margin_m: float) -> np.ndarray:
    """(H, W) bool: cells whose centre is inside ``polygon`` or within ``margin_m`` of its edges.

    The margin catches the points of a wall, which fall half a cell either side of it."""
    rows, cols = raster.shape
    if rows == 0 or cols == 0:
        return np.zeros((rows, cols), bool)
    n, e = raster.cell_centres()
    centres = np.stack(np.broadcast_arrays(n, e), axis=-1).reshape(-1, 2)
    poly = np.asarray(polygon, float)
    # Only cells in the polygon's bounding box (plus margin) can qualify: test those.
    lo, hi = poly.min(axis=0) - margin_m, poly.max(axis=0) + margin_m
    box = np.all((centres >= lo) & (centres <= hi), axis=1)
    mask = np.zeros(len(centres), bool)
    cand = centres[box]
    if len(cand):
        ok = points_in_polygon(cand, poly)
        if margin_m > 0:
            ok |= distance_to_polygon_edges(cand, poly) <= margin_m
        mask[np.flatnonzero(box)] = ok
    return mask.reshape(rows, cols)


def mapped_height_over_footprint(raster: MapRaster, polygon: np.ndarray, min_count: int = 2,
                                 quantile: float = 0.95, margin_m: float | None = None,
                                 ground_m: float = math.nan) -> MappedHeight:
    """The obstacle's height as mapped: a high quantile over its footprint's supported cells.

    margin_m: footprint growth (default one cell, see :func:`footprint_cells`). ground_m: the
    altitude reported when no cell of the footprint is supported, the map showing no obstacle
    there (the paper's fig. 2 draws such a lap at the ground; default NaN, "unknown");
    ``cells`` is then 0."""
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"quantile must be within [0, 1], got {quantile}")
    mask = footprint_cells(raster, polygon, raster.cell_m if margin_m is None else margin_m)
    supported = mask & (raster.count >= min_count) & np.isfinite(raster.height)
    h = raster.height[supported]
    if h.size == 0:
        return MappedHeight(ground_m, ground_m, 0, int(mask.sum()))
    return MappedHeight(float(np.quantile(h, quantile)), float(h.max()), int(h.size), int(mask.sum()))


def ground_around(polygon: np.ndarray, terrain_fn: TerrainFn, distance_m: float = 3.0) -> float:
    """The obstacle's base altitude (m): the median true terrain on its footprint's bounding box
    grown by ``distance_m``, sampled every metre along the box's edges."""
    lo = np.asarray(polygon, float).min(axis=0) - distance_m
    hi = np.asarray(polygon, float).max(axis=0) + distance_m
    n = np.linspace(lo[0], hi[0], max(2, int(hi[0] - lo[0]) + 1))
    e = np.linspace(lo[1], hi[1], max(2, int(hi[1] - lo[1]) + 1))
    north = np.concatenate([n, n, np.full_like(e, lo[0]), np.full_like(e, hi[0])])
    east = np.concatenate([np.full_like(n, lo[1]), np.full_like(n, hi[1]), e, e])
    return float(np.median(terrain_fn(north, east)))


def height_over_flat_ground(ne: np.ndarray, alt_m: np.ndarray, terrain_fn: TerrainFn,
                            radius_m: float = 15.0) -> tuple[float, int]:
    """Median height above the terrain (m) of the samples whose true terrain is flat within
    ``radius_m`` (the same height at the sample and at 8 points around it): how high the vehicle
    cruises where nothing asks it to climb, to set beside the nominal altitude. Returns the median
    (NaN without such samples) and the number of samples. ne (N, 2), alt_m (N,)."""
    ne = np.asarray(ne, float).reshape(-1, 2)
    alt = np.asarray(alt_m, float).reshape(-1)
    if len(ne) == 0:
        return math.nan, 0
    here = np.asarray(terrain_fn(ne[:, 0], ne[:, 1]), float)
    flat = np.ones(len(ne), bool)
    for dn in (-radius_m, 0.0, radius_m):
        for de in (-radius_m, 0.0, radius_m):
            flat &= np.asarray(terrain_fn(ne[:, 0] + dn, ne[:, 1] + de), float) == here
    if not flat.any():
        return math.nan, 0
    return float(np.median(alt[flat] - here[flat])), int(flat.sum())


def first_detection_time(t_s: np.ndarray, mapped_m: np.ndarray, threshold_m: float) -> float:
    """First time the mapped obstacle height reached ``threshold_m`` (NaN values never count);
    NaN when it never did. t_s, mapped_m (N,) in time order."""
    t_s, mapped_m = np.asarray(t_s, float), np.asarray(mapped_m, float)
    hit = np.flatnonzero(np.nan_to_num(mapped_m, nan=-np.inf) >= threshold_m)
    return float(t_s[hit[0]]) if len(hit) else math.nan


@dataclass(frozen=True, slots=True)
class MapError:
    """Observed cells against the truth at their centres (map - truth, m): RMSE, bias, the share
    within 1 m, the 95th percentile of |error| and the largest error; ``cells`` compared and
    ``over_3m`` of them mapped more than 3 m above the truth (phantom obstacles)."""

    rmse_m: float
    bias_m: float
    within_1m: float
    p95_abs_m: float
    max_abs_m: float
    cells: int
    over_3m: int = 0


# Where a cell's true top is looked for: a 5 x 5 lattice over the cell (fractions of the cell from its
# centre), so a face through the cell counts wherever it stands in it, not only across the centre.
CELL_TOP_OFFSETS = (-0.4, -0.2, 0.0, 0.2, 0.4)


def cell_top_truth(raster: MapRaster, terrain_fn: TerrainFn, cells: np.ndarray | None = None) -> np.ndarray:
    """The highest true terrain over each cell (H, W) (or over the cells of the (H, W) bool mask
    ``cells``, (K,)): what a cell of the map claims (the fusion keeps a cell's top, docs/terrain.md),
    so the truth a mapped cell is judged against. On flat ground it is the terrain at the centre;
    on a cell a wall's face crosses, the wall's top."""
    n, e = raster.cell_centres()
    nn, ee = np.broadcast_arrays(n, e)
    if cells is not None:
        nn, ee = nn[cells], ee[cells]
    top = np.full(nn.shape, -np.inf)
    for dn in CELL_TOP_OFFSETS:
        for de in CELL_TOP_OFFSETS:
            top = np.maximum(top, np.asarray(terrain_fn(nn + dn * raster.cell_m, ee + de * raster.cell_m), float))
    return top


def map_error(raster: MapRaster, terrain_fn: TerrainFn, min_count: int = 1) -> MapError:
    """Error of every observed cell (evidence count >= ``min_count``) against the highest true
    terrain over the cell (:func:`cell_top_truth`)."""
    observed = (raster.count >= min_count) & np.isfinite(raster.height)
    if not observed.any():
        return MapError(math.nan, math.nan, math.nan, math.nan, math.nan, 0)
    err = raster.height[observed] - cell_top_truth(raster, terrain_fn, observed)
    a = np.abs(err)
    return MapError(float(np.sqrt(np.mean(err * err))), float(np.mean(err)), float(np.mean(a <= 1.0)),
                    float(np.quantile(a, 0.95)), float(a.max()), int(err.size), int(np.count_nonzero(err > 3.0)))


# --------------------------------------------------------------------------------------------
# Side profile of a lap
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Profile:
    """Along one lap (all (M,)): distance flown (m), altitude, true terrain, the terrain a
    texture-following mapper can see, the mapped terrain under the path and the highest mapped
    cell across the path within the corridor half-width (what the avoidance law looks at; NaN
    unknown)."""

    distance_m: np.ndarray
    alt_m: np.ndarray
    true_terrain_m: np.ndarray
    textured_terrain_m: np.ndarray
    mapped_terrain_m: np.ndarray
    mapped_corridor_max_m: np.ndarray


def lap_profile(ne: np.ndarray, alt_m: np.ndarray, terrain_fn: TerrainFn, raster: MapRaster,
                textured_fn: TerrainFn | None = None, max_points: int = 4000, corridor_m: float = 5.0) -> Profile:
    """The side profile of a lap (decimated to at most ``max_points`` samples for drawing)."""
    ne = np.asarray(ne, float).reshape(-1, 2)
    alt_m = np.asarray(alt_m, float).reshape(-1)
    step = max(1, math.ceil(len(ne) / max_points))
    ne, alt_m = ne[::step], alt_m[::step]
    d = path_length(ne)
    true = np.asarray(terrain_fn(ne[:, 0], ne[:, 1]), float) if len(ne) else np.zeros(0)
    textured = np.asarray(textured_fn(ne[:, 0], ne[:, 1]), float) if (textured_fn and len(ne)) else true
    mapped, _ = raster.sample(ne)
    # Across-track samples every half cell out to the corridor half-width; (M, K) then max over K.
    tangent = np.gradient(ne, axis=0) if len(ne) >= 2 else np.zeros_like(ne)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    across = np.where(norm > 1e-9, np.stack([-tangent[:, 1], tangent[:, 0]], axis=1) / np.maximum(norm, 1e-9), 0.0)
    offsets = np.arange(-corridor_m, corridor_m + 1e-9, raster.cell_m / 2)
    pts = ne[:, None, :] + offsets[None, :, None] * across[:, None, :]
    h, _ = raster.sample(pts.reshape(-1, 2))
    h = h.reshape(len(ne), len(offsets))
    any_known = np.isfinite(h).any(axis=1)
    corridor = np.full(len(ne), np.nan)
    corridor[any_known] = np.nanmax(h[any_known], axis=1)
    return Profile(d, alt_m, true, textured, mapped, corridor)


# --------------------------------------------------------------------------------------------
# Verdicts against the demo's requirements and the paper
# --------------------------------------------------------------------------------------------


CLEARANCE_REQUIRED, CLEARANCE_GOAL = 0.8, 0.9   # of the configured clearance, on every lap
FLAT_EXCESS_GOAL_M = 1.0                        # median height over flat ground above the nominal altitude


def criteria(laps: list[dict], clearance_m: float, textured_height_m: float, other_laps: list[dict] | None = None,
             roof_height_m: float = math.nan, nominal_alt_m: float = math.nan) -> dict:
    """The demo's criteria and the paper's checks on one run's laps (dicts as the demo writes them:
    ``min_clearance_m``, ``mapped_obstacle_height_m``, ``cruise_height_over_flat_m``).

    * clearance: every lap, the first included, keeps at least 0.8 (required, the ``issue_*`` keys)
      / 0.9 (goal) of ``clearance_m`` over the obstacle; a lap without a crossing fails (the
      vehicle never flew over it);
    * height over flat ground: the worst lap's median height over flat ground is within
      ``FLAT_EXCESS_GOAL_M`` of ``nominal_alt_m`` (goal);
    * height: the last lap's mapped height holds at least 80 % of the textured height (what corners
      see) and at most 120 % of the roof (required), and at least 90 % of the roof (goal: the plain
      top too, which only its outline shows; the paper's map reached about 75 % of its roof height,
      which was about its textured height). Without ``roof_height_m`` the roof is the textured height;
    * comparison: this run's height error against the roof, averaged over the laps, is smaller than
      ``other_laps``' (the Cartesian baseline), when given: the paper compares the parameterisations
      lap by lap (figs. 2 and 3), how soon the obstacle is mapped as well as how high (see
      :func:`mean_height_error`);
    * the paper: the last lap's height as a fraction of ``roof_height_m`` beside the paper's 0.75.
    """
    def last(key):
        return laps[-1].get(key, math.nan) if laps else math.nan

    clear = np.array([_finite_or_nan(lap.get("min_clearance_m")) for lap in laps], float)
    worst = float(np.min(clear)) if len(clear) and np.isfinite(clear).all() else math.nan
    ratio = worst / clearance_m if clearance_m > 0 else math.nan
    first = float(clear[0]) / clearance_m if len(clear) and clearance_m > 0 else math.nan
    flat = np.array([_finite_or_nan(lap.get("cruise_height_over_flat_m")) for lap in laps], float)
    excess = float(np.max(flat)) - nominal_alt_m if len(flat) and np.isfinite(flat).all() else math.nan
    height = last("mapped_obstacle_height_m")
    roof = roof_height_m if roof_height_m > 0 else textured_height_m
    out = {
        "laps_judged": len(laps),
        "worst_clearance_m": worst,
        "clearance_ratio": ratio,
        "first_lap_clearance_ratio": first,
        "issue_clearance_ok": bool(np.isfinite(ratio)) and ratio >= CLEARANCE_REQUIRED,
        "goal_clearance_ok": bool(np.isfinite(ratio)) and ratio >= CLEARANCE_GOAL,
        "flat_excess_m": excess,
        "goal_flat_height_ok": bool(np.isfinite(excess)) and abs(excess) <= FLAT_EXCESS_GOAL_M,
        "height_ratio_last_lap": height / textured_height_m if textured_height_m > 0 else math.nan,
        "issue_height_ok": bool(np.isfinite(height)) and 0.8 * textured_height_m <= height <= 1.2 * roof,
        "goal_height_ok": bool(np.isfinite(height)) and 0.9 * roof <= height <= 1.2 * roof,
        "height_fraction_of_roof_last_lap": height / roof_height_m if roof_height_m > 0 else math.nan,
        "paper_fraction_of_roof": PAPER_MAPPED_FRACTION,
    }
    out["mean_height_error_m"] = mean_height_error(laps, roof)
    if other_laps is not None:
        err, other_err = out["mean_height_error_m"], mean_height_error(other_laps, roof)
        out["other_mean_height_error_m"] = other_err
        out["maps_better_than_other"] = bool(np.isfinite(err)) and (not np.isfinite(other_err) or err < other_err)
    return out


def _finite_or_nan(x) -> float:
    return float(x) if x is not None and math.isfinite(float(x)) else math.nan


def mean_height_error(laps: list[dict], height_m: float) -> float:
    """Mean over the laps of ``|mapped_obstacle_height_m - height_m|`` (m), ``height_m`` the height
    the map should hold (the roof); a lap whose map holds nothing of the obstacle (NaN) counts the
    whole height. NaN without laps."""
    if not laps:
        return math.nan
    h = np.array([math.nan if lap.get("mapped_obstacle_height_m") is None else lap["mapped_obstacle_height_m"]
                  for lap in laps], float)
    err = np.where(np.isfinite(h), np.abs(h - height_m), height_m)
    return float(err.mean())
