"""Pull-up / push-over law: the kinematics behind eqs. 18-20 (docs/avoidance.md) and the command."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from companion.method.avoidance import (
    PullUpLaw,
    ground_band,
    ground_below,
    ground_flown_over,
    ground_reference,
    height_restriction,
    law_heights,
    local_surface,
    minimum_climb_rate,
    nominal_climb_rate,
    soften_near_ground,
    stopping_time,
    time_to_go,
)
from companion.config import AvoidanceConfig
from companion.method.messages import TerrainPoints
from companion.method.terrain import TerrainGrid


def bang_bang_gain(w, s, a):
    """Altitude gained by +a then -a from climb rate w to zero climb rate in s/a seconds."""
    return (s * s + 2 * s * w - w * w) / (4 * a)


def profile_end(w, dt, a, cap, steps=20000):
    """Integrate the profile the law assumes: accelerate at +a (up to the cap) while the distance
    needed to stop at -a is not yet reached in the remaining time, then brake. Returns the
    altitude gained and the final climb rate."""
    # time-optimal structure: accelerate, (cruise), decelerate; found numerically by bisection on t1
    step = dt / steps
    k = np.arange(steps + 1)

    def run(t1):
        # climb rate at every step: +a (held at the cap) before the switch, -a after it
        n1 = min(int(math.ceil(t1 / step - 1e-12)), steps)  # steps taken at +a
        v = np.minimum(w + a * step * np.minimum(k, n1), cap)
        v[0] = w
        v -= a * step * np.maximum(k - n1, 0)
        return float(0.5 * step * (v[:-1] + v[1:]).sum()), float(v[-1])

    lo, hi = 0.0, dt
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        _, v = run(mid)
        lo, hi = (mid, hi) if v < 0 else (lo, mid)
    return run(0.5 * (lo + hi))


@settings(max_examples=100, deadline=None)
@given(gain=st.floats(-50, 50), dt=st.floats(0.1, 30), a=st.floats(0.2, 5))
def test_eq19_is_the_bang_bang_pull_up(gain, dt, a):
    """Between the push-over and the saturated regions, w = s - sqrt(2 s^2 - 4 a H) starts a
    +a/-a profile that arrives at h_i + h_c after dt with zero climb rate."""
    s = a * dt
    assume(-s * s / (2 * a) < gain <= s * s / (2 * a))
    w = float(minimum_climb_rate(np.array([gain]), np.array([dt]), a)[0])
    t1 = (s - w) / (2 * a)  # switch time from +a to -a
    assert -1e-9 <= t1 <= dt + 1e-9
    assert w + a * t1 - a * (dt - t1) == pytest.approx(0.0, abs=1e-9 * max(1, s))
    assert bang_bang_gain(w, s, a) == pytest.approx(gain, abs=1e-7 * max(1, abs(gain), s * s / a))
    # Tight: starting slower by 1 cm/s the same profile family falls short.
    assert bang_bang_gain(w - 0.01, s, a) < gain


@settings(max_examples=25, deadline=None)
@given(gain=st.floats(1, 40), dt=st.floats(2, 30), a=st.floats(0.3, 3), cap=st.floats(0.5, 5))
def test_climb_limit_gives_the_trapezoid(gain, dt, a, cap):
    """When the bang-bang peak would exceed max_climb, the bound is the start of an
    accelerate-cruise-brake profile that still arrives level at the restriction in time."""
    w = float(minimum_climb_rate(np.array([gain]), np.array([dt]), a, cap)[0])
    w_free = float(minimum_climb_rate(np.array([gain]), np.array([dt]), a)[0])
    assume(w < cap - 1e-3 and 0.5 * (a * dt + w_free) > cap)
    assert w >= w_free - 1e-12  # the cap can only make the bound stricter
    h, v = profile_end(w, dt, a, cap, steps=40000)
    assert v == pytest.approx(0.0, abs=2e-3 * max(1, a * dt))
    assert h == pytest.approx(gain, abs=0.02 * max(1, gain))


def test_push_over_and_saturated_regions_are_braking_curves():
    a, dt = 2.0, 1.5
    s = a * dt
    far_above = -5 * s * s / (2 * a)
    w = minimum_climb_rate(np.array([far_above]), np.array([dt]), a)[0]
    assert w == pytest.approx(-math.sqrt(2 * a * -far_above))
    assert w * w / (2 * a) == pytest.approx(-far_above)  # braking at a stops exactly at the restriction
    too_low = 3 * s * s / (2 * a)
    w = minimum_climb_rate(np.array([too_low]), np.array([dt]), a)[0]
    assert w == pytest.approx(math.sqrt(2 * a * too_low))
    # Eq. 20 (w = a dt) is the value on the boundary; over the obstacle (dt = 0) a vehicle still
    # below the restriction keeps climbing instead of being told 0.
    assert minimum_climb_rate(np.array([s * s / (2 * a)]), np.array([dt]), a)[0] == pytest.approx(s)
    assert minimum_climb_rate(np.array([4.0]), np.array([0.0]), a)[0] == pytest.approx(4.0)
    assert minimum_climb_rate(np.array([-4.0]), np.array([0.0]), a)[0] == pytest.approx(-4.0)
    assert minimum_climb_rate(np.array([4.0]), np.array([np.inf]), a)[0] == -np.inf


@settings(max_examples=40, deadline=None)
@given(dt=st.floats(0, 20), a=st.floats(0.2, 5), cap=st.one_of(st.just(math.inf), st.floats(0.5, 8)))
def test_bound_is_continuous_and_monotone(dt, a, cap):
    gains = np.linspace(-60, 60, 6001)
    w = minimum_climb_rate(gains, np.full(gains.shape, dt), a, cap)
    w = np.minimum(w, cap)  # beyond the cap the command is clipped anyway
    assert np.all(np.diff(w) >= -1e-9)
    # Lipschitz away from H = 0 at dt = 0 (sqrt there): steps of 0.02 m move w by little.
    assert np.max(np.diff(w)) < 0.5 + 2 * math.sqrt(2 * a * 0.02)
    later = minimum_climb_rate(gains, np.full(gains.shape, dt + 0.5), a, cap)
    assert np.all(np.minimum(later, cap) <= w + 1e-9)


def test_eq18_and_time_to_go():
    assert height_restriction(np.array(10.0), 5.0, 2.0, np.array(3.0)) == pytest.approx(6.0)
    along = np.array([20.0, 20.0, 3.0, -2.0])
    cross = np.array([0.0, 4.0, 1.0, 0.0])
    dt = time_to_go(along, cross, 5.0, 2.0)
    np.testing.assert_allclose(dt, [7.5, 8.5, 0.0, 0.0])
    np.testing.assert_array_equal(time_to_go(along, cross, 5.0, 0.0), [np.inf, np.inf, 0.0, 0.0])


def test_nominal_return_needs_at_most_a_c_and_is_linear_near_target():
    a, tau = 1.5, 1.2
    e = np.linspace(-40, 40, 80001)
    w = np.array([nominal_climb_rate(x, a, tau) for x in e])
    assert np.all(np.diff(w) > 0) and nominal_climb_rate(0.0, a, tau) == 0.0
    # Following w(e) with de/dt = -w needs dw/dt = -w'(e) w: never more than a.
    dwde = np.gradient(w, e)
    assert np.max(np.abs(dwde * w)) <= a * 1.001
    assert nominal_climb_rate(0.01, a, tau) == pytest.approx(0.01 / tau, rel=1e-2)
    assert nominal_climb_rate(-30.0, a, tau) == pytest.approx(-(math.sqrt(2 * a * 30 + (a * tau) ** 2) - a * tau))


def test_stopping_time():
    assert stopping_time(4.0, 1.0) == pytest.approx(4.0)  # 2 sqrt(H/a)
    assert stopping_time(16.0, 1.0, 3.0) == pytest.approx(16 / 3 + 3)
    assert stopping_time(-1.0, 1.0) == 0.0
    for gain, a, cap in [(4.0, 1.0, math.inf), (16.0, 1.0, 3.0), (9.0, 1.0, 3.0)]:
        t = stopping_time(gain, a, cap)
        assert minimum_climb_rate(np.array([gain]), np.array([t]), a, cap)[0] == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------------------------ the command


def mapped(cells, ground=0.0, extent=((-30, 150), (-20, 20))):
    """A grid with flat mapped ground and some cells (north, east, height) above it."""
    grid = TerrainGrid(gate_min_count=10**6)  # test maps: no gating, the last word wins
    (n0, n1), (e0, e1) = extent
    n, e = np.meshgrid(np.arange(n0, n1) + 0.5, np.arange(e0, e1) + 0.5, indexing="ij")
    pos = np.c_[n.ravel(), e.ravel(), np.full(n.size, -ground)]
    grid.insert(TerrainPoints(0.0, pos, np.tile(np.eye(3) * 1e-4, (len(pos), 1, 1))))
    if len(cells):
        cells = np.asarray(cells, dtype=float)
        # Replace the ground under the obstacle cells (a fresh grid would need evidence to move).
        g2 = TerrainGrid(gate_min_count=10**6)
        for key in grid.keys():
            g2.put_tile(grid.tile(key))
        grid = g2
        tiles = {}
        for n_, e_, h_ in cells:
            ci, cj = int(math.floor(n_)), int(math.floor(e_))
            key = (ci // 32, cj // 32)
            tile = tiles.get(key) or grid.tile(key)
            tile.height[ci % 32, cj % 32] = h_
            tiles[key] = tile
        for tile in tiles.values():
            grid.put_tile(tile)
    return grid


CFG = AvoidanceConfig(clearance_m=10.0, accel_mps2=1.0, miss_distance_m=3.0, lookahead_m=80.0, height_margin_sigma=0.0,
                      max_climb_mps=3.0, max_descent_mps=2.0, nominal_alt_m=10.0)


def test_level_flight_over_flat_ground_commands_nothing():
    c = PullUpLaw(CFG).command([0, 0.5, -10.0], [5, 0, 0], mapped([]))
    assert c.climb_rate_mps == pytest.approx(0.0, abs=1e-9) and not c.engaged
    assert c.unknown_cells_ahead == 0 and c.limiting_cell_ne is None


def test_obstacle_ahead_sets_the_command_and_reports_it():
    grid = mapped([[40.5, 0.5, 8.0]])
    far = PullUpLaw(CFG).command([0, 0.5, -10.0], [5, 0, 0], grid)
    assert not far.engaged  # 36 m to go: a level vehicle need not climb yet
    c = PullUpLaw(CFG).command([13, 0.5, -10.0], [5, 0, 0], grid)
    radius = CFG.miss_distance_m + math.sqrt(0.5)
    dt = (27.5 - radius) / 5.0
    expected = minimum_climb_rate(np.array([8.0]), np.array([dt]), 1.0, 3.0)[0]
    assert 0 < expected < 3.0
    assert c.engaged and c.limiting_cell_ne == (40.5, 0.5) and c.limiting_height_m == 8.0
    assert c.time_to_go_s == pytest.approx(dt)
    assert c.climb_rate_mps == pytest.approx(expected)
    assert c.required_alt_m == pytest.approx(18.0 - 0.5 * dt * dt)
    # Too close to pull up smoothly: the climb limit.
    c = PullUpLaw(CFG).command([30, 0.5, -10.0], [5, 0, 0], grid)
    assert c.climb_rate_mps == CFG.max_climb_mps


def test_only_cells_within_the_miss_distance_count():
    radius = CFG.miss_distance_m + math.sqrt(0.5)
    law = PullUpLaw(CFG)
    inside = law.command([0, 0.0, -10.0], [5, 0, 0], mapped([[40.5, radius - 0.6, 15.0]]))
    outside = law.command([0, 0.0, -10.0], [5, 0, 0], mapped([[40.5, radius + 0.6, 15.0]]))
    behind = law.command([0, 0.0, -10.0], [5, 0, 0], mapped([[-radius - 1.0, 0.5, 15.0]]))
    assert inside.engaged and not outside.engaged and not behind.engaged


def test_hover_looks_around_not_ahead():
    law = PullUpLaw(CFG)
    ahead = law.command([0, 0.5, -10.0], [0.05, 0, 0], mapped([[10.5, 0.5, 8.0]]))
    assert not ahead.engaged  # never arrives at hover speed
    beside = law.command([0, 0.5, -10.0], [0.0, 0.0, 0], mapped([[2.5, -1.5, 8.0]]))
    assert beside.engaged and beside.climb_rate_mps == pytest.approx(min(math.sqrt(2 * 8.0), 3.0))


def test_push_over_is_bounded_by_the_terrain_and_the_descent_limit():
    law = PullUpLaw(CFG)
    # 30 m above a 10 m clearance over flat ground, nominal 10 m: descend at the descent limit.
    c = law.command([0, 0.5, -40.0], [5, 0, 0], mapped([]))
    assert c.climb_rate_mps == -CFG.max_descent_mps
    # Nominal says go down to 10, but a mapped 25 m plateau holds the vehicle at 35.
    plateau = mapped([], ground=25.0)
    c = law.command([0, 0.5, -36.0], [5, 0, 0], plateau)
    assert c.engaged and -math.sqrt(2 * 1.0 * 1.0) - 1e-9 <= c.climb_rate_mps < 0
    c = law.command([0, 0.5, -35.0], [5, 0, 0], plateau)
    assert c.climb_rate_mps == pytest.approx(0.0, abs=1e-9)


def test_unmapped_cells_are_not_ground_at_zero():
    law = PullUpLaw(CFG)
    # An empty map: no information, the law cannot invent an obstacle; it says so.
    c = law.command([0, 0.5, -10.0], [5, 0, 0], TerrainGrid())
    assert not c.engaged and c.climb_rate_mps == pytest.approx(0.0, abs=1e-9)
    corridor = TerrainGrid().corridor((0, 0.5), (1, 0), CFG.lookahead_m, CFG.miss_distance_m + math.sqrt(0.5))
    assert c.unknown_cells_ahead == len(corridor) > 0
    # A 25 m plateau with an unmapped hole under and ahead of the vehicle: the hole is plateau.
    full = mapped([], ground=25.0)
    holed, zero = TerrainGrid(gate_min_count=10**6), TerrainGrid(gate_min_count=10**6)
    for key in full.keys():
        t = full.tile(key)
        if key[0] == 0:
            t.height[:8, :], t.variance[:8, :], t.count[:8, :] = np.nan, np.inf, 0
        holed.put_tile(t)
        if key[0] == 0:
            t.height[:8, :], t.variance[:8, :], t.count[:8, :] = 0.0, 1e-4, 1
        zero.put_tile(t)
    assert np.isnan(holed.height_at(4.5, 0.5)[0])
    below_only = PullUpLaw(dataclasses.replace(CFG, descend_ground_radius_m=0.0))
    for alt in (34.0, 35.0, 36.0, 38.0):
        a = law.command([4, 0.5, -alt], [5, 0, 0], holed)
        b = law.command([4, 0.5, -alt], [5, 0, 0], full)
        assert a.unknown_cells_ahead == 0
        if b.climb_rate_mps >= 0:
            assert a.climb_rate_mps == pytest.approx(b.climb_rate_mps)
        else:
            # No push-over while the terrain below is unseen (test_no_push_over_into_an_unseen_roof)...
            held = below_only.command([4, 0.5, -alt], [5, 0, 0], holed)
            assert held.holding_over_unknown and held.climb_rate_mps == 0.0
            # ...except down to the clearance above the plateau flown over, which stands in for it.
            assert not a.holding_over_unknown and b.climb_rate_mps <= a.climb_rate_mps < 0.0
            assert a.climb_rate_mps == pytest.approx(nominal_climb_rate(25.0 + CFG.clearance_m - alt, 1.0, CFG.nominal_time_constant_s))
    # Hovering over the hole: ground at zero there would let the vehicle sink into the plateau's
    # clearance; the law takes the highest mapped height around instead.
    assert law.command([4, 0.5, -36.0], [0, 0, 0], zero).climb_rate_mps == -CFG.max_descent_mps
    # Over the hole itself it sinks no lower than the clearance above the plateau around it; with
    # only the cells right below to go by, not at all: the terrain there has not been seen.
    assert law.command([4, 0.5, -36.0], [0, 0, 0], holed).climb_rate_mps == pytest.approx(
        nominal_climb_rate(25.0 + CFG.clearance_m - 36.0, 1.0, CFG.nominal_time_constant_s))
    assert below_only.command([4, 0.5, -36.0], [0, 0, 0], holed).climb_rate_mps == 0.0
    assert law.command([4, 0.5, -34.0], [0, 0, 0], holed).climb_rate_mps == pytest.approx(math.sqrt(2.0))
    # Beyond the fill distance from anything mapped, a cell is reported, not guessed.
    far = mapped([], ground=25.0, extent=((-30, 20), (-20, 20)))
    c = law.command([0, 0.5, -35.0], [5, 0, 0], far)
    assert c.unknown_cells_ahead > 0


def test_the_law_names_the_mapped_cell_an_unmapped_limiting_cell_stands_in_for():
    """A 6 m cell at 30.5 m in flat ground whose rows 26-29 m are unmapped: the unmapped cells stand
    in at 6 m and, nearer, limit the climb; the command names the 6 m cell as their source. Over
    the mapped cell itself, or a mapped map, there is no source."""
    grid = mapped([[30.5, 1.5, 6.0]])
    holed = TerrainGrid(gate_min_count=10**6)
    for key in grid.keys():
        t = grid.tile(key)
        if key[0] == 0:
            t.height[26:30, :], t.variance[26:30, :], t.count[26:30, :] = np.nan, np.inf, 0
        holed.put_tile(t)
    c = PullUpLaw(CFG).command([10, 0.5, -15.0], [5, 0, 0], holed)
    assert c.engaged and 26.0 <= c.limiting_cell_ne[0] < 30.0
    assert np.isnan(holed.height_at(*c.limiting_cell_ne)[0])
    assert c.limiting_source_ne == (30.5, 1.5)
    full = PullUpLaw(CFG).command([10, 0.5, -15.0], [5, 0, 0], grid)
    assert full.engaged and full.limiting_cell_ne == (30.5, 1.5) and full.limiting_source_ne is None


def test_bad_state_is_refused():
    with pytest.raises(ValueError, match="finite"):
        PullUpLaw(CFG).command([0, np.nan, -10.0], [5, 0, 0], TerrainGrid())


def test_command_time(capsys):
    """Query time of the law (generous bound: catches pathologies, not a benchmark)."""
    rng = np.random.default_rng(0)
    grid = TerrainGrid()
    n, e = np.meshgrid(np.arange(-50, 200) + 0.5, np.arange(-60, 60) + 0.5, indexing="ij")
    pos = np.c_[n.ravel(), e.ravel(), -rng.uniform(0, 5, n.size)]
    grid.insert(TerrainPoints(0.0, pos, np.tile(np.eye(3) * 1e-2, (len(pos), 1, 1))))
    law = PullUpLaw(AvoidanceConfig(lookahead_m=100.0, miss_distance_m=5.0))
    times = {}
    for name, vel in (("along north", [6.0, 0, 0]), ("diagonal", [4.2, 4.2, 0])):
        t = []
        for _ in range(50):
            t0 = time.perf_counter()
            law.command([0, 0.3, -15.0], vel, grid)
            t.append(time.perf_counter() - t0)
        times[name] = np.median(t) * 1e3
    with capsys.disabled():
        print("\nPullUpLaw.command, 100 m look-ahead, miss 5 m: "
              + ", ".join(f"{k} {v:.3f} ms" for k, v in times.items()))
    assert max(times.values()) < 10.0


def test_no_push_over_into_an_unseen_roof():
    """The paper's building: windows (mapped) on the south wall, a plain roof (never mapped). Past the
    wall the law must not descend over the unknown roof; once mapped ground is below again it does."""
    law = PullUpLaw(CFG)
    grid = TerrainGrid(gate_min_count=10**6)
    n = np.arange(-40.0, 80.0, 0.5) + 0.25
    e = np.arange(-15.0, 15.0, 0.5) + 0.25
    N, E = np.meshgrid(n, e, indexing="ij")
    ground = ~((N >= 20) & (N < 40))                      # the building covers north 20..40
    wall = (N >= 20) & (N < 21)                           # its textured south wall, mapped at 9 m
    pts = np.column_stack([N[ground | wall], E[ground | wall], -np.where(wall, 9.0, 0.0)[ground | wall]])
    grid.insert(TerrainPoints(0.0, pts, np.tile(np.diag([0.01, 0.01, 0.01]), (len(pts), 1, 1))))
    over_roof = law.command([32.0, 0.0, -CFG.nominal_alt_m - 9.0], [5, 0, 0], grid)
    assert over_roof.holding_over_unknown and over_roof.climb_rate_mps == 0.0
    # Near the far edge the mapped ground ahead fills the disc around the vehicle, but the vehicle
    # is still over the roof: what counts is the ground it has just flown over (found in the demo).
    for north in (38.0, 39.5):
        near_edge = law.command([north, 0.0, -CFG.nominal_alt_m - 9.0], [5, 0, 0], grid)
        assert near_edge.holding_over_unknown and near_edge.climb_rate_mps == 0.0
    past = law.command([52.0, 0.0, -CFG.nominal_alt_m - 9.0], [5, 0, 0], grid)
    assert not past.holding_over_unknown and past.climb_rate_mps < 0.0


def test_sparse_ground_flown_over_lets_the_vehicle_down_and_an_obstacle_flown_over_holds_it():
    """After a block the ground is mapped one cell in 25, and not at all within 6 m of the vehicle:
    nothing below to descend on. The ground flown over (10+ mapped cells within 20 m behind) stands
    in: with only ground there the vehicle descends at the nominal rate; with the block's 12 m top
    there it descends to 12 m + the clearance and holds."""
    law = PullUpLaw(CFG)
    grid = TerrainGrid(gate_min_count=10**6)
    n, e = np.meshgrid(np.arange(0.0, 100.0) + 0.5, np.arange(-20.0, 20.0) + 0.5, indexing="ij")
    n, e = n.ravel(), e.ravel()
    gaps = ((n >= 34) & (n < 46)) | ((n >= 54) & (n < 66))  # around the two positions tried
    sparse = (np.arange(n.size) % 25 == 0) & ~gaps
    block = (n >= 20) & (n < 30) & (np.abs(e) < 5)
    keep = sparse | block
    pts = np.column_stack([n[keep], e[keep], -np.where(block[keep], 12.0, 0.3)])
    grid.insert(TerrainPoints(0.0, pts, np.tile(np.eye(3) * 1e-4, (len(pts), 1, 1))))
    # 60 m north: sparse ground 40-54 m behind; nothing within 6 m.
    assert ground_below(grid, np.array([60.0, 0.5]), CFG.miss_distance_m + math.sqrt(0.5), np.array([1.0, 0.0]))[0] == 0.0
    assert ground_flown_over(grid, np.array([60.0, 0.5]), np.array([1.0, 0.0]), 20.0) == pytest.approx(0.3, abs=1e-5)
    down = law.command([60.0, 0.5, -25.0], [5, 0, 0], grid)
    assert not down.holding_over_unknown and down.climb_rate_mps == -CFG.max_descent_mps
    assert PullUpLaw(dataclasses.replace(CFG, descend_ground_radius_m=0.0)).command(
        [60.0, 0.5, -25.0], [5, 0, 0], grid).holding_over_unknown
    # 40 m north: the block's top lies within 20 m behind.
    assert ground_below(grid, np.array([40.0, 0.5]), CFG.miss_distance_m + math.sqrt(0.5), np.array([1.0, 0.0]))[0] == 0.0
    assert ground_flown_over(grid, np.array([40.0, 0.5]), np.array([1.0, 0.0]), 20.0) == pytest.approx(12.0, abs=1e-5)
    slow = law.command([40.0, 0.5, -25.0], [5, 0, 0], grid)
    assert slow.climb_rate_mps == pytest.approx(nominal_climb_rate(12.0 + CFG.clearance_m - 25.0, 1.0, CFG.nominal_time_constant_s))
    held = law.command([40.0, 0.5, -22.0], [5, 0, 0], grid)
    assert held.holding_over_unknown and held.climb_rate_mps == pytest.approx(0.0, abs=1e-6)


def test_the_ground_reference_is_the_median_of_the_mapped_cells_near_the_vehicle():
    """The map's ground where the navigation reads 0.8 m high is 0.8 m: the reference; a block
    covering less than half the cells does not move it; it is clipped; too few cells, or off: 0. The
    law takes the cells of its corridor within 10 m of the vehicle."""
    h = np.full(40, 0.8)
    known = np.ones(40, bool)
    d = np.linspace(0.0, 20.0, 40)  # 20 cells within 10 m
    assert ground_reference(h, known, d, 10.0, 3.0) == pytest.approx(0.8)
    block = np.where(np.arange(40) % 3 == 0, 12.0, 0.8)  # a third of them
    assert ground_reference(block, known, d, 10.0, 3.0) == pytest.approx(0.8)
    assert ground_reference(h + 4.2, known, d, 10.0, 3.0) == 3.0
    assert ground_reference(h - 5.8, known, d, 10.0, 3.0) == -3.0
    assert ground_reference(np.where(d > 10.0, 5.0, 0.8), known, d, 10.0, 3.0) == pytest.approx(0.8)  # farther: not counted
    assert ground_reference(h, known & (np.arange(40) < 9), d, 10.0, 3.0) == 0.0  # nine mapped
    assert ground_reference(h, known, d, 0.0, 3.0) == 0.0 and ground_reference(h, known, d, 10.0, 0.0) == 0.0
    law = PullUpLaw(CFG)
    assert law.command([40.0, 0.5, -10.8], [5, 0, 0], mapped([], ground=0.8)).ground_reference_m == pytest.approx(0.8, abs=1e-5)
    cells = [[n + 0.5, e + 0.5, 12.0] for n in range(40, 44) for e in range(-4, 4)]  # 32 cells ahead, in the corridor
    assert law.command([40.0, 0.5, -10.8], [5, 0, 0], mapped(cells, ground=0.8)).ground_reference_m == pytest.approx(0.8, abs=1e-5)
    assert law.command([40.0, 0.5, -10.8], [5, 0, 0], TerrainGrid()).ground_reference_m == 0.0


@settings(max_examples=200, deadline=None)
@given(h=st.floats(-20.0, 40.0), g=st.floats(-3.0, 3.0), b=st.floats(0.01, 2.0))
def test_terrain_near_the_ground_is_lowered_by_at_most_one_band(h, g, b):
    """soften_near_ground against its definition: h - b up to one band above the ground, the ramp
    g + 2 (h - g - b) to two bands, h above; never more than b lower, never higher than h; and
    continuous (a step would make the law jump)."""
    out = float(soften_near_ground(np.array([h]), g, b)[0])
    x = h - g
    expected = h - b if x <= b else (g + 2.0 * (x - b) if x < 2.0 * b else h)
    assert out == pytest.approx(expected, abs=1e-9)
    assert h - b - 1e-9 <= out <= h + 1e-9
    if x >= 2.0 * b:
        assert out == h
    eps = 1e-7
    near = soften_near_ground(np.array([h - eps, h + eps]), g, b)
    assert abs(near[1] - near[0]) <= 2 * 2 * eps + 1e-9
    assert np.isnan(soften_near_ground(np.array([np.nan]), g, b)[0])


def test_the_nominal_altitude_stands_on_the_mapped_ground_and_its_noise_does_not_engage_the_law():
    """A flat map 0.8 m high (the navigation reads 0.8 m high): the nominal altitude is 0.8 m
    higher, held and returned to without the law; a 0.9 m margin (k sigma) on that ground is within
    the band (with a nominal altitude below the clearance the band still keeps the law over it); an
    8 m block ahead still gets the full clearance; a 1.5 m bump gets all but 2 b - 1.5 = 0.5 m."""
    cfg = dataclasses.replace(CFG, height_margin_sigma=2.0, local_radius_m=0.0)
    assert ground_band(cfg) == pytest.approx(1.0)  # min(1 m, 0.1 x 10 m)
    flat = with_variance(mapped([], ground=0.8), 0.2)
    held = PullUpLaw(cfg).command([0, 0.5, -10.8], [5, 0, 0], flat)
    assert held.ground_reference_m == pytest.approx(0.8, abs=1e-5)
    assert held.climb_rate_mps == pytest.approx(0.0, abs=1e-3) and not held.engaged  # the map stores float32
    low = PullUpLaw(cfg).command([0, 0.5, -10.7], [5, 0, 0], flat)  # 0.1 m under: the nominal's return
    assert not low.engaged and low.climb_rate_mps == pytest.approx(nominal_climb_rate(0.1, 1.0, CFG.nominal_time_constant_s), abs=1e-4)
    # 0.8 m under it, too: the ground is the nominal's to follow, at its gentle return, not the law's.
    under = PullUpLaw(cfg).command([0, 0.5, -10.0], [5, 0, 0], flat)
    assert not under.engaged and under.climb_rate_mps == pytest.approx(nominal_climb_rate(0.8, 1.0, CFG.nominal_time_constant_s), abs=1e-4)
    # A nominal altitude below the clearance: the ground's cells (one band lower) keep the law above it.
    low_nominal = PullUpLaw(dataclasses.replace(cfg, nominal_alt_m=8.0)).command([0, 0.5, -9.0], [5, 0, 0], flat)
    assert low_nominal.engaged and low_nominal.limiting_height_m == pytest.approx(0.8 + 2 * math.sqrt(0.2) - 1.0, abs=1e-5)
    block = with_variance(mapped([[40.5, 0.5, 8.8]], ground=0.8), 0.2)
    full = PullUpLaw(cfg).command([13, 0.5, -10.8], [5, 0, 0], block)
    without = PullUpLaw(dataclasses.replace(cfg, ground_band_m=0.0, ground_reference_radius_m=0.0)).command(
        [13, 0.5, -10.8], [5, 0, 0], block)
    assert full.engaged and full.limiting_height_m == pytest.approx(8.8 + 2.0 * math.sqrt(0.2), abs=1e-5)
    assert full.climb_rate_mps == pytest.approx(without.climb_rate_mps, abs=1e-6)
    bump = with_variance(mapped([[40.5, 0.5, 2.3 - 2.0 * math.sqrt(0.2)]], ground=0.8), 0.2)  # + 2 sigma: 1.5 m above
    c = PullUpLaw(cfg).command([33, 0.5, -10.8], [5, 0, 0], bump)
    assert c.engaged and c.limiting_height_m == pytest.approx(0.8 + 2.0 * (1.5 - 1.0), abs=1e-5)


def test_the_default_band_leaves_a_one_point_ground_cell_its_margin_and_an_obstacle_its_clearance():
    """At the defaults (clearance 15 m, k = 2, band 1.5 m) a ground cell holding one point
    (sigma 0.35 m) 0.5 m above well-observed ground, 2.5 m ahead, is taken at h + 2 sigma = 1.2 m,
    within the band: the nominal command holds. With a 1 m band the same cell sits on the ramp and
    engages the law (0.4 m of climb asked). A 3 m rise (2 b) is taken in full, and a 2.2 m one
    loses 2 b - x, at most the band: the clearance over it stays 0.9 h_c or more."""
    cfg = dataclasses.replace(AvoidanceConfig(), local_radius_m=0.0)
    assert cfg.clearance_m == 15.0 and cfg.height_margin_sigma == 2.0 and ground_band(cfg) == pytest.approx(1.5)

    def ground_with(height, variance):
        grid = with_variance(mapped([[40.5, 0.5, height]]), 0.01)
        tile = grid.tile((1, 0))
        tile.variance[40 % 32, 0] = variance
        grid.put_tile(tile)
        return grid

    one_point = ground_with(0.5, 0.35**2)
    held = PullUpLaw(cfg).command([38, 0.5, -15.0], [5, 0, 0], one_point)
    assert not held.engaged and held.climb_rate_mps == pytest.approx(0.0, abs=1e-3)
    narrow = PullUpLaw(dataclasses.replace(cfg, ground_band_m=1.0)).command([38, 0.5, -15.0], [5, 0, 0], one_point)
    assert narrow.engaged and narrow.limiting_height_m == pytest.approx(2.0 * (0.5 + 0.7 - 1.0), abs=1e-4)
    for rise, taken in ((3.0, 3.2), (2.2, 2.0 * (2.4 - 1.5))):
        c = PullUpLaw(cfg).command([38, 0.5, -15.0], [5, 0, 0], ground_with(rise, 0.01))
        assert c.engaged and c.limiting_height_m == pytest.approx(taken, abs=1e-4)
        assert c.limiting_height_m + cfg.clearance_m >= rise + 0.9 * cfg.clearance_m


def with_variance(grid, variance):
    """A copy of ``grid`` whose known cells all have ``variance`` (m^2)."""
    out = TerrainGrid(gate_min_count=10**6)
    for key in grid.keys():
        t = grid.tile(key)
        t.variance[t.count > 0] = variance
        out.put_tile(t)
    return out


def test_the_law_keeps_its_clearance_above_the_map_uncertainty():
    """h + k sigma: a cell mapped at 8 m +- 0.5 m is taken as 9 m with k = 2 (the clearance is meant
    above the true terrain, which the map only estimates)."""
    grid = with_variance(mapped([[40.5, 0.5, 8.0]]), 0.25)
    cfg2 = AvoidanceConfig(**{**{f: getattr(CFG, f) for f in CFG.__dataclass_fields__}, "height_margin_sigma": 2.0,
                              "local_radius_m": 0.0})
    c0 = PullUpLaw(CFG).command([13, 0.5, -10.0], [5, 0, 0], grid)
    c2 = PullUpLaw(cfg2).command([13, 0.5, -10.0], [5, 0, 0], grid)
    assert c0.limiting_height_m == pytest.approx(8.0) and c2.limiting_height_m == pytest.approx(9.0)
    assert c2.climb_rate_mps > c0.climb_rate_mps
    # Over flat ground mapped to +-0.5 m, without the ground band, the vehicle holds nominal + 1 m.
    flat = with_variance(mapped([]), 0.25)
    no_band = dataclasses.replace(cfg2, ground_band_m=0.0)
    assert PullUpLaw(no_band).command([0, 0.5, -11.0], [5, 0, 0], flat).climb_rate_mps == pytest.approx(0.0, abs=1e-9)
    assert PullUpLaw(no_band).command([0, 0.5, -10.5], [5, 0, 0], flat).climb_rate_mps > 0.0
    # With the band (1 m) that margin is the ground's: the nominal altitude holds, the law stays out.
    level = PullUpLaw(cfg2).command([0, 0.5, -10.0], [5, 0, 0], flat)
    assert level.climb_rate_mps == pytest.approx(0.0, abs=1e-9) and not level.engaged


def _surface_reference(n, e, h, v, i, radius, outlier_sigma, max_step=math.inf):
    """local_surface's cell i computed from its definition (docs/avoidance.md, "The surface a cell
    belongs to"), cell by cell: (height, variance, fused)."""
    disc = ((n - n[i]) ** 2 + (e - e[i]) ** 2 <= radius * radius + 1e-9) & np.isfinite(h)
    w = 1.0 / v[disc]
    m_w = np.sum(w * h[disc]) / np.sum(w)
    q = np.sum(w * (h[disc] - m_w) ** 2)
    c = np.sum(w) - np.sum(w * w) / np.sum(w)
    tau2 = max(0.0, (q - (disc.sum() - 1)) / c)
    others = disc.copy()
    others[i] = False
    w_o = 1.0 / (v[others] + tau2)
    m_o = np.sum(w_o * h[others]) / np.sum(w_o)
    prior_v = tau2 + 1.0 / np.sum(w_o)
    if disc.sum() < 3 or (h[i] - m_o) ** 2 > outlier_sigma**2 * (v[i] + prior_v) or abs(h[i] - m_o) > max_step:
        return h[i], v[i], False
    v_post = 1.0 / (1.0 / v[i] + 1.0 / prior_v)
    return v_post * (h[i] / v[i] + m_o / prior_v), v_post, True


