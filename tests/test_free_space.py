"""Bounds on the terrain from what the camera saw: free space (ceilings, carving), floors from
features not yet converged, and how the law reads them (docs/terrain.md "Free space" and
"Floors", docs/mapper.md "Bounds of an unconverged feature", docs/avoidance.md "What a cell may
hold" and "Unmapped cells")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import AvoidanceConfig, MapperConfig
from companion.method.avoidance import PullUpLaw, law_heights
from companion.method.geometry import camera_from_config
from companion.config import CameraConfig
from companion.method.mapper import Mapper
from companion.method.mapper import cartesian, inverse_depth
from companion.method.messages import FreeSpaceRays, TerrainFloors, TerrainPoints
from companion.method.terrain import TerrainGrid
from companion.method.terrain.codec import decode_tile, encode_tile
from companion.method.terrain.fusion import confirm_floor, highest_two_per_cell
from companion.method.terrain.grid import Corridor


def one_ray(end, origin=(0.0, 0.0, -15.0)):
    return FreeSpaceRays(0.0, np.array(origin, float), np.array([end], float))


def bounds(grid, north, east=0.5):
    """(ceiling, floor) of the cell holding (north, east)."""
    ci, cj = grid.cell_index(np.array([north]), np.array([east]))
    key = (int(ci[0]) // grid.tile_cells, int(cj[0]) // grid.tile_cells)
    t = grid.tile(key, with_disagreement=True)
    i, j = int(ci[0]) % grid.tile_cells, int(cj[0]) % grid.tile_cells
    return float(t.ceiling[i, j]), float(t.floor[i, j])


def test_a_line_of_sight_bounds_the_cells_below_it_from_above():
    """Camera at 15 m, a ground feature 20 m north: over a cell the line of sight passes at
    15 (1 - s / 20) for the samples s in that cell; the ceiling is the lowest of them. Cells nearer
    than carve_start_m or within carve_end_margin_m of the end are not touched."""
    grid = TerrainGrid(carve_start_m=2.0, carve_end_margin_m=1.5)
    stats = grid.carve(one_ray((20.0, 0.2, 0.0)))
    assert stats.rays == 1 and stats.cells_lowered > 10
    length = math.hypot(20.0, 0.2)
    samples = np.arange(2.0, length - 1.5 + 1e-9, 0.5)  # horizontal distances sampled, every half cell
    for north in (3.5, 10.5, 17.5):
        inside = samples[np.floor(samples * 20.0 / length) == math.floor(north)]
        ceiling, floor = bounds(grid, north, 0.2)
        assert ceiling == pytest.approx(15.0 * (1 - inside.max() / length), abs=1e-4)
        assert floor == -np.inf
    assert bounds(grid, 0.5, 0.2)[0] == np.inf  # nearer than carve_start_m
    assert bounds(grid, 19.5, 0.2)[0] == np.inf  # the feature's own cell, within the end margin
    # A second, lower line of sight lowers the ceiling; a higher one leaves it.
    before = bounds(grid, 10.5, 0.2)[0]
    grid.carve(one_ray((12.0, 0.2, 0.0)))
    assert bounds(grid, 10.5, 0.2)[0] < before
    low = bounds(grid, 10.5, 0.2)[0]
    grid.carve(one_ray((40.0, 0.2, 0.0)))
    assert bounds(grid, 10.5, 0.2)[0] == low


def test_a_phantom_does_not_survive_carve_rays_looks_through_it():
    """A cell mapped at 8 m where lines of sight pass at ~3 m: each frame through it counts
    reset_evidence / carve_rays of disagreement; the third clears it. A point agreeing with the
    cell in between starts the count again."""
    grid = TerrainGrid(carve_rays=3.0, gate_min_count=10**6, lone_rise_m=math.inf)  # the phantom got in
    phantom = TerrainPoints(0.0, np.array([[16.5, 0.5, -8.0]]), np.eye(3)[None] * 0.01, np.array([1]))
    grid.insert(phantom)
    ray = one_ray((20.0, 0.5, 0.0))  # passes over north 16.5 at ~2.6 m
    grid.carve(ray)
    grid.carve(ray)
    assert grid.height_at(np.array([16.5]), np.array([0.5]))[2][0] == 1  # still there after two looks
    grid.insert(phantom)  # the cell seen again: agreeing evidence
    grid.carve(ray)
    grid.carve(ray)
    assert grid.height_at(np.array([16.5]), np.array([0.5]))[2][0] > 0
    stats = grid.carve(ray)
    h, _, n = grid.height_at(np.array([16.5]), np.array([0.5]))
    assert stats.cells_cleared == 1 and n[0] == 0 and np.isnan(h[0])


def test_one_feature_seen_through_a_cell_in_many_frames_counts_once():
    """A feature tracked wrongly (occluded by a mast and still matched, its range past the mast)
    repeats its line of sight under the mast's cell every frame: with the segments' feature ids
    the cell counts features, not frames, so ten frames of one feature leave it, and the third
    distinct feature clears it (two in one frame count two). An agreeing point forgets them."""
    grid = TerrainGrid(carve_rays=3.0, gate_min_count=10**6, lone_rise_m=math.inf)
    top = TerrainPoints(0.0, np.array([[16.5, 0.5, -30.0]]), np.eye(3)[None] * 0.01, np.array([1]))
    grid.insert(top)

    def rays(*ids):
        return FreeSpaceRays(0.0, np.array([0.0, 0.0, -40.0]), np.array([[20.0, 0.5, -5.0]] * len(ids)), np.array(ids))

    def mapped():
        return int(grid.height_at(np.array([16.5]), np.array([0.5]))[2][0]) > 0

    for _ in range(10):
        stats = grid.carve(rays(7))
        assert stats.cells_passed_under == 1 and stats.cells_cleared == 0
    assert mapped()
    grid.carve(rays(8))
    assert mapped()  # two features
    grid.insert(top)  # seen again: the disagreement and its features are forgotten
    grid.carve(rays(7))
    grid.carve(rays(7, 7))
    stats = grid.carve(rays(7, 8))
    assert mapped() and stats.cells_cleared == 0  # 7 counts again after the agreeing point, once; 8
    stats = grid.carve(rays(8, 9, 10))  # 9 is the third
    assert stats.cells_cleared == 1 and not mapped()
    with pytest.raises(ValueError, match="feature_ids"):  # a malformed message, not a silent miscount
        grid.carve(FreeSpaceRays(0.0, np.array([0.0, 0.0, -40.0]), np.array([[20.0, 0.5, -5.0]]), np.array([1, 2])))


def test_a_line_of_sight_takes_away_only_what_it_surely_crossed():
    """The lines of sight's direction is known to angle_sigma_rad: at 25 m from the camera a 2 deg
    sigma puts a segment 0.87 m to either side (1 sigma), beyond carve_lateral_sigma_m (0.5 m), so
    it may have passed beside a thin mast's cell: five features there leave the cell's height and
    its floor (and lower its ceiling). At 10 m (0.35 m) the third clears it, as with an exact
    direction at any distance."""
    def setup(north):
        grid = TerrainGrid(carve_rays=3.0, carve_lateral_sigma_m=0.5, gate_min_count=10**6, lone_rise_m=math.inf)
        grid.insert(TerrainPoints(0.0, np.array([[north, 0.5, -30.0]]), np.eye(3)[None] * 0.01, np.array([1])))
        grid.raise_floors(TerrainFloors(0.0, np.array([[north, 0.5, -25.0]] * 2)))
        return grid

    def rays(north, ids, sigma):  # camera at 40 m, 0.5 north: each segment passes the cell at 20 m
        end = np.array([north + (north - 0.5), 0.5, 0.0])
        return FreeSpaceRays(0.0, np.array([0.5, 0.5, -40.0]), np.array([end] * len(ids)), np.array(ids), sigma)

    def mapped(grid, north):
        return int(grid.height_at(np.array([north]), np.array([0.5]))[2][0]) > 0

    far, near, sigma = 25.5, 10.5, np.radians(2.0)
    grid = setup(far)
    for fid in range(5):
        stats = grid.carve(rays(far, [fid], sigma))
        assert stats.cells_passed_under == 0 and stats.floors_dropped == 0
    assert mapped(grid, far) and bounds(grid, far)[1] == pytest.approx(25.0)
    assert bounds(grid, far)[0] == pytest.approx(20.0, abs=0.6)  # the ceiling is still the line's
    for north, s in ((near, sigma), (far, 0.0)):
        grid = setup(north)
        grid.carve(rays(north, [0, 1], s))
        assert mapped(grid, north)
        stats = grid.carve(rays(north, [2], s))
        assert stats.cells_cleared == 1 and not mapped(grid, north) and bounds(grid, north)[1] == -np.inf


def test_floors_keep_the_highest_bound_and_a_line_of_sight_below_drops_them():
    grid = TerrainGrid()
    assert grid.raise_floors(TerrainFloors(0.0, np.array([[10.5, 0.5, -4.0], [10.6, 0.4, -6.0]]))) == 1
    assert bounds(grid, 10.5)[1] == pytest.approx(4.0)  # two bounds: the lower; 6 m waits
    assert grid.raise_floors(TerrainFloors(0.0, np.array([[10.5, 0.5, -6.0]]))) == 1  # 6 m again: confirmed
    assert bounds(grid, 10.5)[1] == pytest.approx(6.0)
    assert grid.raise_floors(TerrainFloors(0.0, np.array([[10.5, 0.5, -5.0]]))) == 0  # lower: no change
    assert grid.raise_floors(TerrainFloors(0.0, np.array([[np.nan, 0.5, -5.0], [2e6, 0.0, 0.0]]))) == 0  # invalid rows
    stats = grid.carve(one_ray((14.0, 0.5, 0.0)))  # passes over north 10.5 at ~3.2 m, below the floor
    assert stats.floors_dropped == 1 and bounds(grid, 10.5)[1] == -np.inf
    # A floor is not evidence of where the surface is: the map's height layer is untouched.
    assert grid.height_at(np.array([10.5]), np.array([0.5]))[2][0] == 0


def test_one_wild_bound_lifts_no_floor_and_a_second_confirms_only_the_lower():
    """As a point above a cell (docs/terrain.md, "Floors"): one bound alone raises nothing, however
    high; a second, of the same frame or a later one, in the cell or a neighbouring one, shows the
    terrain reaches at least the lower of the two. A line of sight below a pending bound drops it,
    as it drops a floor."""
    grid = TerrainGrid()
    assert grid.raise_floors(TerrainFloors(0.0, np.array([[10.5, 0.5, -5.0]]))) == 0  # a track a frame old, 5 m up
    assert bounds(grid, 10.5)[1] == -np.inf
    assert grid.raise_floors(TerrainFloors(0.1, np.array([[10.5, 0.5, -1.0]]))) == 1  # a second, lower
    assert bounds(grid, 10.5)[1] == pytest.approx(1.0)
    grid.carve(one_ray((14.0, 0.5, 0.0)))  # ~3.2 m over the cell: below the pending 5 m, above the floor
    assert bounds(grid, 10.5)[1] == pytest.approx(1.0)
    assert grid.raise_floors(TerrainFloors(0.2, np.array([[10.5, 0.5, -4.5]]))) == 0  # 5 m is gone; 4.5 m is above the line of sight
    assert bounds(grid, 10.5)[1] == pytest.approx(1.0)
    # A feature whose bound holds over two frames confirms itself.
    other = TerrainFloors(0.3, np.array([[30.5, 0.5, -7.0]]))
    assert grid.raise_floors(other) == 0 and grid.raise_floors(other) == 1
    assert bounds(grid, 30.5)[1] == pytest.approx(7.0)
    # So does one that moved to the next cell while converging, or another feature's bound there
    # (waiting, or of the same frame): at the lower of the two. Two cells apart is not support.
    assert grid.raise_floors(TerrainFloors(0.4, np.array([[50.5, 0.5, -9.0]]))) == 0
    assert grid.raise_floors(TerrainFloors(0.5, np.array([[51.5, 1.5, -8.0]]))) == 1  # diagonal neighbour
    assert bounds(grid, 51.5, 1.5)[1] == pytest.approx(8.0) and bounds(grid, 50.5)[1] == -np.inf
    assert grid.raise_floors(TerrainFloors(0.6, np.array([[60.5, 0.5, -6.0], [62.5, 0.5, -6.0]]))) == 0
    assert grid.raise_floors(TerrainFloors(0.7, np.array([[70.5, 0.5, -6.0], [70.5, 1.5, -4.0]]))) == 2
    assert bounds(grid, 70.5)[1] == pytest.approx(4.0) and bounds(grid, 70.5, 1.5)[1] == pytest.approx(4.0)


def test_a_bound_above_a_line_of_sight_already_seen_lifts_no_floor_in_either_order():
    """A line of sight crossed the cell at ~3.2 m: the terrain there is lower. Two bounds at 5 m
    lift nothing and do not wait, whether they come after the line of sight (refused) or before it
    (dropped by it); bounds within ``carve_margin_m`` of it, or in a cell no line of sight crossed,
    are floors as before."""
    ray = one_ray((14.0, 0.5, 0.0))  # over north 10.5 at 15 (1 - 11 / 14) = 3.2 m at the lowest
    five = TerrainFloors(0.0, np.array([[10.5, 0.5, -5.0], [10.6, 0.4, -5.0]]))
    after = TerrainGrid(carve_margin_m=0.5)
    after.carve(ray)
    ceiling = bounds(after, 10.5)[0]
    assert 3.0 < ceiling < 3.4
    assert after.raise_floors(five) == 0 and bounds(after, 10.5)[1] == -np.inf
    assert after.raise_floors(TerrainFloors(0.1, np.array([[10.5, 0.5, -5.0]]))) == 0  # nothing waited
    before = TerrainGrid(carve_margin_m=0.5)
    assert before.raise_floors(five) == 1
    assert before.carve(ray).floors_dropped == 1 and bounds(before, 10.5)[1] == -np.inf
    near = -(ceiling + 0.4)
    assert after.raise_floors(TerrainFloors(0.2, np.array([[10.5, 0.5, near], [10.6, 0.4, near]]))) == 1
    assert bounds(after, 10.5)[1] == pytest.approx(-near)
    assert after.raise_floors(TerrainFloors(0.3, np.array([[30.5, 0.5, -5.0], [30.6, 0.4, -5.0]]))) == 1
    assert bounds(after, 30.5)[1] == pytest.approx(5.0)


def test_a_floor_follows_the_feature_that_set_it_and_stays_when_the_feature_dies():
    """A young feature's estimate slides along its line of sight while it converges: its bound of
    a frame ago, in the cell it has since left, is no longer its word, and the floor it set there
    goes. Another feature's floor stays; a feature that stops reporting (died) leaves its floor."""
    grid = TerrainGrid()

    def bounds_of(t, rows):
        return TerrainFloors(t, np.array([r[1:] for r in rows], float), np.array([r[0] for r in rows]))

    # Feature 7 at 5 m in north 10.5 over two frames: confirmed. Feature 8 at 4 m in north 40.5.
    grid.raise_floors(bounds_of(0.0, [(7, 10.5, 0.5, -5.0), (8, 40.5, 0.5, -4.0)]))
    assert grid.raise_floors(bounds_of(0.1, [(7, 10.5, 0.5, -5.0), (8, 40.5, 0.5, -4.0)])) == 2
    assert bounds(grid, 10.5)[1] == pytest.approx(5.0) and bounds(grid, 40.5)[1] == pytest.approx(4.0)
    # Feature 7 now bounds north 13.5 at 3 m (it slid): 10.5 loses its floor; 8, in its cell, keeps.
    grid.raise_floors(bounds_of(0.2, [(7, 13.5, 0.5, -3.0), (8, 40.5, 0.5, -3.5)]))
    assert bounds(grid, 10.5)[1] == -np.inf and bounds(grid, 40.5)[1] == pytest.approx(4.0)
    # Feature 8 dies (reports no more); feature 9 elsewhere: 8's floor stays.
    grid.raise_floors(bounds_of(0.3, [(9, 70.5, 0.5, -2.0)]))
    assert bounds(grid, 40.5)[1] == pytest.approx(4.0)
    # Without feature ids (an older producer) floors are kept as they were.
    plain = TerrainGrid()
    plain.raise_floors(TerrainFloors(0.0, np.array([[10.5, 0.5, -5.0], [10.6, 0.4, -5.0]])))
    plain.raise_floors(TerrainFloors(0.1, np.array([[13.5, 0.5, -3.0], [13.6, 0.4, -3.0]])))
    assert bounds(plain, 10.5)[1] == pytest.approx(5.0)


