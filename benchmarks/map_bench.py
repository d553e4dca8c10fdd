"""Terrain map figures: inserting 1,000 converged points, an avoidance query over a 100 m
look-ahead, memory per km^2 at 1 m cells (square against strip), and the mapper's per-frame cost
against the size of the map it reads its depth prior from and writes its points to.

The 1,000 points are real converged features (positions and covariances) from a mapper run over
the rendered flight (:mod:`benchmarks.common`); areas are filled with one point per cell.
"""

from __future__ import annotations

import math
import time

import numpy as np

from benchmarks.common import Flight, summary, time_calls
from companion.config import AvoidanceConfig, TerrainConfig
from companion.method.avoidance import PullUpLaw
from companion.method.messages import TerrainPoints
from companion.method.terrain.grid import TerrainGrid

BYTES_PER_CELL = 32  # height f32, variance f32, count u32, disagreement f32, pending f32, ceiling f32, weight f32, floor f32 (companion.method.terrain.grid)


def converged_points(flight: Flight, n_points: int = 1000, n_features: int = 300) -> TerrainPoints:
    """``n_points`` converged features of a mapper run over the flight (repeated if fewer)."""
    from benchmarks.mapper_bench import new_mapper

    mapper = new_mapper(flight, n_features)
    pos, cov = [], []
    for nav, img in zip(flight.navs, flight.images):
        s = mapper.step(nav, img)
        if len(s.points):
            pos.append(s.points.positions_ned_m)
            cov.append(s.points.covariances)
        if sum(len(p) for p in pos) >= n_points:
            break
    P, C = np.concatenate(pos), np.concatenate(cov)
    idx = np.arange(n_points) % len(P)
    return TerrainPoints(0.0, P[idx], C[idx], np.arange(n_points, dtype=np.int64))


def fill_area(grid: TerrainGrid, north0: float, east0: float, north1: float, east1: float,
              height_fn=None, batch: int = 200_000) -> None:
    """One sharp point at the centre of every cell of the rectangle (heights ``height_fn(n, e)``, 0 by default)."""
    c = grid.cell_size_m
    n = np.arange(north0 + c / 2, north1, c)
    e = np.arange(east0 + c / 2, east1, c)
    N, E = np.meshgrid(n, e, indexing="ij")
    N, E = N.ravel(), E.ravel()
    H = np.zeros_like(N) if height_fn is None else height_fn(N, E)
    cov1 = np.diag([0.01, 0.01, 0.04])
    for a in range(0, len(N), batch):
        sl = slice(a, a + batch)
        k = len(N[sl])
        pos = np.column_stack([N[sl], E[sl], -H[sl]])
        grid.insert(TerrainPoints(0.0, pos, np.broadcast_to(cov1, (k, 3, 3)).copy(), np.arange(k, dtype=np.int64)))


def building(N, E):
    """A 12 m block 20 m x 20 m at (100, 0), as in the default scenario."""
    return np.where((np.abs(N - 100.0) < 10.0) & (np.abs(E) < 10.0), 12.0, 0.0)


def insert_benchmark(points: TerrainPoints, repeats: int) -> dict:
    """``TerrainGrid.insert`` of the points: into an empty grid (tiles created) and into a grid
    that already maps their area (steady state)."""
    cfg = TerrainConfig()
    empty = []
    for _ in range(repeats):
        grid = TerrainGrid.from_config(cfg)
        t0 = time.perf_counter()
        grid.insert(points)
        empty.append((time.perf_counter() - t0) * 1e3)
    grid = TerrainGrid.from_config(cfg)
    grid.insert(points)
    steady = time_calls(lambda: grid.insert(points), repeats)
    stats = grid.insert(points)
    return {"points": len(points), "empty_grid_ms": summary(empty), "mapped_area_ms": summary(steady),
            "pairs_cells_touched": stats.cells_touched, "tiles": len(grid)}