def test_a_cell_is_estimated_with_the_neighbours_of_its_surface():
    """local_surface against its definition, cell by cell: the relief tau^2 of the disc from its
    scatter, the neighbours' mean weighted by 1 / (v + tau^2), the cell's estimate updating that
    prior; a cell standing out of its neighbours, or with fewer than 3 in its disc, alone."""
    rng = np.random.default_rng(3)
    n, e = np.meshgrid(np.arange(20) + 0.5, np.arange(9) + 0.5, indexing="ij")
    n, e = n.ravel(), e.ravel()
    v = rng.uniform(0.2, 0.8, len(n))
    h = rng.normal(0.0, np.sqrt(v))  # flat ground, each cell off by its own sigma
    crowns = n > 14  # tree crowns: 2 m of relief from cell to cell around 15 m
    h[crowns] = 15.0 + rng.normal(0.0, 2.0, crowns.sum()) + rng.normal(0.0, np.sqrt(v[crowns]))
    mast = int(np.flatnonzero((n == 6.5) & (e == 4.5))[0])
    h[mast] = 6.0
    h[3] = np.nan  # unmapped
    fused_h, fused_v, fused = local_surface(n, e, h, v, 1.0, 2.0, 2.0)
    for i in np.flatnonzero(np.isfinite(h)):
        ref_h, ref_v, ref_fused = _surface_reference(n, e, h, v, i, 2.0, 2.0)
        assert fused[i] == ref_fused
        assert fused_h[i] == pytest.approx(ref_h, rel=1e-9, abs=1e-9)
        assert fused_v[i] == pytest.approx(ref_v, rel=1e-9)
    assert not fused[mast] and fused_h[mast] == h[mast] and fused_v[mast] == v[mast]
    assert not fused[3] and np.isnan(fused_h[3])
    # Flat ground whose disc holds neither the mast nor a crown: about the information of its disc
    # (13 cells; some discs see a little relief in the noise).
    flat = fused & (n < 12.5) & (np.hypot(n - 6.5, e - 4.5) > 2.5) & (e > 1.5) & (e < 7.5)
    assert flat.sum() > 20
    assert np.median(v[flat] / fused_v[flat]) > 6.0
    # Inside the crowns the relief is the crown's own: a cell keeps most of its height above the
    # disc's mean (a crown fused with its neighbours would lose the top the law must clear).
    inner = crowns & (n > 16) & (e > 1.5) & (e < 7.5)
    top = inner & (h > 17.0)
    assert top.any() and np.all(fused_h[top] >= h[top] - 0.25 * (h[top] - 15.0))
    assert local_surface(n, e, h, v, 1.0, 0.0, 2.0)[2].sum() == 0  # radius 0: each cell alone


