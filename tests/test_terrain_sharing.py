"""Evidence from other vehicles (companion/method/terrain/sharing.py, docs/terrain.md): placement in
this vehicle's frame, fusion against its derivation, a tile counted once however often it comes,
no echo of one's own evidence, trust and withdrawal, and the law's view of it all."""

from __future__ import annotations

import numpy as np
import pytest

from companion.method.messages import TerrainPoints
from companion.method.terrain.grid import TerrainGrid
from companion.method.terrain.sharing import SharedEvidence, SharedView, fuse_cells
from companion.method.terrain.tile import Tile

T, C = 8, 1.0


def tile(tx: int, ty: int, height: float, var: float = 0.25, count: int = 3, rows: slice = slice(None)) -> Tile:
    h = np.full((T, T), np.nan, np.float32)
    v = np.full((T, T), np.inf, np.float32)
    n = np.zeros((T, T), np.uint32)
    h[rows], v[rows], n[rows] = height, var, count
    return Tile(tx, ty, h, v, n, cell_size_m=C)


def at(shared: SharedEvidence, source: str, ci, cj):
    return shared.lookup(source, np.asarray(ci, np.int64), np.asarray(cj, np.int64))


def test_a_source_s_cells_land_shifted_by_its_origin_rounded_to_whole_cells():
    s = SharedEvidence("me", C, T)
    s.set_frame("other", (10.4, -3.6, 2.0))  # its origin 10.4 m north, 3.6 m west, 2 m above ours
    t = tile(0, 0, 5.0)
    t.height[2, 3] = 7.0
    assert s.put("other", t)
    h, v, n = at(s, "other", [2 + 10, 0 + 10, 7 + 10, -1 + 10], [3 - 4, 0 - 4, 7 - 4, 0 - 4])
    assert h[0] == pytest.approx(9.0) and h[1] == pytest.approx(7.0) and h[2] == pytest.approx(7.0)  # heights + 2 m
    assert np.isnan(h[3]) and n[3] == 0 and (n[:3] == 3).all() and (v[:3] == 0.25).all()
    # The tile straddles four of ours (offset not a multiple of T): every cell placed once.
    ci, cj = np.meshgrid(np.arange(10, 10 + T), np.arange(-4, -4 + T), indexing="ij")
    assert (at(s, "other", ci.ravel(), cj.ravel())[2] == 3).all()
    # A new frame re-places what was received.
    s.set_frame("other", (0.0, 0.0, 0.0))
    assert at(s, "other", [2], [3])[0][0] == pytest.approx(7.0) and np.isnan(at(s, "other", [12], [-1])[0][0])


def test_a_tile_received_again_replaces_its_predecessor_and_counts_once():
    s = SharedEvidence("me", C, T)
    s.set_frame("other", (0.0, 0.0, 0.0))
    s.put("other", tile(0, 0, 5.0, rows=slice(0, 4)))
    once = at(s, "other", [1], [1])
    for _ in range(3):  # the same tile again (republished, or a query reply)
        s.put("other", tile(0, 0, 5.0, rows=slice(0, 4)))
    assert [float(x[0]) for x in at(s, "other", [1], [1])] == [float(x[0]) for x in once]
    # A newer version that no longer knows a cell empties it.
    s.put("other", tile(0, 0, 6.0, rows=slice(0, 2)))
    h, _, n = at(s, "other", [1, 3], [1, 1])
    assert h[0] == pytest.approx(6.0) and np.isnan(h[1]) and n[1] == 0
    # Fused into the own map: the information of one tile, however often it came.
    own_h, own_v, own_n = np.array([5.0]), np.array([0.25]), np.array([2])
    fused = fuse_cells(own_h, own_v, own_n, *at(s, "other", [1], [1]), 3.0)
    assert fused[1][0] == pytest.approx(0.125)


def test_own_evidence_is_refused_and_a_withdrawn_or_unframed_source_gives_nothing():
    s = SharedEvidence("me", C, T)
    with pytest.raises(ValueError, match="this vehicle"):
        s.set_frame("me", (0.0, 0.0, 0.0))
    assert not s.put("other", tile(0, 0, 5.0))  # no frame yet: cannot be placed
    s.set_frame("other", (0.0, 0.0, 0.0))
    assert not s.put("other", Tile(0, 0, np.zeros((4, 4), np.float32), np.ones((4, 4), np.float32),
                                   np.ones((4, 4), np.uint32), cell_size_m=C))  # another lattice
    assert s.put("other", tile(0, 0, 5.0))
    s.withdraw("other")
    assert s.sources == []
    with pytest.raises(ValueError, match="weight"):
        s.set_frame("third", (0.0, 0.0, 0.0), weight=0.0)