def test_a_bound_no_feature_owns_stays_and_moves_no_feature_floor():
    """Rows of feature id -1 (rises seen by dense flow, docs/mapper.md) belong to no feature: a batch
    of them alone withdraws nothing, they do not move when later rows of -1 bound other cells, and
    a feature's floor keeps following its feature beside them; a line of sight below ends them."""
    grid = TerrainGrid()

    def bounds_of(t, rows):
        return TerrainFloors(t, np.array([r[1:] for r in rows], float), np.array([r[0] for r in rows]))

    grid.raise_floors(bounds_of(0.0, [(7, 10.5, 0.5, -5.0), (7, 10.5, 0.5, -5.0)]))
    assert bounds(grid, 10.5)[1] == pytest.approx(5.0)
    # a batch of unowned rows only: two in north 30.5 confirm a floor there, nothing else moves
    assert grid.raise_floors(bounds_of(0.1, [(-1, 30.5, 0.5, -9.0), (-1, 30.6, 0.4, -8.0)])) == 1
    assert bounds(grid, 30.5)[1] == pytest.approx(8.0) and bounds(grid, 10.5)[1] == pytest.approx(5.0)
    # unowned rows elsewhere later: the first unowned floor stays (it does not follow "feature -1")
    grid.raise_floors(bounds_of(0.2, [(-1, 50.5, 0.5, -4.0), (-1, 50.5, 0.5, -4.0), (7, 10.5, 0.5, -5.0)]))
    assert bounds(grid, 30.5)[1] == pytest.approx(8.0) and bounds(grid, 50.5)[1] == pytest.approx(4.0)
    # feature 7 slides to another cell: its floor goes, the unowned ones stay
    grid.raise_floors(bounds_of(0.3, [(7, 13.5, 0.5, -3.0)]))
    assert bounds(grid, 10.5)[1] == -np.inf and bounds(grid, 30.5)[1] == pytest.approx(8.0)
    # a line of sight passing below an unowned floor ends it, as any floor
    stats = grid.carve(one_ray((34.0, 0.5, 0.0), origin=(20.0, 0.5, -15.0)))  # over north 30.5 at ~3.7 m
    assert stats.floors_dropped == 1 and bounds(grid, 30.5)[1] == -np.inf


