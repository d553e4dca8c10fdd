"""The map kept in the navigation's vertical frame (docs/terrain.md, "The navigation's frame")."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import TerrainConfig
from companion.method.messages import FreeSpaceRays, TerrainFloors, TerrainPoints
from companion.method.terrain import TerrainGrid
from companion.method.terrain.frame import FrameTracker, weighted_median


def ground(t_s, frame_m, rng, n0=0.0, size=30, sigma=0.2, roof=None):
    """One look at flat ground (and a 6 m roof over ``roof``, a (n, e, size) square) in a
    navigation frame ``frame_m`` above the truth: one point per cell, noise ``sigma``."""
    n, e = np.meshgrid(n0 + 0.5 + np.arange(size), 0.5 + np.arange(size), indexing="ij")
    h = np.zeros(n.shape)
    if roof is not None:
        rn, re, rs = roof
        h[(n > rn) & (n < rn + rs) & (e > re) & (e < re + rs)] = 6.0
    h = h + frame_m + rng.normal(0.0, sigma, n.shape)
    pos = np.c_[n.ravel(), e.ravel(), -h.ravel()]
    cov = np.zeros((len(pos), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = 0.05**2
    cov[:, 2, 2] = sigma**2
    return TerrainPoints(float(t_s), pos, cov)


def cells(grid):
    h = np.concatenate([t.height[t.count > 0] for t in grid.tiles()])
    return h.astype(float)


def fly_passes(cfg, frames, rng, roof=None, looks=3):
    """Passes 60 s apart, each ``looks`` looks at the same ground (a second apart) in its frame."""
    grid = TerrainGrid.from_config(cfg)
    for k, frame in enumerate(frames):
        for j in range(looks):
            grid.insert(ground(60.0 * k + j, frame, rng, roof=roof))
    return grid


# -------------------------------------------------------------------------- weighted median


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-100, 100), st.floats(0.01, 10)), min_size=1, max_size=30))
def test_the_weighted_median_minimises_the_weighted_absolute_deviation(pairs):
    v = np.array([p[0] for p in pairs])
    w = np.array([p[1] for p in pairs])
    m = weighted_median(v, w)
    cost = lambda x: float(np.sum(w * np.abs(x - v)))  # noqa: E731
    assert m in v
    assert cost(m) <= min(cost(x) for x in v) + 1e-9 * (1 + np.sum(w) * 200)


def test_the_weighted_median_of_equal_weights_is_the_lower_median_and_nan_without_weight():
    assert weighted_median(np.array([3.0, 1.0, 2.0, 10.0]), np.ones(4)) == 2.0
    assert weighted_median(np.array([0.0, 5.0]), np.array([1.0, 3.0])) == 5.0
    assert np.isnan(weighted_median(np.zeros(0), np.zeros(0)))
    assert np.isnan(weighted_median(np.array([1.0]), np.array([0.0])))


# ---------------------------------------------------------------------------------- tracker


def test_the_tracker_moves_by_the_median_once_it_holds_enough_points_and_never_for_far_residuals():
    rng = np.random.default_rng(1)
    tr = FrameTracker(min_age_s=20.0, window_s=3.0, min_points=10.0, max_offset_m=3.0, deadband_m=0.05)
    r = 1.2 + rng.normal(0, 0.2, 9)
    assert tr.update(0.0, r, np.ones(9)) == 0.0  # nine points: not yet
    # The next batch: the window holds both; far residuals (another surface) are not counted at all.
    shift = tr.update(0.1, np.r_[1.25, -5.0, 4.0], np.ones(3))
    assert shift == weighted_median(np.r_[r, 1.25], np.ones(10))
    assert tr.shift_m == shift and tr.shifts == 1
    # The residuals kept are re-expressed against the moved map: the same evidence moves it no further.
    assert tr.update(0.2, np.zeros(0), np.zeros(0)) == 0.0
    # New pairs that agree with the moved map keep it; within the deadband nothing moves.
    assert tr.update(0.3, np.full(20, 0.03), np.ones(20)) == 0.0
    # After the window the old residuals are forgotten: a new shift is the new pairs' median alone.
    assert tr.update(5.0, np.full(12, -0.5), np.ones(12)) == -0.5
    assert abs(tr.shift_m - (shift - 0.5)) < 1e-12 and tr.shifts == 2


def test_the_tracker_weighs_each_pair_by_its_share_of_its_point():
    tr = FrameTracker(min_points=2.0)
    # Four pairs of one point shared over four cells (a quarter each) are one point: not enough.
    assert tr.update(0.0, np.full(4, 1.0), np.full(4, 0.25)) == 0.0
    assert tr.update(0.0, np.full(4, 1.0), np.full(4, 0.25)) == 1.0


# ------------------------------------------------------------------------------------- grid


def test_a_pass_in_a_higher_frame_moves_the_map_instead_of_raising_it_and_the_map_comes_back_down():
    """Three passes a minute apart over flat ground, the navigation's frame 0, +1.5, 0 m above
    the truth. Without tracking the top-surface rule raises every cell to the second pass's frame
    and keeps it there (the vehicle would fly 1.5 m high on the third); with it the map follows the
    frame, and after the third pass it is where the third pass sees the ground."""
    off = TerrainConfig(frame_tracking=False)
    on = TerrainConfig()
    ratchet = fly_passes(off, [0.0, 1.5, 0.0], np.random.default_rng(2))
    followed = fly_passes(on, [0.0, 1.5, 0.0], np.random.default_rng(2))
    assert abs(np.median(cells(ratchet)) - 1.5) < 0.15  # raised by the second pass, never lowered
    assert abs(np.median(cells(followed))) < 0.1
    assert followed.frame_shifts >= 2 and abs(followed.frame_shift_m) < 0.1  # up, then back down
    # In the second pass the map stood in that pass's frame.
    mid = fly_passes(on, [0.0, 1.5], np.random.default_rng(2))
    assert abs(np.median(cells(mid)) - 1.5) < 0.1 and abs(mid.frame_shift_m - 1.5) < 0.1


def test_a_roof_keeps_its_height_above_the_ground_when_the_map_moves():
    roof = (10.0, 10.0, 10.0)
    cfg = TerrainConfig()
    grid = fly_passes(cfg, [0.0, -1.0], np.random.default_rng(3), roof=roof)
    n, e = np.meshgrid(np.arange(30) + 0.5, np.arange(30) + 0.5, indexing="ij")
    h, _, _ = grid.height_at(n.ravel(), e.ravel())
    on_roof = ((n > 11) & (n < 19) & (e > 11) & (e < 19)).ravel()
    far = ((n < 8) | (n > 22) | (e < 8) | (e > 22)).ravel()
    assert abs(grid.frame_shift_m + 1.0) < 0.1
    assert abs(np.median(h[far]) + 1.0) < 0.1
    assert abs(np.median(h[on_roof]) - np.median(h[far]) - 6.0) < 0.1


def test_cells_made_within_the_minimum_age_say_nothing_of_the_frame():
    """Points a second after the cells they fall on, 0.4 m above them (a bias of the points, or the
    drift of a second): no shift; the cells fuse them."""
    grid = TerrainGrid.from_config(TerrainConfig())
    rng = np.random.default_rng(4)
    for j in range(10):
        grid.insert(ground(float(j), 0.4 * (j > 0), rng))
    assert grid.frame_shifts == 0 and grid.frame_shift_m == 0.0


def test_the_shift_moves_every_height_and_bound_in_the_navigation_frame_and_no_tile_of_the_map_frame():
    """Moving the map is its offset to the navigation's frame: every height and bound read in the
    navigation's frame moves by it (queries, tiles); the map's own frame, which is published, stays
    bit for bit, so no tile goes out again; evidence fused after the move lands where it was seen."""
    grid = TerrainGrid.from_config(TerrainConfig())
    grid.insert(ground(0.0, 0.0, np.random.default_rng(5), size=40))
    grid.insert(ground(0.5, 0.0, np.random.default_rng(6), size=40))
    grid.carve(FreeSpaceRays(1.0, np.array([0.5, 60.5, -20.0]), np.array([[0.5, 100.5, -1.0]])))
    grid.raise_floors(TerrainFloors(1.0, np.array([[5.5, 70.5, -3.0], [5.6, 70.4, -3.5], [8.5, 80.5, -4.0]])))
    before = {k: grid.tile(k, with_disagreement=True) for k in grid.keys()}
    published = {k: grid.tile(k, in_map_frame=True) for k in grid.keys()}
    corridor = grid.corridor((0.5, 0.5), (0.0, 1.0), 90.0, 10.0)
    grid.pop_dirty()
    grid.shift_heights(-0.15)
    grid.shift_heights(-0.9)
    grid.shift_heights(0.1)
    assert grid.pop_dirty() == [] and abs(grid.frame_shift_m + 0.95) < 1e-12 and grid.frame_shifts == 3
    for k, old in before.items():
        new = grid.tile(k, with_disagreement=True)
        for name in ("height", "pending", "ceiling", "floor"):
            a, b = getattr(old, name).astype(float), getattr(new, name).astype(float)
            finite = np.isfinite(a)
            assert np.array_equal(finite, np.isfinite(b)) and np.array_equal(a[~finite], b[~finite], equal_nan=True)
            assert np.allclose(b[finite], a[finite] - 0.95, atol=1e-5)
        assert np.array_equal(old.variance, new.variance) and np.array_equal(old.count, new.count)
        assert grid.tile(k, in_map_frame=True).same_as(published[k])
    assert np.isfinite([t.ceiling for t in before.values()]).any()
    assert np.isfinite([t.floor for t in before.values()]).any()
    moved = grid.corridor((0.5, 0.5), (0.0, 1.0), 90.0, 10.0)
    for name in ("height_m", "ceiling_m", "floor_m"):
        a, b = getattr(corridor, name), getattr(moved, name)
        finite = np.isfinite(a)
        assert finite.any() and np.array_equal(finite, np.isfinite(b)) and np.allclose(b[finite], a[finite] - 0.95)
    # The pending floor of (8.5, 80.5) at 4 m, confirmed after the move by a bound at 4.2 m seen now.
    grid.raise_floors(TerrainFloors(2.0, np.array([[8.5, 80.5, -4.2]])))
    assert abs(grid.corridor((8.5, 80.5), (1.0, 0.0), 0.0, 0.1).floor_m[0] - (4.0 - 0.95)) < 1e-5
    # A roof seen at 6 m after the move is at 6 m in the navigation's frame, 6.95 m in the map's.
    rng = np.random.default_rng(11)
    pts = np.column_stack([rng.uniform(30.2, 30.8, 20), rng.uniform(40.2, 40.8, 20), np.full(20, -6.0)])
    grid.insert(TerrainPoints(3.0, pts, np.tile(np.diag([0.01, 0.01, 0.04]), (20, 1, 1))))
    grid.insert(TerrainPoints(3.1, pts, np.tile(np.diag([0.01, 0.01, 0.04]), (20, 1, 1))))
    h, _, _ = grid.height_at(30.5, 40.5)
    key = tuple(int(v) for v in np.floor(np.array([30.5, 40.5]) / (grid.cell_size_m * grid.tile_cells)))
    in_map = grid.tile(key, in_map_frame=True).height[30 % 32, 40 % 32]
    assert abs(float(h) - 6.0) < 1e-4 and abs(float(in_map) - 6.95) < 1e-4


def test_a_map_loaded_from_a_snapshot_is_old_and_follows_the_frame_of_the_new_flight(tmp_path):
    """A snapshot holds an earlier flight's map; the barometer's frame has moved since. The first
    points of the new flight (time 0 of a new clock) re-reference it, where without tracking they
    would raise it to the new frame's noise top and leave it there."""
    cfg = TerrainConfig()
    grid = fly_passes(cfg, [0.0], np.random.default_rng(7))
    path = tmp_path / "terrain.snapshot"
    grid.save_snapshot(path)
    loaded = TerrainGrid.load_snapshot(path, cfg)
    loaded.insert(ground(0.0, -1.2, np.random.default_rng(8)))
    assert abs(loaded.frame_shift_m + 1.2) < 0.1
    assert abs(np.median(cells(loaded)) + 1.2) < 0.1


def test_a_batch_without_a_time_is_fused_and_moves_nothing():
    grid = TerrainGrid.from_config(TerrainConfig())
    rng = np.random.default_rng(9)
    grid.insert(ground(float("nan"), 0.0, rng))  # no time: no epoch either
    grid.insert(ground(0.0, 0.0, rng))
    grid.insert(ground(60.0, 1.0, rng))  # a minute later the cells are old: the map follows
    assert abs(grid.frame_shift_m - 1.0) < 0.1
    grid.insert(ground(float("nan"), -1.0, rng))  # a metre below, at no time: fused or ignored, no move
    assert abs(grid.frame_shift_m - 1.0) < 0.1 and grid.frame_shifts >= 1