def test_the_surface_of_a_diagonal_corridor_is_its_definition():
    """local_surface on the corridor the law reads, 37 degrees off north over a map with holes,
    relief and a post, every cell against the definition: a diagonal corridor's cells are a
    sparse part of their bounding box, and each disc must read exactly the corridor's own cells."""
    rng = np.random.default_rng(5)
    grid = TerrainGrid(gate_min_count=10**6)
    n, e = np.meshgrid(np.arange(-10, 90) + 0.5, np.arange(-10, 80) + 0.5, indexing="ij")
    keep = rng.random(n.size) < 0.6
    n, e = n.ravel()[keep], e.ravel()[keep]
    height = rng.normal(0.0, 0.5, n.size) + np.where(n + e > 90.0, 4.0 + rng.normal(0.0, 1.5, n.size), 0.0)
    height[np.argmin(np.hypot(n - 30.5, e - 22.5))] = 7.0
    sd = rng.uniform(0.3, 0.9, n.size)
    grid.insert(TerrainPoints(0.0, np.c_[n, e, -height], np.array([np.diag([1e-4, 1e-4, s * s]) for s in sd])))
    heading = math.radians(37.0)
    corr = grid.corridor((0.0, 0.0), (math.cos(heading), math.sin(heading)), 100.0, 5.7)
    h = np.where(corr.count > 0, corr.height_m, np.nan)
    fused_h, fused_v, fused = local_surface(corr.north_m, corr.east_m, h, corr.height_variance, 1.0, 2.0, 2.0,
                                            max_step_m=1.5)
    assert np.isfinite(h).sum() > 500 and 0 < fused.sum() < np.isfinite(h).sum()
    for i in np.flatnonzero(np.isfinite(h)):
        ref_h, ref_v, ref_fused = _surface_reference(corr.north_m, corr.east_m, h, corr.height_variance, i, 2.0, 2.0, 1.5)
        assert fused[i] == ref_fused
        assert fused_h[i] == pytest.approx(ref_h, rel=1e-9, abs=1e-9)
        assert fused_v[i] == pytest.approx(ref_v, rel=1e-9)