def test_a_floor_whose_feature_ended_goes_when_nothing_near_backs_it():
    """docs/terrain.md, "A floor whose feature ended": a feature that confirmed its own bound and
    then left the mapper without converging leaves a floor nothing else says; alone (more than
    lone_rise_m above every height in the 3x3 blocks of 4 cells around it) it goes, counted. One
    within lone_rise_m of a mapped cell, a pending height or a live feature's floor near it stays,
    and so does a floor whose feature is still alive."""
    grid = TerrainGrid()  # lone_rise_m 1.5, blocks of 4 cells
    cov = np.eye(3)[None] * 0.04

    def bounds_of(t, rows, ended=()):
        return TerrainFloors(t, np.array([r[1:] for r in rows], float).reshape(-1, 3), np.array([r[0] for r in rows], np.int64),
                             np.array(ended, np.int64))

    # Ground mapped at 0 m around north 40 and 80; floors of features 1 (40.5: 6 m, nothing near),
    # 2 (80.5: 1.2 m, ground 0 m two cells away), 3 (120.5: 6 m, feature 4's live floor of 5 m
    # three cells away) and 5 (160.5: 6 m, alive throughout).
    ground = np.array([[42.5, 0.5, 0.0], [43.5, 0.5, 0.0], [82.5, 0.5, 0.0], [83.5, 0.5, 0.0]])
    grid.insert(TerrainPoints(0.0, ground, np.repeat(cov, 4, axis=0), np.arange(100, 104)))
    grid.insert(TerrainPoints(0.0, ground, np.repeat(cov, 4, axis=0), np.arange(104, 108)))
    assert grid.height_at(np.array([42.5]), np.array([0.5]))[2][0] > 0
    rows = [(1, 40.5, 0.5, -6.0), (2, 80.5, 0.5, -1.2), (3, 120.5, 0.5, -6.0), (4, 123.5, 0.5, -5.0), (5, 160.5, 0.5, -6.0)]
    grid.add_evidence(TerrainPoints.empty(0.1), floors=bounds_of(0.1, rows))
    stats = grid.add_evidence(TerrainPoints.empty(0.2), floors=bounds_of(0.2, rows))  # held over two frames
    assert stats.lone_floors == 0
    assert [bounds(grid, n)[1] for n in (40.5, 80.5, 120.5, 160.5)] == pytest.approx([6.0, 1.2, 6.0, 6.0])
    # Features 1, 2 and 3 end (feature 4 still bounds its cell, 5 is still alive).
    stats = grid.add_evidence(TerrainPoints.empty(0.3), floors=bounds_of(0.3, [rows[3], rows[4]], ended=[1, 2, 3]))
    assert stats.lone_floors == 1
    assert bounds(grid, 40.5)[1] == -np.inf  # alone: gone
    assert bounds(grid, 80.5)[1] == pytest.approx(1.2)  # within 1.5 m of the ground near it
    assert bounds(grid, 120.5)[1] == pytest.approx(6.0)  # a live floor 1 m below it, 3 cells away
    assert bounds(grid, 160.5)[1] == pytest.approx(6.0)  # its feature lives
    # What stayed is nobody's now: the same ids ending again change nothing.
    assert grid.withdraw_ended_floors(np.array([1, 2, 3])) == 0
    assert bounds(grid, 120.5)[1] == pytest.approx(6.0)