def test_fusion_follows_its_derivation():
    """Only one known: that one. Agreeing within the gate: information adds. The other's far
    above: a higher surface, taken. Far below: left. Counts add where the other is used."""
    h = np.array([np.nan, 2.0, 2.0, 2.0, 2.0])
    v = np.array([np.inf, 0.5, 0.5, 0.5, 0.5])
    n = np.array([0, 4, 4, 4, 4])
    h_s = np.array([3.0, 2.6, 9.0, -6.0, np.nan])
    v_s = np.array([0.2, 0.3, 0.2, 0.2, np.inf])
    n_s = np.array([2, 2, 2, 2, 0])
    fh, fv, fn = fuse_cells(h, v, n, h_s, v_s, n_s, gate_sigma=3.0)
    assert (fh[0], fv[0], fn[0]) == (3.0, 0.2, 2)
    assert fh[1] == pytest.approx((2.0 / 0.5 + 2.6 / 0.3) / (1 / 0.5 + 1 / 0.3)) and fv[1] == pytest.approx(1 / (1 / 0.5 + 1 / 0.3))
    assert (fh[2], fv[2], fn[2]) == (9.0, 0.2, 6)
    assert (fh[3], fv[3], fn[3]) == (2.0, 0.5, 4) and (fh[4], fv[4], fn[4]) == (2.0, 0.5, 4)


def test_a_source_trusted_less_moves_an_agreeing_cell_less():
    s = SharedEvidence("me", C, T)
    s.set_frame("full", (0.0, 0.0, 0.0))
    s.set_frame("half", (0.0, 0.0, 0.0), weight=0.5)
    for name in ("full", "half"):
        s.put(name, tile(0, 0, 3.0, var=0.5))
    own = (np.array([2.0]), np.array([0.5]), np.array([4]))
    full = fuse_cells(*own, *at(s, "full", [0], [0]), 3.0)[0][0]
    half = fuse_cells(*own, *at(s, "half", [0], [0]), 3.0)[0][0]
    assert at(s, "half", [0], [0])[1][0] == pytest.approx(1.0)  # 0.5 / 0.5
    assert 2.0 < half < full == pytest.approx(2.5)


def test_the_law_s_view_fuses_another_vehicle_s_obstacle_into_its_corridor():
    """A wall 30 m ahead that only the other vehicle has mapped is in the corridor the law reads;
    the own grid, what this vehicle publishes, is untouched."""
    grid = TerrainGrid(cell_size_m=C, tile_cells=T)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 20, 300), rng.uniform(-4, 4, 300), rng.normal(0.0, 0.1, 300)]
    grid.insert(TerrainPoints(0.0, pts, np.tile(np.eye(3) * 0.01, (300, 1, 1))))
    s = SharedEvidence("me", C, T)
    s.set_frame("other", (0.0, 0.0, 0.0))
    s.put("other", tile(3, -1, 12.0, rows=slice(6, 8)))  # cells north 30-31, east -8..-1
    s.put("other", tile(3, 0, 12.0, rows=slice(6, 8)))   # east 0..7
    view = SharedView(grid, s)
    c = view.corridor(np.array([0.0, 0.0]), np.array([1.0, 0.0]), 60.0, 3.0)
    wall = (c.north_m > 30) & (c.north_m < 32)
    assert wall.any() and np.all(c.height_m[wall] == 12.0) and np.all(c.count[wall] == 3)
    own = grid.corridor(np.array([0.0, 0.0]), np.array([1.0, 0.0]), 60.0, 3.0)
    assert np.isnan(own.height_m[wall]).all()
    assert view.cell_size_m == grid.cell_size_m  # everything but the corridor is the own grid's
    ground = (c.north_m < 19) & (own.count > 0)
    np.testing.assert_array_equal(c.height_m[ground], own.height_m[ground])