def test_no_cell_is_fused_across_a_step_larger_than_the_limit():
    """An obstacle's first point is uncertain: 2.5 m +- 1.5 m among flat cells known to +-0.5 m
    agrees with them by the sigmas (2.5 < 2 sqrt(2.25 + ...)) and is fused down without a limit;
    with max_step_m = 1.5 it keeps its own height, and every cell matches the definition."""
    n, e = np.meshgrid(np.arange(9) + 0.5, np.arange(9) + 0.5, indexing="ij")
    n, e = n.ravel(), e.ravel()
    h = np.random.default_rng(7).normal(0.0, 0.5, len(n))
    v = np.full(len(n), 0.25)
    first = int(np.flatnonzero((n == 4.5) & (e == 4.5))[0])
    h[first], v[first] = 2.5, 2.25
    free_h, _, free = local_surface(n, e, h, v, 1.0, 2.0, 2.0)
    assert free[first] and free_h[first] < 1.0
    capped_h, capped_v, capped = local_surface(n, e, h, v, 1.0, 2.0, 2.0, max_step_m=1.5)
    assert not capped[first] and capped_h[first] == 2.5 and capped_v[first] == 2.25
    for i in range(len(n)):
        ref_h, ref_v, ref_fused = _surface_reference(n, e, h, v, i, 2.0, 2.0, 1.5)
        assert capped[i] == ref_fused
        assert capped_h[i] == pytest.approx(ref_h, rel=1e-9, abs=1e-9)
        assert capped_v[i] == pytest.approx(ref_v, rel=1e-9)