def test_the_floors_of_features_that_ended_together_do_not_back_each_other():
    """Two floors side by side whose features both ended are each judged with the other gone:
    neither is evidence any more. A floor one of them no longer holds (dropped by a line of sight
    since) is not withdrawn twice, and an id the map never saw is ignored."""
    grid = TerrainGrid()
    rows = np.array([[10.5, 0.5, -6.0], [11.5, 0.5, -6.0]])
    for t in (0.0, 0.1):
        grid.raise_floors(TerrainFloors(t, rows, np.array([1, 2])))
    assert [bounds(grid, n)[1] for n in (10.5, 11.5)] == pytest.approx([6.0, 6.0])
    assert grid.withdraw_ended_floors(np.array([1, 2, 99])) == 2
    assert [bounds(grid, n)[1] for n in (10.5, 11.5)] == [-np.inf, -np.inf]
    # A line of sight drops feature 7's floor before it ends: nothing left to withdraw.
    for t in (0.2, 0.3):
        grid.raise_floors(TerrainFloors(t, np.array([[30.5, 0.5, -6.0]]), np.array([7])))
    grid.carve(one_ray((40.0, 0.5, -2.0), origin=(20.0, 0.5, -2.0)))
    assert bounds(grid, 30.5)[1] == -np.inf
    assert grid.withdraw_ended_floors(np.array([7])) == 0