def avoidance_benchmark(repeats: int, seed: int = 3) -> dict:
    """``PullUpLaw.command`` at 6 m/s with a 100 m look-ahead over a mapped 400 m x 400 m area (with
    the 12 m block), from random positions and headings that keep the corridor inside the map."""
    grid = TerrainGrid.from_config(TerrainConfig())
    fill_area(grid, -100.0, -200.0, 300.0, 200.0, building)
    cfg = AvoidanceConfig(lookahead_m=100.0)
    law = PullUpLaw(cfg)
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(64):
        heading = rng.uniform(0, 2 * math.pi)
        d = np.array([math.cos(heading), math.sin(heading)])
        start = np.array([100.0, 0.0]) - d * rng.uniform(20.0, 110.0)  # towards the block
        cases.append((np.array([start[0], start[1], -15.0]), np.array([6.0 * d[0], 6.0 * d[1], 0.0])))
    it = iter(range(10**9))
    engaged = sum(law.command(p, v, grid).engaged for p, v in cases)

    def one():
        p, v = cases[next(it) % len(cases)]
        law.command(p, v, grid)

    times = time_calls(one, repeats, warmup=10)
    corridor = grid.corridor(cases[0][0][:2], cases[0][1][:2] / 6.0, cfg.lookahead_m + cfg.unknown_fill_m,
                             cfg.miss_distance_m + math.sqrt(0.5))
    return {"lookahead_m": cfg.lookahead_m, "query_ms": summary(times), "corridor_cells": len(corridor),
            "engaged_cases": f"{engaged}/{len(cases)}"}


def memory_table(shapes_m: list[tuple[float, float]]) -> list[dict]:
    """Memory of grids holding the given rectangles (north x east, m) at 1 m cells."""
    rows = []
    for length, width in shapes_m:
        grid = TerrainGrid.from_config(TerrainConfig())
        fill_area(grid, 0.0, 0.0, length, width)
        area_km2 = grid.observed_area_m2() / 1e6
        tiles = len(grid)
        t = grid.tile_cells
        in_tiles = tiles * t * t * BYTES_PER_CELL
        rows.append({"shape_m": f"{length:g} x {width:g}", "observed_km2": area_km2, "tiles": tiles,
                     "memory_MB": grid.memory_bytes() / 1e6, "tiles_MB": in_tiles / 1e6,
                     "MB_per_km2": grid.memory_bytes() / 1e6 / area_km2,
                     "tiles_MB_per_km2": in_tiles / 1e6 / area_km2})
    return rows


def mapper_vs_map_size(flight: Flight, sides_m: list[float], frames: int, n_features: int = 50) -> list[dict]:
    """Per-frame mapper cost (step + depth prior from the map + insertion of its points) with the
    map already holding a square of each side around the flight (the sizes interleaved frame by
    frame), plus the map's own queries alone on each map."""
    from benchmarks.mapper_bench import run_interleaved, variant

    grids = {}
    for side in sides_m:
        grid = TerrainGrid.from_config(TerrainConfig())
        if side > 0:
            fill_area(grid, 70.0 - side / 2, -side / 2, 70.0 + side / 2, side / 2)
        grids[side] = grid
    sizes = {side: (grid.observed_area_m2() / 1e6, len(grid)) for side, grid in grids.items()}
    runs = run_interleaved(flight, {side: variant(flight, n_features, grid=lambda g=g: g) for side, g in grids.items()},
                           repeats=1, warmup_frames=10, frames=frames)
    rays = np.array([[0.7, 0.0, 0.7], [0.6, 0.3, 0.74], [0.6, -0.3, 0.74]])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    law = PullUpLaw(AvoidanceConfig(lookahead_m=100.0))
    origin = np.array([50.0, 0.0, -15.0])
    rows = []
    for side, grid in grids.items():
        ray_ms = time_calls(lambda: grid.ray_range(origin, rays, 200.0), 200)
        query_ms = time_calls(lambda: law.command(origin, np.array([6.0, 0.0, 0.0]), grid), 200)
        r = runs[side]
        rows.append({"map_side_m": side, "map_km2": sizes[side][0], "tiles": sizes[side][1],
                     "step_ms": r["step_ms"], "ray_range_ms": summary(ray_ms)["median"],
                     "avoidance_query_ms": summary(query_ms)["median"], "matched": r["matched"],
                     "memory_MB": grid.memory_bytes() / 1e6})
    return rows