def test_the_relief_is_zero_where_the_scatter_is_the_sigmas_and_the_fusion_is_the_disc_mean():
    """With every cell at one height the relief is 0 and a cell's estimate is the information-
    weighted mean of its disc, variance 1 / sum 1 / v (the fixed-effect case)."""
    n, e = np.meshgrid(np.arange(9) + 0.5, np.arange(9) + 0.5, indexing="ij")
    n, e = n.ravel(), e.ravel()
    v = np.random.default_rng(1).uniform(0.2, 0.8, len(n))
    h = np.full(len(n), 2.0)
    fused_h, fused_v, fused = local_surface(n, e, h, v, 1.0, 2.0, 2.0)
    assert fused.all()
    for i in range(len(n)):
        disc = (n - n[i]) ** 2 + (e - e[i]) ** 2 <= 4.0 + 1e-9
        assert fused_h[i] == pytest.approx(2.0)
        assert fused_v[i] == pytest.approx(1.0 / np.sum(1.0 / v[disc]))


def test_flat_ground_known_to_half_a_metre_costs_less_margin_fused_and_a_small_post_keeps_its_own():
    """Over flat ground whose cells each hold +-0.5 m, the law with k = 2 keeps its clearance above
    h + 2 sqrt(V) of the fused cells (V = 0.25 / n for the n cells of a disc of 2 m: 13 inside the
    corridor, fewer at its edges), not h + 1 m; a 2.5 m post in that ground stands out (2.5 m >
    2 sqrt(0.25 + 0.25 / 12)) and still counts at its own 2.5 + 1 m. (Without the ground band,
    which would take both margins as the ground's.)"""
    fields = {**{f: getattr(CFG, f) for f in CFG.__dataclass_fields__}, "ground_band_m": 0.0}
    alone = PullUpLaw(AvoidanceConfig(**{**fields, "height_margin_sigma": 2.0, "local_radius_m": 0.0}))
    fused = PullUpLaw(AvoidanceConfig(**{**fields, "height_margin_sigma": 2.0, "local_radius_m": 2.0}))
    flat = with_variance(mapped([]), 0.25)
    assert alone.command([0, 0.5, -10.6], [5, 0, 0], flat).engaged  # it wants 11 m
    assert not fused.command([0, 0.5, -10.6], [5, 0, 0], flat).engaged  # 2 * 0.5 / sqrt(n) < 0.6 for n >= 3
    assert fused.command([0, 0.5, -10.0], [5, 0, 0], flat).engaged  # but not nothing
    post = with_variance(mapped([[40.5, 0.5, 2.5]]), 0.25)
    corridor = post.corridor(np.array([8.0, 0.5]), np.array([1.0, 0.0]), 85.0, 3.7)
    at_post = (corridor.north_m == 40.5) & (corridor.east_m == 0.5)
    for radius in (0.0, 2.0):
        heights = law_heights(corridor.along_m, corridor, 2.0, 5.0, 1.0, False, radius, 2.0)
        assert heights[at_post] == pytest.approx(3.5) and heights.max() == pytest.approx(3.5)
    fused_flat = law_heights(corridor.along_m, corridor, 2.0, 5.0, 1.0, False, 2.0, 2.0)
    far = np.hypot(corridor.north_m - 40.5, corridor.east_m - 0.5) > 2.5  # discs without the post
    assert fused_flat[far].max() <= 2 * 0.5 / math.sqrt(3) + 1e-6
    assert fused_flat[far].min() == pytest.approx(2 * 0.5 / math.sqrt(13), rel=1e-5)