def test_confirm_floor_is_the_second_highest_of_the_pending_and_the_batch():
    inf = np.inf
    h1 = np.array([5.0, 5.0, 5.0, -inf, 3.0])
    h2 = np.array([2.0, -inf, -inf, -inf, -inf])
    pending = np.array([-inf, 4.0, 7.0, 6.0, -inf])
    floor, still = confirm_floor(h1, h2, pending)
    assert floor.tolist() == [2.0, 4.0, 5.0, -inf, -inf]
    assert still.tolist() == [5.0, 5.0, 7.0, 6.0, 3.0]
    cell = np.array([2, 0, 2, 2, 1])
    first, second = highest_two_per_cell(cell, np.array([1.0, 4.0, 3.0, 2.0, 0.5]), 4)
    assert first.tolist() == [4.0, 0.5, 3.0, -inf] and second.tolist() == [-inf, -inf, 2.0, -inf]


def test_a_cells_own_points_replace_its_floor_and_live_features_raise_theirs_again():
    """A floor is a warning until the cell's own evidence comes (docs/terrain.md, "Floors"): a
    point that sets the cell's height drops it, so a floor left by a feature that converged
    elsewhere or died does not outlive the point; in the same frame a feature still unconverged
    raises its floor again after the points, so a live warning stands."""
    grid = TerrainGrid()
    cov = np.eye(3)[None] * 0.09
    stale = TerrainFloors(0.0, np.array([[10.5, 0.5, -3.0]]))
    grid.add_evidence(TerrainPoints.empty(0.0), floors=stale)
    grid.add_evidence(TerrainPoints.empty(0.05), floors=stale)  # held over two frames: confirmed
    assert bounds(grid, 10.5)[1] == pytest.approx(3.0)
    grid.add_evidence(TerrainPoints(0.1, np.array([[10.5, 0.5, 1.0]]), cov, np.array([1])))  # h = -1 m
    h, _, n = grid.height_at(np.array([10.5]), np.array([0.5]))
    assert n[0] == 1 and h[0] == pytest.approx(-1.0)
    assert bounds(grid, 10.5)[1] == -np.inf
    # Points and a live floor in the same frame: the floor stands after the points.
    grid.add_evidence(TerrainPoints(0.2, np.array([[10.5, 0.5, 1.0]]), cov, np.array([2])),
                      floors=TerrainFloors(0.2, np.array([[10.5, 0.5, -4.0], [10.5, 0.5, -4.0]])))
    assert bounds(grid, 10.5)[1] == pytest.approx(4.0)
    # A point in another cell leaves this cell's floor alone.
    grid.add_evidence(TerrainPoints(0.3, np.array([[20.5, 0.5, 0.0]]), cov, np.array([3])))
    assert bounds(grid, 10.5)[1] == pytest.approx(4.0)


def test_snapshots_carry_ceiling_weight_and_floor_and_the_wire_does_not():
    grid = TerrainGrid()
    grid.insert(TerrainPoints(0.0, np.array([[5.5, 0.5, -1.0]]), np.eye(3)[None] * 0.01, np.array([1])))
    grid.carve(one_ray((20.0, 0.5, 0.0)))
    grid.raise_floors(TerrainFloors(0.0, np.array([[12.5, 0.5, -2.0], [12.5, 0.5, -2.0]])))
    for key in grid.keys():
        full = grid.tile(key, with_disagreement=True)
        back = decode_tile(encode_tile(full, with_disagreement=True))
        assert back.same_as(full) and back.floor is not None and back.ceiling is not None and back.weight is not None
        wire = decode_tile(encode_tile(full))
        assert wire.ceiling is None and wire.floor is None and wire.weight is None
        restored = TerrainGrid()
        restored.put_tile(back)
        assert restored.tile(key, with_disagreement=True).same_as(full)


def corridor(height, variance, count, ceiling, floor):
    k = len(height)
    along = np.arange(k, dtype=float)
    return along, Corridor(np.zeros(k), along, along, np.zeros(k), np.asarray(height, float), np.asarray(variance, float),
                           np.asarray(count), np.asarray(ceiling, float), np.asarray(variance, float), np.asarray(floor, float))