@settings(max_examples=30, deadline=None)
@given(k=st.floats(0.0, 4.0), sigma=st.floats(0.01, 2.0), alt=st.floats(8.0, 30.0), north=st.floats(-5.0, 35.0))
def test_margin_is_the_same_law_on_a_map_raised_by_k_sigma(k, sigma, alt, north):
    """Property: the law with margin k on a map of variance sigma^2 commands exactly what the law
    without margin commands on the same map raised by k sigma (the ground reference and its band
    off: raising the map raises its ground too)."""
    cells = [[40.5, 0.5, 8.0], [41.5, 0.5, 6.0], [60.5, -1.5, 12.0]]
    fields = {**{f: getattr(CFG, f) for f in CFG.__dataclass_fields__}, "ground_reference_radius_m": 0.0, "ground_band_m": 0.0}
    with_k = PullUpLaw(AvoidanceConfig(**{**fields, "height_margin_sigma": k, "local_radius_m": 0.0}))
    extent = ((-15, 75), (-8, 8))
    grid = with_variance(mapped(cells, extent=extent), sigma * sigma)
    raised = with_variance(mapped([[n, e, h + k * sigma] for n, e, h in cells], ground=k * sigma, extent=extent),
                           sigma * sigma)
    a = with_k.command([north, 0.5, -alt], [5, 0, 0], grid)
    b = PullUpLaw(AvoidanceConfig(**fields)).command([north, 0.5, -alt], [5, 0, 0], raised)
    assert a.climb_rate_mps == pytest.approx(b.climb_rate_mps, abs=1e-5)  # the map stores float32
    assert a.engaged == b.engaged


@settings(max_examples=60, deadline=None)
@given(gain=st.floats(0.1, 40.0), w0=st.floats(-2.0, 3.0), a=st.floats(0.3, 3.0), cap=st.floats(0.5, 5.0))
def test_climb_time_is_the_fastest_level_to_level_climb(gain, w0, a, cap):
    """climb_time(H, w0) against the profile flown in small steps: from w0 (stopping a descent
    first) accelerate at +a up to the cap while the altitude still needed exceeds the braking
    distance w^2 / (2a), else brake at -a. Flown for climb_time seconds it has gained H (ending
    level there, or passing it when already climbing too fast to stop below it); flown for 90 % of
    that time it has not."""
    from companion.method.avoidance import climb_time
    t = float(climb_time(np.array([gain]), w0, a, cap)[0])

    def flown(duration):
        w, h, dt = min(w0, cap), 0.0, 1e-4
        for _ in range(int(round(duration / dt))):
            accelerate = w <= 0 or gain - h > w * w / (2 * a)
            w_new = min(w + a * dt, cap) if accelerate else w - a * dt
            h += 0.5 * (w + w_new) * dt
            w = w_new
        return h

    assert flown(t) == pytest.approx(gain, abs=2e-3 * (1.0 + gain))
    assert flown(0.9 * t) < gain


def test_brake_speed_stops_within_the_distance():
    from companion.method.avoidance import brake_speed
    for d in (0.0, 1.0, 9.3, 40.0):
        v = float(brake_speed(np.array([d]), 2.0, 0.5)[0])
        assert v * 0.5 + v * v / (2 * 2.0) == pytest.approx(d)


def test_a_late_obstacle_slows_the_vehicle_until_the_climb_fits():
    """A 12 m wall mapped 12 m ahead of a level vehicle at the nominal altitude (clearance 10 m):
    the climb takes climb_time(12 - ...) s, too long at 6 m/s, so the limit is the speed from which
    the vehicle still stops before the zone. Climbed to within the shortfall, no limit is left;
    flat ground and the option off give none."""
    from companion.method.avoidance import brake_speed, climb_time
    cfg = AvoidanceConfig(**{**{f: getattr(CFG, f) for f in CFG.__dataclass_fields__}, "speed_limit": True,
                             "speed_limit_shortfall": 0.1, "brake_accel_mps2": 2.0, "reaction_time_s": 0.5})
    grid = mapped([[n + 0.5, e + 0.5, 12.0] for n in range(12, 15) for e in range(-3, 3)])
    cmd = PullUpLaw(cfg).command([0.0, 0.5, -10.0], [6.0, 0.0, 0.0], grid)
    radius = cfg.miss_distance_m + math.sqrt(0.5)
    entry = 12.5 - radius  # the nearest cell centre on the track line
    gain = 12.0 + 0.9 * cfg.clearance_m - 10.0
    by_climb = entry / float(climb_time(np.array([gain]), 0.0, cfg.accel_mps2, cfg.max_climb_mps)[0])
    by_brake = float(brake_speed(np.array([entry]), 2.0, 0.5)[0])
    assert cmd.speed_limit_mps == pytest.approx(max(by_climb, by_brake), rel=1e-6)
    assert cmd.speed_limit_mps < 6.0
    above = PullUpLaw(cfg).command([0.0, 0.5, -(12.0 + 0.9 * cfg.clearance_m + 0.01)], [6.0, 0.0, 0.0], grid)
    assert above.speed_limit_mps == math.inf
    assert PullUpLaw(cfg).command([0.0, 0.5, -10.0], [6.0, 0.0, 0.0], mapped([])).speed_limit_mps == math.inf
    off = AvoidanceConfig(**{**{f: getattr(cfg, f) for f in cfg.__dataclass_fields__}, "speed_limit": False})
    assert PullUpLaw(off).command([0.0, 0.5, -10.0], [6.0, 0.0, 0.0], grid).speed_limit_mps == math.inf


def test_the_highest_line_of_sight_follows_the_mount_and_the_attitude():
    """The camera's highest line of sight ahead: the mount's pitch less the half field of view above
    the optical axis (top row ``top_px`` in), plus the body's nose-down pitch; a camera that sees the
    horizon has a negative depression."""
    from companion.method.geometry import CameraMount, PinholeCamera, view_depression
    cam = PinholeCamera(fx=625.3, fy=625.3, cx=319.5, cy=239.5, width=640, height=480)
    half_up = math.atan2(239.5 - 8.0, 625.3)
    level = np.eye(3)
    down45 = CameraMount.from_euler_deg(0.0, -45.0, 0.0, (0.0, 0.0, 0.0))
    assert view_depression(cam, down45, level, 8.0) == pytest.approx(math.radians(45.0) - half_up, abs=1e-9)
    pitch = math.radians(-10.0)  # nose 10 deg down: body x turns towards NED down
    R_nb = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    assert view_depression(cam, down45, R_nb, 8.0) == pytest.approx(math.radians(55.0) - half_up, abs=1e-9)
    forward = CameraMount.from_euler_deg(0.0, -10.0, 0.0, (0.0, 0.0, 0.0))
    assert view_depression(cam, forward, level, 8.0) < 0.0


def test_the_view_limit_stops_the_vehicle_for_what_the_camera_has_not_seen():
    """docs/avoidance.md, "What the camera can see": the top row looks 30 deg down, so terrain
    (1 - s) h_c below the camera is in view D = (1 - s) h_c / tan 30 deg ahead; from the limit
    speed the vehicle flies the latency and the reaction time, brakes at the configured rate and
    stops exactly at the miss distance before D. Level or upward views, the option off and hovering
    give no limit; the command's limit is the lesser of the view's and the map's. (The flat ground
    mapped here would let the known horizon pass beyond the view: that is the next tests', so it
    counts lines of sight alone here.)"""
    from companion.method.avoidance import view_distance, view_speed_limit
    cfg = AvoidanceConfig(**{**{f: getattr(CFG, f) for f in CFG.__dataclass_fields__}, "speed_limit_shortfall": 0.1,
                             "brake_accel_mps2": 2.0, "reaction_time_s": 0.5, "map_latency_s": 1.5,
                             "view_speed_limit": True, "known_horizon_mapped": False})
    dep = math.radians(30.0)
    d = view_distance(dep, cfg)
    assert d == pytest.approx(0.9 * cfg.clearance_m / math.tan(dep))
    assert view_distance(0.0, cfg) == math.inf and view_distance(-0.1, cfg) == math.inf
    v = view_speed_limit(d, cfg)
    assert v * (0.5 + 1.5) + v * v / (2 * 2.0) == pytest.approx(d - cfg.miss_distance_m)
    assert view_speed_limit(cfg.miss_distance_m - 1.0, cfg) == 0.0 and view_speed_limit(math.inf, cfg) == math.inf
    # A steeper camera sees less far and so allows less speed.
    assert view_speed_limit(view_distance(math.radians(40.0), cfg), cfg) < v

    law = PullUpLaw(cfg)
    flat = mapped([[n + 0.5, e + 0.5, 0.0] for n in range(0, 60) for e in range(-6, 6)])
    cmd = law.command([0.0, 0.5, -cfg.nominal_alt_m], [6.0, 0.0, 0.0], flat, view_depression_rad=dep)
    assert cmd.view_distance_m == pytest.approx(d) and cmd.view_speed_limit_mps == pytest.approx(v)
    assert cmd.speed_limit_mps == pytest.approx(v) and not cmd.engaged
    assert law.command([0.0, 0.5, -cfg.nominal_alt_m], [6.0, 0.0, 0.0], flat).speed_limit_mps == math.inf
    hover = law.command([0.0, 0.5, -cfg.nominal_alt_m], [0.0, 0.0, 0.0], flat, view_depression_rad=dep)
    assert hover.speed_limit_mps == math.inf
    off = AvoidanceConfig(**{**{f: getattr(cfg, f) for f in cfg.__dataclass_fields__}, "view_speed_limit": False})
    cmd_off = PullUpLaw(off).command([0.0, 0.5, -cfg.nominal_alt_m], [6.0, 0.0, 0.0], flat, view_depression_rad=dep)
    assert cmd_off.speed_limit_mps == math.inf and cmd_off.view_distance_m == pytest.approx(d)
    # A wall mapped near ahead limits harder than the view: the lesser limit stands.
    wall = mapped([[n + 0.5, e + 0.5, 12.0] for n in range(6, 9) for e in range(-3, 3)])
    near = law.command([0.0, 0.5, -10.0], [6.0, 0.0, 0.0], wall, view_depression_rad=dep)
    assert near.speed_limit_mps < near.view_speed_limit_mps == pytest.approx(v)


def _carved(origins_n, height_m, reach_m, stop_n=math.inf, end_height_m=0.0):
    """A map with no heights, only free space: from cameras ``height_m`` up at each north of
    ``origins_n`` and every half metre east across 15 m, lines of sight due north down to
    ``end_height_m`` ``reach_m`` ahead, none reaching past ``stop_n`` (as if a wall there hid what
    lies behind it)."""
    from companion.method.messages import FreeSpaceRays
    grid = TerrainGrid()
    for n0 in origins_n:
        n_end = min(n0 + reach_m, stop_n)
        if n_end <= n0:
            continue
        z_end = height_m + (end_height_m - height_m) * (n_end - n0) / reach_m
        for e in np.arange(-7.0, 7.5, 0.5):
            grid.carve(FreeSpaceRays(0.0, np.array([float(n0), e, -height_m]), np.array([[n_end, e, -z_end]])))
    return grid