def test_what_a_cell_may_hold():
    """max(h, min(h + k sigma, ceiling)) for a mapped cell; an unmapped one takes its neighbours'
    (within fill) no higher than its own ceiling; every cell at least its floor."""
    inf = np.inf
    along, c = corridor(
        height=[8.0, 8.0, 8.0, np.nan, np.nan, 8.0, np.nan],
        variance=[1.0, 1.0, 1.0, inf, inf, 1.0, inf],
        count=[3, 3, 3, 0, 0, 3, 0],
        ceiling=[inf, 9.0, 7.0, 5.0, inf, inf, inf],
        floor=[-inf, -inf, -inf, -inf, -inf, 12.0, -inf],
    )
    got = law_heights(along, c, 2.0, 1.0, 1.0, False)
    assert got[0] == pytest.approx(10.0)  # h + 2 sigma
    assert got[1] == pytest.approx(9.0)   # capped by the free space seen above it
    assert got[2] == pytest.approx(8.0)   # never below its own estimate
    assert got[3] == pytest.approx(5.0)   # a gap stands in at its neighbour's 10 m, capped by its ceiling
    assert got[4] == pytest.approx(10.0)  # a gap: the neighbour's estimate + 2 sigma (its floor is its own)
    assert got[5] == pytest.approx(12.0)  # the floor lifts the cell
    assert got[6] == pytest.approx(10.0)
    # Alone, an unmapped cell with a floor counts at it; with nothing, it is NaN (not ground at zero).
    along, c = corridor([np.nan, np.nan], [inf, inf], [0, 0], [inf, inf], [6.0, -inf])
    got = law_heights(along, c, 2.0, 0.0, 1.0, False)
    assert got[0] == pytest.approx(6.0) and np.isnan(got[1])


CFG = AvoidanceConfig(clearance_m=10.0, accel_mps2=1.0, miss_distance_m=3.0, lookahead_m=80.0, height_margin_sigma=0.0,
                      max_climb_mps=3.0, max_descent_mps=2.0, nominal_alt_m=10.0)


def test_a_floor_ahead_makes_the_law_climb_before_any_point_converged():
    grid = TerrainGrid()
    law = PullUpLaw(CFG)
    assert law.command([0.0, 0.5, -10.0], [5.0, 0.0, 0.0], grid).climb_rate_mps == pytest.approx(0.0)
    for _ in range(2):  # a feature's bound held over two frames
        grid.raise_floors(TerrainFloors(0.0, np.array([[25.5, 0.5, -6.0]])))
    cmd = law.command([0.0, 0.5, -10.0], [5.0, 0.0, 0.0], grid)
    assert cmd.engaged and cmd.limiting_height_m == pytest.approx(6.0) and cmd.climb_rate_mps > 0


def test_the_law_looks_along_the_route_not_the_drift():
    """The vehicle flies north-east (turning) while its route leads north: the obstacle north counts,
    at the speed over ground along the route (3 m/s)."""
    grid = TerrainGrid()
    grid.raise_floors(TerrainFloors(0.0, np.array([[20.5, 0.5, -8.0], [20.5, 0.5, -8.0]])))
    law = PullUpLaw(CFG)
    drift = law.command([0.0, 0.5, -10.0], [3.0, 3.0, 0.0], grid)
    along_route = law.command([0.0, 0.5, -10.0], [3.0, 3.0, 0.0], grid, direction_ne=[1.0, 0.0])
    assert not drift.engaged and along_route.engaged


def test_descent_over_ground_seen_only_through_free_space_stops_above_its_ceiling():
    """After a plain roof the vehicle is 9 m above its nominal altitude over unmapped ground. With
    nothing seen below it holds; with lines of sight below (ceilings at most 3 m) it descends, to no
    lower than the highest ceiling + the clearance."""
    law = PullUpLaw(CFG)
    grid = TerrainGrid()
    high = law.command([50.0, 0.5, -19.0], [5.0, 0.0, 0.0], grid)
    assert high.holding_over_unknown and high.climb_rate_mps == 0.0
    n, e = np.meshgrid(np.arange(30.0, 60.0) + 0.5, np.arange(-6.0, 7.0) + 0.5, indexing="ij")
    ends = np.column_stack([n.ravel() + 1.6, e.ravel(), np.zeros(n.size)])
    for dz in (-1.0, -2.0, -3.0):  # lines of sight from 1, 2, 3 m above each cell: the ceilings come down to ~ that
        for o_n in np.arange(20.0, 60.0, 5.0):
            grid.carve(FreeSpaceRays(0.0, np.array([o_n, 0.0, dz]), ends[ends[:, 0] > o_n + 4.0]))
    cmd = law.command([50.0, 0.5, -19.0], [5.0, 0.0, 0.0], grid)
    assert not cmd.holding_over_unknown and cmd.climb_rate_mps < 0.0
    from companion.method.avoidance import ground_below
    mapped, seen, top = ground_below(grid, np.array([50.0, 0.5]), 3.0 + math.sqrt(0.5), np.array([1.0, 0.0]))
    assert mapped == 0.0 and seen > 0.5 and 0.0 < top <= 3.0
    at_bound = law.command([50.0, 0.5, -(top + CFG.clearance_m)], [5.0, 0.0, 0.0], grid)
    assert at_bound.climb_rate_mps >= -1e-9