def test_the_known_horizon_lets_the_vehicle_fly_on_over_ground_lines_of_sight_have_proven_low():
    """docs/avoidance.md, "The known horizon": beyond the view distance D the vehicle need only stop
    before the first corridor cell no line of sight crossed below the heights that would need a
    climb (h - (1 - s) h_c). Over a corridor proven low to its end, the limit is the stop before
    the corridor's end; with a strip no line of sight reached (behind a wall), exactly the stop
    before that strip's nearest cell, brute-forced here from the map's ceilings; lines of sight
    above those heights prove nothing, and the option off or a proven strip within D changes
    nothing."""
    from companion.method.avoidance import entry_distance, known_horizon, view_distance, view_speed_limit
    base = {f: getattr(CFG, f) for f in CFG.__dataclass_fields__}
    cfg = AvoidanceConfig(**{**base, "clearance_m": 15.0, "nominal_alt_m": 25.0, "speed_limit_shortfall": 0.1,
                             "brake_accel_mps2": 2.0, "reaction_time_s": 0.5, "map_latency_s": 1.5,
                             "view_speed_limit": True, "known_horizon": True, "lookahead_m": 100.0})
    off = AvoidanceConfig(**{**base, **{f: getattr(cfg, f) for f in cfg.__dataclass_fields__}, "known_horizon": False})
    dep = math.radians(30.0)
    d = view_distance(dep, cfg)
    danger = cfg.nominal_alt_m - 0.9 * cfg.clearance_m  # 11.5 m
    radius = cfg.miss_distance_m + math.sqrt(0.5)
    here, vel = [0.0, 0.5, -cfg.nominal_alt_m], [6.0, 0.0, 0.0]

    proven = _carved(range(-40, 110, 2), 11.0, 30.0)  # every line of sight below 11 m
    cmd = PullUpLaw(cfg).command(here, vel, proven, view_depression_rad=dep)
    end = cfg.lookahead_m - radius
    assert cmd.view_speed_limit_mps == pytest.approx(view_speed_limit(end + cfg.miss_distance_m, cfg))
    assert cmd.view_speed_limit_mps > 2.0 * view_speed_limit(d, cfg)
    assert PullUpLaw(off).command(here, vel, proven, view_depression_rad=dep).view_speed_limit_mps == pytest.approx(
        view_speed_limit(d, cfg))

    # A wall at north 60 hides what lies behind it until the vehicle is past it.
    walled = _carved([n for n in range(-40, 110, 2) if n < 60 or n > 66], 11.0, 30.0, stop_n=60.0)
    cmd = PullUpLaw(cfg).command(here, vel, walled, view_depression_rad=dep)
    c = walled.corridor(np.array(here[:2]), np.array([1.0, 0.0]), cfg.lookahead_m, radius)
    beyond_open = (c.along_m + math.sqrt(0.5) > d) & ~(c.ceiling_m <= danger)  # cells of 1 m reaching past D
    first = float(entry_distance(c.along_m[beyond_open], c.cross_m[beyond_open], radius).min())
    assert 50.0 < first < 60.0
    v = cmd.view_speed_limit_mps
    tau = cfg.reaction_time_s + cfg.map_latency_s
    assert v * tau + v * v / (2.0 * cfg.brake_accel_mps2) == pytest.approx(first)
    assert cmd.known_horizon_m == pytest.approx(first) and cmd.speed_limit_mps == pytest.approx(v)
    assert known_horizon(c.along_m, c.cross_m, c.ceiling_m, radius, 1.0, d, danger, cfg.lookahead_m) == pytest.approx(first)

    # Lines of sight to a plateau 20 m up cross every cell above the heights that matter.
    high = _carved(range(-40, 110, 2), 40.0, 30.0, end_height_m=20.0)
    assert PullUpLaw(cfg).command(here, vel, high, view_depression_rad=dep).view_speed_limit_mps == pytest.approx(
        view_speed_limit(d, cfg))
    # Unproven cells within D are in view: they do not shorten the horizon.
    near_gap = _carved([n for n in range(-40, 110, 2) if not -30 <= n <= 12], 11.0, 30.0)
    c = near_gap.corridor(np.array(here[:2]), np.array([1.0, 0.0]), cfg.lookahead_m, radius)
    assert not (c.ceiling_m[(c.along_m > 1.0) & (c.along_m < 15.0)] <= danger).all()
    assert PullUpLaw(cfg).command(here, vel, near_gap, view_depression_rad=dep).view_speed_limit_mps == pytest.approx(
        view_speed_limit(end + cfg.miss_distance_m, cfg))


def _mapped_ground(sigma_m=0.1, gap_n=None, high=None):
    """Flat ground mapped at 0 (each cell one point of ``sigma_m``) from north -30 to 150, east -20 to
    20; no cells north of ``gap_n[0]`` up to ``gap_n[1]``; ``high`` (north, height): a row of cells
    across the corridor at that north mapped at that height."""
    n, e = np.meshgrid(np.arange(-30, 150) + 0.5, np.arange(-20, 20) + 0.5, indexing="ij")
    keep = np.ones(n.shape, bool) if gap_n is None else ~((n > gap_n[0]) & (n < gap_n[1]))
    z = np.zeros(n.shape)
    if high is not None:
        z[np.abs(n - high[0]) < 0.6] = high[1]
    pos = np.c_[n[keep], e[keep], -z[keep]]
    grid = TerrainGrid(gate_min_count=10**6)
    grid.insert(TerrainPoints(0.0, pos, np.tile(np.eye(3) * sigma_m**2, (len(pos), 1, 1))))
    return grid


def test_the_known_horizon_passes_over_ground_the_map_holds_low():
    """docs/avoidance.md, "The known horizon": a mapped cell the law takes (its risk quantile
    h + k sigma) at most z_danger = h - (1 - s) h_c high is proven as a line of sight below z_danger
    proves it. Commanded height = clearance = 15 m (z_danger 1.5 m), top row 30 deg down: over flat
    ground mapped to +-0.1 m the horizon is the corridor's end and the vehicle flies on; an unmapped
    strip, or a row mapped 3 m high, ends it exactly at its nearest cell's entry distance (brute
    force from the map); ground mapped to +-3 m a point (its surface, fused with its neighbours, to
    about +-0.8 m: 0 + 2 sigma above z_danger) proves nothing, and
    with the option off the view limit stands alone."""
    from companion.method.avoidance import entry_distance, view_distance, view_speed_limit
    base = {f: getattr(CFG, f) for f in CFG.__dataclass_fields__}
    cfg = AvoidanceConfig(**{**base, "clearance_m": 15.0, "nominal_alt_m": 15.0, "speed_limit_shortfall": 0.1,
                             "brake_accel_mps2": 2.0, "reaction_time_s": 0.5, "map_latency_s": 1.5,
                             "height_margin_sigma": 2.0, "view_speed_limit": True, "known_horizon": True,
                             "known_horizon_mapped": True, "lookahead_m": 100.0, "ground_band_m": 1.0})
    off = AvoidanceConfig(**{**{f: getattr(cfg, f) for f in cfg.__dataclass_fields__}, "known_horizon_mapped": False})
    dep = math.radians(30.0)
    d = view_distance(dep, cfg)
    radius = cfg.miss_distance_m + math.sqrt(0.5)
    here, vel = [0.0, 0.5, -cfg.nominal_alt_m], [6.0, 0.0, 0.0]
    view_only = view_speed_limit(d, cfg)

    known = _mapped_ground()
    cmd = PullUpLaw(cfg).command(here, vel, known, view_depression_rad=dep)
    end = cfg.lookahead_m - radius
    assert not cmd.engaged and cmd.known_horizon_m == pytest.approx(end)
    assert cmd.view_speed_limit_mps == pytest.approx(view_speed_limit(end + cfg.miss_distance_m, cfg))
    assert cmd.view_speed_limit_mps > 2.0 * view_only
    assert PullUpLaw(off).command(here, vel, known, view_depression_rad=dep).view_speed_limit_mps == pytest.approx(view_only)

    def first_entry(grid, unproven):
        c = grid.corridor(np.array(here[:2]), np.array([1.0, 0.0]), cfg.lookahead_m, radius)
        sel = (c.along_m + math.sqrt(0.5) > d) & unproven(c)
        return float(entry_distance(c.along_m[sel], c.cross_m[sel], radius).min())

    gap = _mapped_ground(gap_n=(60.0, 66.0))
    expect = first_entry(gap, lambda c: ~(c.count > 0))
    assert 50.0 < expect < 60.0
    cmd = PullUpLaw(cfg).command(here, vel, gap, view_depression_rad=dep)
    assert cmd.known_horizon_m == pytest.approx(expect)
    v = cmd.view_speed_limit_mps
    assert v * 2.0 + v * v / (2.0 * cfg.brake_accel_mps2) == pytest.approx(expect)

    ridge = _mapped_ground(high=(70.5, 3.0))
    expect = first_entry(ridge, lambda c: c.height_m > 1.0)
    assert 60.0 < expect < 70.0
    assert PullUpLaw(cfg).command(here, vel, ridge, view_depression_rad=dep).known_horizon_m == pytest.approx(expect)

    vague = _mapped_ground(sigma_m=3.0)
    cmd = PullUpLaw(cfg).command(here, vel, vague, view_depression_rad=dep)
    assert cmd.view_speed_limit_mps == pytest.approx(view_only) and cmd.known_horizon_m < d


def test_the_operator_learns_what_the_mount_allows_in_level_flight():
    """What the daemon warns about at start: the view limit of the configured mount with the body
    level. The default 45 deg mount sees the heights that matter 29 m ahead and allows 6.7 m/s; a
    camera looking straight down sees nothing ahead and allows nothing; one looking 10 deg down sees
    the horizon and sets no limit."""
    from companion.config import CompanionConfig, replace
    from companion.method.avoidance import view_distance, view_speed_limit
    from companion.method.control import level_flight_view_limit
    cfg = CompanionConfig()
    d, v = level_flight_view_limit(cfg)
    dep = math.radians(-cfg.camera.mount_pitch_deg) - math.atan2(cfg.camera.cy - cfg.camera.border_px, cfg.camera.fy)
    assert d == pytest.approx(view_distance(dep, cfg.avoidance)) and v == pytest.approx(view_speed_limit(d, cfg.avoidance))
    assert 6.0 < v < 7.0
    d_nadir, v_nadir = level_flight_view_limit(replace(cfg, **{"camera.mount_pitch_deg": -90.0}))
    assert d_nadir < cfg.avoidance.miss_distance_m and v_nadir == 0.0
    assert level_flight_view_limit(replace(cfg, **{"camera.mount_pitch_deg": -10.0})) == (math.inf, math.inf)