@pytest.mark.parametrize("model", [inverse_depth, cartesian])
def test_point_at_sigma_moves_along_the_line_of_sight(model):
    """Inverse depth: the anchor ray at rho + k sigma_rho (so nearer for k > 0, farther for k < 0,
    at infinity when rho - |k| sigma_rho <= 0). Cartesian: X -+ k sigma_u along the ray from the
    origin."""
    R_ref = np.broadcast_to(inverse_depth.reference_rotation(np.eye(3)), (1, 3, 3)).copy()
    if model is inverse_depth:
        y = np.array([[1.0, 2.0, -15.0, 0.3, -0.2, 1 / 20.0]])
        P = np.zeros((1, 6, 6))
        P[0, 5, 5] = (0.01) ** 2
        X, _ = model.point_from_state(y, R_ref)
        m = inverse_depth.world_direction(y, R_ref)[0]
        for k, rho in ((2.0, 0.07), (-2.0, 0.03)):
            got = model.point_at_sigma(y, P, R_ref, y[:, :3], k)[0]
            assert got == pytest.approx(y[0, :3] + m / rho)
        assert np.isnan(model.point_at_sigma(y, P, R_ref, y[:, :3], -6.0)).all()  # 0.05 - 0.06 < 0: infinity
    else:
        origin = np.array([[0.0, 0.0, -15.0]])
        y = np.array([[12.0, 0.0, 1.0]])
        u = (y[0] - origin[0]) / np.linalg.norm(y[0] - origin[0])
        P = np.eye(3)[None] * 0.25
        for k in (2.0, -2.0):
            got = model.point_at_sigma(y, P, R_ref, origin, k)[0]
            assert got == pytest.approx(y[0] - k * 0.5 * u)


def test_the_mapper_floors_a_feature_at_the_lower_end_of_its_depth_bound():
    """A feature 20 m down a 45 deg line of sight with a 1.5 m depth sigma: its floor is the point
    2 sigma farther, whose height is lower by about 2 x 1.5 x sin 45 deg."""
    cfg = MapperConfig()
    camera, mount = camera_from_config(CameraConfig())
    mapper = Mapper(cfg, camera, mount)
    d = 20.0
    m_world = np.array([np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4)])  # NED: north and down
    R_ref = np.broadcast_to(np.eye(3), (1, 3, 3)).copy()
    psi, theta = inverse_depth.angles_from_vector(m_world[None])
    y = np.array([[0.0, 0.0, -15.0, psi[0], theta[0], 1.0 / d]])
    sigma_rho = 1.5 / d**2  # first order: sigma_d = sigma_rho / rho^2
    P = np.zeros((1, 6, 6))
    P[0, 5, 5] = sigma_rho**2
    floors = mapper._floors(1.0, y, P, R_ref, y[:, :3])
    far = 1.0 / (1.0 / d - cfg.floor_sigma * sigma_rho)
    assert len(floors) == 1
    assert -floors.positions_ned_m[0, 2] == pytest.approx(15.0 - far * np.sin(np.pi / 4))
    assert -floors.positions_ned_m[0, 2] < 15.0 - d * np.sin(np.pi / 4)  # below the estimate
    assert floors.positions_ned_m[0, :2] == pytest.approx([d * np.cos(np.pi / 4), 0.0])  # at the estimate


def test_a_tile_carving_creates_is_published_like_any_other():
    """Every tile the map holds is one a subscriber or a map query gets: a tile that only a line of
    sight reached (no height yet) is dirty too, so the daemon publishes it and its status's tile
    count matches what a late joiner's query returns."""
    grid = TerrainGrid()
    grid.carve(one_ray((70.0, 0.5, 0.0)))  # crosses tiles 0, 1 and 2 along north
    assert len(grid) >= 2 and grid.pop_dirty() == grid.keys()
    assert all(int((grid.tile(k).count > 0).sum()) == 0 for k in grid.keys())
    grid.raise_floors(TerrainFloors(0.0, np.array([[-40.5, 0.5, -3.0]])))
    assert grid.pop_dirty() == [(-2, 0)]
