"""`companion demo` and its report.

Unit tests (no processes): the metrics of companion/desk/report.py on synthetic trajectories and maps.
End to end: the demo as a user runs it (subprocesses, MAVLink over TCP/UDP loopback, Zenoh),
with the demo's criteria asserted on its metrics.json.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.cli import main as cli_main
from companion.desk import report

SQUARE = np.array([[90.0, -10.0], [110.0, -10.0], [110.0, 10.0], [90.0, 10.0]])  # the default building
CIRCUIT = np.array([[0.0, 0.0], [200.0, 0.0], [200.0, 60.0], [0.0, 60.0]])


def box_terrain(height: float = 12.0):
    """Ground at 0 and a box of ``height`` on SQUARE."""
    def fn(n, e):
        n, e = np.broadcast_arrays(np.asarray(n, float), np.asarray(e, float))
        return np.where((n >= 90) & (n <= 110) & (e >= -10) & (e <= 10), height, 0.0)
    return fn


def circuit_path(laps: int, step_m: float = 0.5, noise_m: float = 0.0, seed: int = 0) -> np.ndarray:
    """(N, 2) positions flying the circuit ``laps`` times from waypoint 0, with optional noise."""
    legs = []
    loop = np.vstack([CIRCUIT, CIRCUIT[:1]])
    for _ in range(laps):
        for a, b in zip(loop[:-1], loop[1:]):
            n = int(np.linalg.norm(b - a) / step_m)
            legs.append(a + (b - a) * (np.arange(n) / n)[:, None])
    legs.append(CIRCUIT[:1] + [[0.0, 0.0]])
    ne = np.vstack(legs)
    if noise_m:
        ne = ne + np.random.default_rng(seed).normal(0, noise_m, ne.shape)
    return ne


def tile(tx, ty, height, count, t=4, cell=1.0):
    return SimpleNamespace(tx=tx, ty=ty, height=np.asarray(height, np.float32).reshape(t, t),
                           count=np.asarray(count, np.uint32).reshape(t, t), cell_size_m=cell)


# ---- geometry ----------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(st.floats(-50, 250), st.floats(-50, 50))
def test_points_in_polygon_matches_the_box_bounds(n, e):
    inside = report.points_in_polygon(np.array([[n, e]]), SQUARE)[0]
    strictly_in = 90 < n < 110 and -10 < e < 10
    strictly_out = n < 90 or n > 110 or e < -10 or e > 10
    if strictly_in:
        assert inside
    if strictly_out:
        assert not inside


def test_points_in_polygon_handles_a_rotated_concave_polygon():
    ell = np.array([[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]], float)  # an L, north/east
    pts = np.array([[2, 2], [8, 2], [2, 8], [8, 8], [-1, 5]], float)
    assert report.points_in_polygon(pts, ell).tolist() == [True, True, True, False, False]
    with pytest.raises(ValueError, match="3 vertices"):
        report.points_in_polygon(pts, ell[:2])


# ---- laps --------------------------------------------------------------------------------------


def test_three_laps_are_cut_at_the_first_waypoint():
    ne = circuit_path(3, noise_m=0.5, seed=3)
    laps = report.split_laps(ne, CIRCUIT, radius_m=10.0)
    assert len(laps) == 3
    for start, stop in laps:
        assert np.linalg.norm(ne[stop - 1]) <= 10.0          # each lap ends back at waypoint 0
        assert np.max(ne[start:stop, 0]) > 195                 # ... after the far end of the circuit
    assert laps[0][0] == 0 and all(a[1] - 1 == b[0] for a, b in zip(laps, laps[1:]))


def test_back_and_forth_on_one_leg_is_not_a_lap():
    out_and_back = np.vstack([np.linspace([0, 0], [200, 0], 400), np.linspace([200, 0], [0, 0], 400)] * 3)
    assert report.split_laps(out_and_back, CIRCUIT) == []


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 900), min_size=1, max_size=8))
def test_online_lap_counting_does_not_depend_on_how_samples_arrive(cuts):
    ne = circuit_path(2, step_m=1.0)
    counter = report.LapCounter(CIRCUIT)
    edges = sorted({0, len(ne), *[c % len(ne) for c in np.cumsum(cuts)]})
    for a, b in zip(edges[:-1], edges[1:]):
        counter.update(ne[a:b])
    offline = report.split_laps(ne, CIRCUIT)
    assert counter.boundaries == [stop - 1 for _, stop in offline]
    assert counter.laps == 2


# ---- clearance ---------------------------------------------------------------------------------


def test_min_clearance_is_taken_over_the_footprint_only():
    n = np.linspace(0, 200, 2001)
    ne = np.stack([n, np.zeros_like(n)], axis=1)
    alt = np.full_like(n, 15.0)
    alt[(n > 95) & (n < 105)] = 24.0            # climbs to 24 m over the middle of the roof only
    alt[n < 5] = 1.0                            # low near the start: not over the building
    t = n / 6.0
    c = report.min_clearance_over_footprint(t, ne, alt, SQUARE, box_terrain(12.0))
    assert c.min_clearance_m == pytest.approx(3.0)   # 15 m over a 12 m roof at its edges
    assert 90 <= c.at_ne_m[0] <= 110
    assert c.entered_t_s == pytest.approx(t[np.argmax(n > 90)], abs=0.02)
    never = report.min_clearance_over_footprint(t, ne + [0, 50], alt, SQUARE, box_terrain())
    assert math.isnan(never.min_clearance_m) and never.samples == 0
    with pytest.raises(ValueError, match="same length"):
        report.min_clearance_over_footprint(t[:-1], ne, alt, SQUARE, box_terrain())


# ---- the map -----------------------------------------------------------------------------------


def test_raster_from_tiles_places_tiles_and_samples_cells():
    a = tile(0, 0, np.arange(16), np.ones(16))
    b = tile(1, -1, np.full(16, 7.0), np.r_[np.zeros(8), np.ones(8)])
    r = report.raster_from_tiles({(0, 0): a, (1, -1): b})
    assert r.shape == (8, 8) and (r.north0_m, r.east0_m) == (0.0, -4.0)
    h, c = r.sample(np.array([[0.5, 0.5], [1.5, 2.5], [4.5, -3.5], [6.5, -0.5], [50.0, 0.0]]))
    # tile (0,0) cell [1, 2] = 6; tile (1,-1) row 0 has no evidence, row 2 has 7; outside = unknown
    assert h[0] == 0 and h[1] == 6 and math.isnan(h[2]) and h[3] == 7 and math.isnan(h[4])
    assert c.tolist() == [1, 1, 0, 1, 0]
    assert report.raster_from_tiles({}).shape == (0, 0)
    with pytest.raises(ValueError, match="different sizes"):
        report.raster_from_tiles([a, tile(2, 2, np.zeros(4), np.ones(4), t=2)])


def test_crop_keeps_the_lattice_and_pads_with_unknown():
    r = report.raster_from_tiles([tile(0, 0, np.arange(16), np.ones(16))])
    c = r.crop(2.0, 6.0, -2.0, 1.5)
    assert c.shape == (4, 4) and (c.north0_m, c.east0_m) == (2.0, -2.0)
    assert c.height[0, 2] == 8 and math.isnan(c.height[0, 0]) and math.isnan(c.height[3, 3])
    assert c.observed_cells() == 4


def synthetic_building_map(roof_m: float, rng, wild: int = 0, count: int = 3) -> report.MapRaster:
    """A 1 m map of the default building: ground 0 around, ``roof_m`` over the footprint cells
    (with noise), ``wild`` cells far too high inside."""
    n0, e0, rows, cols = 60.0, -30.0, 80, 60
    n = n0 + np.arange(rows)[:, None] + 0.5
    e = e0 + np.arange(cols)[None, :] + 0.5
    h = np.where((n > 90) & (n < 110) & (e > -10) & (e < 10), roof_m, 0.0) + rng.normal(0, 0.2, (rows, cols))
    idx = np.argwhere((n > 90) & (n < 110) & (e > -10) & (e < 10))
    for i, j in idx[rng.choice(len(idx), wild, replace=False)]:
        h[i, j] = 60.0
    return report.MapRaster(h, np.full((rows, cols), count, np.int64), n0, e0, 1.0)


def test_mapped_height_is_robust_to_a_few_wild_cells_and_ignores_single_points():
    rng = np.random.default_rng(1)
    m = report.mapped_height_over_footprint(synthetic_building_map(9.0, rng, wild=5), SQUARE)
    assert m.height_m == pytest.approx(9.0, abs=0.6) and m.max_m == 60.0
    assert m.cells == m.footprint_cells == 22 * 22  # footprint grown by one cell
    single = report.mapped_height_over_footprint(synthetic_building_map(9.0, rng, count=1), SQUARE)
    assert math.isnan(single.height_m) and single.cells == 0
    # with the ground given, a map holding nothing of the obstacle shows it at the ground
    at_ground = report.mapped_height_over_footprint(synthetic_building_map(9.0, rng, count=1), SQUARE, ground_m=0.5)
    assert at_ground.height_m == at_ground.max_m == 0.5 and at_ground.cells == 0
    with pytest.raises(ValueError, match="quantile"):
        report.mapped_height_over_footprint(synthetic_building_map(9.0, rng), SQUARE, quantile=1.5)


def test_a_wall_mapped_just_outside_the_footprint_still_counts():
    h = np.full((40, 40), np.nan)
    h[9, 10:30] = 9.0          # a row of wall points at north 89..90 (the south wall is at 90)
    r = report.MapRaster(h, np.where(np.isfinite(h), 4, 0), 80.0, -20.0, 1.0)
    assert report.mapped_height_over_footprint(r, SQUARE).height_m == pytest.approx(9.0)
    assert math.isnan(report.mapped_height_over_footprint(r, SQUARE, margin_m=0.0).height_m)


def test_ground_around_is_the_terrain_beside_the_footprint_not_its_top():
    # a 12 m box on ground tilted 1 m per 20 m to the north: the median of the ring is the box's centre line
    def terrain(n, e):
        n, e = np.broadcast_arrays(np.asarray(n, float), np.asarray(e, float))
        inside = (n > 90) & (n < 110) & (e > -10) & (e < 10)
        return np.where(inside, 12.0, (n - 100.0) / 20.0)
    assert report.ground_around(SQUARE, terrain) == pytest.approx(0.0, abs=0.05)
    assert report.ground_around(SQUARE, lambda n, e: np.full(np.shape(n), 3.0)) == 3.0


def test_map_error_is_the_rmse_of_observed_cells_against_the_truth():
    rng = np.random.default_rng(2)
    m = synthetic_building_map(12.0, rng)
    err = report.map_error(m, box_terrain(12.0))
    assert err.rmse_m == pytest.approx(0.2, abs=0.02) and abs(err.bias_m) < 0.02 and err.cells == 80 * 60
    wrong = report.MapRaster(m.height + 5.0, m.count, m.north0_m, m.east0_m, 1.0)
    e5 = report.map_error(wrong, box_terrain(12.0))
    assert e5.rmse_m == pytest.approx(np.sqrt(25 + 0.04), abs=0.05) and e5.over_3m == e5.cells
    hidden = report.MapRaster(m.height, np.zeros_like(m.count), m.north0_m, m.east0_m, 1.0)
    assert math.isnan(report.map_error(hidden, box_terrain()).rmse_m)


def test_first_detection():
    t = np.arange(10.0)
    h = np.array([np.nan, 0, 1, 3, 4.4, 4.6, 9, 2, 9, 9])
    assert report.first_detection_time(t, h, 4.5) == 5.0
    assert math.isnan(report.first_detection_time(t, h, 20.0))


def test_lap_profile_samples_truth_and_map_along_the_path():
    ne = circuit_path(1, step_m=0.5)
    alt = np.full(len(ne), 20.0)
    m = synthetic_building_map(9.0, np.random.default_rng(0))
    p = report.lap_profile(ne, alt, box_terrain(12.0), m, box_terrain(9.0), max_points=500)
    assert len(p.distance_m) <= 500 and p.distance_m[-1] == pytest.approx(520.0, abs=3.0)
    over = (p.distance_m > 92) & (p.distance_m < 108)
    assert np.all(p.true_terrain_m[over] == 12.0) and np.all(p.textured_terrain_m[over] == 9.0)
    assert np.allclose(p.mapped_terrain_m[over], 9.0, atol=1.0)
    assert np.isnan(p.mapped_terrain_m[p.distance_m > 300]).all()  # the map covers the first leg only


def test_height_over_flat_ground_leaves_out_samples_near_structures():
    path = circuit_path(1)
    alt = np.where((path[:, 0] > 70) & (path[:, 0] < 130) & (np.abs(path[:, 1]) < 30), 27.0, 17.0)
    median, n = report.height_over_flat_ground(path, alt, box_terrain())
    assert median == pytest.approx(17.0) and 0.7 * len(path) < n < len(path)
    # Over the box itself the height counts above the roof, but those samples are not flat around.
    near = (path[:, 0] > 75) & (path[:, 0] < 125) & (np.abs(path[:, 1]) < 25)
    _, n_far = report.height_over_flat_ground(path[~near], alt[~near], box_terrain())
    assert n_far == n
    assert np.isnan(report.height_over_flat_ground(np.zeros((0, 2)), np.zeros(0), box_terrain())[0])


def test_criteria_judge_every_lap_and_compare_parameterisations():
    laps = [dict(min_clearance_m=12.5, mapped_obstacle_height_m=11.5, cruise_height_over_flat_m=15.4),
            dict(min_clearance_m=13.6, mapped_obstacle_height_m=11.6, cruise_height_over_flat_m=15.9),
            dict(min_clearance_m=14.0, mapped_obstacle_height_m=11.8, cruise_height_over_flat_m=15.2)]
    cart = [dict(min_clearance_m=9.0, mapped_obstacle_height_m=6.0)]
    v = report.criteria(laps, 15.0, 9.0, cart, roof_height_m=12.0, nominal_alt_m=15.0)
    assert v["laps_judged"] == 3 and v["worst_clearance_m"] == 12.5
    assert v["first_lap_clearance_ratio"] == pytest.approx(12.5 / 15.0)
    assert v["issue_clearance_ok"] and not v["goal_clearance_ok"]          # 12.5 >= 12 but < 13.5
    assert v["flat_excess_m"] == pytest.approx(0.9) and v["goal_flat_height_ok"]
    assert v["issue_height_ok"] and v["goal_height_ok"] and v["maps_better_than_other"]
    assert v["height_fraction_of_roof_last_lap"] == pytest.approx(11.8 / 12.0)
    # the texture's height alone (what corners see) is required, the roof is the goal
    textured_only = report.criteria([dict(lap, mapped_obstacle_height_m=8.8) for lap in laps], 15.0, 9.0, roof_height_m=12.0)
    assert textured_only["issue_height_ok"] and not textured_only["goal_height_ok"]
    # The first pass counts like any other: a low first lap fails the run whatever follows.
    low_first = [dict(laps[0], min_clearance_m=11.9)] + laps[1:]
    assert not report.criteria(low_first, 15.0, 9.0)["issue_clearance_ok"]
    # A lap that never crossed the obstacle (no clearance figure) fails too, and so does flying high.
    assert not report.criteria(laps[:2] + [dict(laps[2], min_clearance_m=None)], 15.0, 9.0)["issue_clearance_ok"]
    high = report.criteria(laps[:2] + [dict(laps[2], cruise_height_over_flat_m=16.2)], 15.0, 9.0, nominal_alt_m=15.0)
    assert high["flat_excess_m"] == pytest.approx(1.2) and not high["goal_flat_height_ok"]
    assert math.isnan(report.criteria(laps, 15.0, 9.0)["flat_excess_m"])   # no nominal altitude given
    tall = report.criteria(laps[:2] + [dict(laps[2], mapped_obstacle_height_m=31.0)], 15.0, 9.0, cart)
    assert not tall["issue_height_ok"] and not tall["goal_height_ok"] and not tall["maps_better_than_other"]
    # The comparison averages the laps' errors against the roof: a baseline that catches up by the
    # last lap still maps worse.
    assert v["mean_height_error_m"] == pytest.approx((0.5 + 0.4 + 0.2) / 3)
    late = [dict(lap, mapped_obstacle_height_m=h) for lap, h in zip(laps, (None, 7.0, 8.9))]
    assert report.mean_height_error(late, 9.0) == pytest.approx((9.0 + 2.0 + 0.1) / 3)
    assert report.criteria(laps, 15.0, 9.0, late)["maps_better_than_other"]
    assert not report.criteria(late, 15.0, 9.0, laps)["maps_better_than_other"]


# ---- the command line --------------------------------------------------------------------------


@pytest.mark.parametrize("argv, message", [
    (["demo", "--laps", "0"], "--laps"),
    (["demo", "--speedup", "0"], "--speedup"),
    (["demo", "--speedup", "nan"], "--speedup"),
    (["demo", "--scenario", "no_such_scenario"], "no_such_scenario"),
])
def test_bad_options_exit_2_naming_the_problem(argv, message, capsys, tmp_path):
    assert cli_main(argv + ["--output", str(tmp_path / "out")]) == 2
    assert message in capsys.readouterr().err


def test_progress_is_plain_lines_when_stderr_is_not_a_terminal(tmp_path):
    from companion.desk.demo.progress import Progress, progress_line

    with open(tmp_path / "err.txt", "w") as f:
        p = Progress(f, every_s=0.0)
        p.update(progress_line("inverse_depth", 1, 3, 120.0, 27.5, 40, 1500, 3, True, 30.0, 0.5))
        p.done(progress_line("inverse_depth", 3, 3, 280.0, 15.0, 60, 4000, 9, False, 70.0))
    lines = (tmp_path / "err.txt").read_text().splitlines()
    assert len(lines) == 2 and "\r" not in "".join(lines)
    assert "lap 2/3" in lines[0] and "ENGAGED" in lines[0] and "alt  27.5 m" in lines[0]
    assert "lap 3/3" in lines[1] and "#" * 20 in lines[1]


# ---- end to end --------------------------------------------------------------------------------
#
# Two demos, as a user runs them:
# * the closed loop (the demo's criteria): inverse depth, 2 laps (the first pass over unmapped
#   ground, and a pass over the map it made; the demo's default is the paper's 3), the law obeyed;
# * the same path for both parameterisations (the paper's comparison): `--no-avoid`, 2 laps, so
#   that the two maps differ by the parameterisation alone. In the closed loop each run flies where
#   its own map sends it, and the climb itself shrinks what inverse depth is for (docs/demo.md,
#   "Inverse depth against Cartesian").

# The demo flies in lockstep (docs/sim.md): x3 is the most its flights run at, and a host that
# cannot map every frame at x3 (beside the rest of the suite, a 2-core host maps 40-50 frames/s)
# runs them slower instead of dropping frames. Paced by the wall clock alone, x3 on such a host
# dropped 26 % of the frames and mapped the building late. The timeout bounds a flight at real time.
CLOSED_LOOP_LAPS, SAME_PATH_LAPS, E2E_SPEEDUP, E2E_TIMEOUT_S = 2, 2, 3, 900
TRACKING_TOLERANCE_M = 0.25  # the vehicle's altitude tracking, as tests/test_avoidance_closed_loop.py allows


def _run_demo(out, *options) -> SimpleNamespace:
    argv = [sys.executable, "-m", "companion.cli", "demo", "--speedup", str(E2E_SPEEDUP), "--output", str(out), *options]
    t0 = time.monotonic()
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=E2E_TIMEOUT_S)
    wall = time.monotonic() - t0
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").exists() else None
    print(f"\n{' '.join(argv[3:])}: exit {proc.returncode}, {wall:.0f} s wall")
    print(proc.stderr[-3000:])
    return SimpleNamespace(out=out, proc=proc, metrics=metrics, wall=wall)


@pytest.fixture(scope="module")
def closed_loop_run(tmp_path_factory):
    return _run_demo(tmp_path_factory.mktemp("closed_loop"), "--laps", str(CLOSED_LOOP_LAPS),
                     "--parameterisation", "inverse_depth")


@pytest.fixture(scope="module")
def same_path_run(tmp_path_factory):
    return _run_demo(tmp_path_factory.mktemp("same_path"), "--laps", str(SAME_PATH_LAPS), "--no-avoid")


def _figures(m):
    for p, run in m["runs"].items():
        for lap in run["laps"]:
            print(f"  {p:13s} lap {lap['lap']}: mapped height {lap['mapped_obstacle_height_m']} m "
                  f"(textured {m['obstacle_textured_height_m']} m), min clearance {lap['min_clearance_m']} m "
                  f"(configured {m['clearance_m']} m), warning {lap['warning_s']} s (smooth climb: {m['warning_needed_s']} s), "
                  f"height over flat ground {lap['cruise_height_over_flat_m']} m")
        print(f"  {p:13s} map RMSE {run['map_rmse_m']} m over {run['map_error']['cells']} cells; "
              f"frames {run['frames_mapped']}/{run['frames']} mapped ({run['frames_dropped']} dropped)")


def _check_report(demo, parameterisations, laps):
    """The plumbing of one demo: every run completes, the service stops cleanly with its map
    saved, the report holds the documented keys and readable PNGs."""
    assert demo.proc.returncode == 0, demo.proc.stderr[-2000:]
    m = demo.metrics
    _figures(m)
    assert isinstance(m["clearance_m"], float) and isinstance(m["obstacle_textured_height_m"], float)
    assert sorted(m["runs"]) == sorted(parameterisations)
    for p in parameterisations:
        run = m["runs"][p]
        assert run["complete"] and len(run["laps"]) == laps
        for lap in run["laps"]:
            assert isinstance(lap["min_clearance_m"], float) and isinstance(lap["mapped_obstacle_height_m"], float)
        assert isinstance(run["map_rmse_m"], float)
        assert run["service"]["exit"]["returncode"] == 0 and run["service"]["exit"]["stop_wall_s"] < 5
        assert run["service"]["exit"]["snapshot_saved"]
        assert run["simulator_exit"]["slips"] == 0
        # Lockstep: simulated time waited for the workers, so neither the mapper's queue nor the dense
        # flow's dropped a frame, whatever the host's speed; the frames not mapped are those without
        # navigation (before the EKF origin).
        assert m["lockstep"] and run["lockstep"] is not None
        assert run["frames_dropped"] == 0 and run["service"]["flow"]["queue_dropped"] == 0
        assert run["frames_mapped"] >= 0.95 * run["frames"]
        assert run["ground_station"]["counts"]["bad_tiles"] == 0
        names = [f"map_{p}.png"] + [f"profile_{p}_lap{k}.png" for k in range(1, laps + 1)]
        for name in names + ["comparison.png"]:
            img = cv2.imread(str(demo.out / name))
            assert img is not None and img.shape[0] > 300 and img.shape[1] > 300, name
        assert (demo.out / "runs" / p / "trajectory.csv").exists()


@pytest.mark.slow
def test_demo_flies_both_parameterisations_and_writes_the_report(same_path_run):
    _check_report(same_path_run, ("inverse_depth", "cartesian"), SAME_PATH_LAPS)
    # --no-avoid: the law is evaluated and published, never obeyed; the vehicle holds its altitude
    for run in same_path_run.metrics["runs"].values():
        assert max(lap["max_alt_m"] for lap in run["laps"]) < 20.0


@pytest.mark.slow
def test_demo_closed_loop_run_writes_its_report(closed_loop_run):
    _check_report(closed_loop_run, ("inverse_depth",), CLOSED_LOOP_LAPS)


@pytest.mark.slow
def test_demo_meets_its_criteria(closed_loop_run):
    """Every lap, the first included, keeps at least 0.9 of the configured clearance over the
    building (the goal), less the vehicle's altitude tracking tolerance (0.25 m, as the closed-loop
    tests of the law); the mapped building height (last lap) meets the required criterion: at
    least 80 % of its textured height and at most 120 % of its roof. The building's top, 3 m above
    its texture, has no corner: its outline's edgels map it (docs/mapper.md, "Edgels"), which is
    what lets the law keep 0.9 of the clearance over the roof rather than over the texture. The
    flat-ground goal (within 1 m of the nominal altitude) is printed, and the scenario suite
    (docs/quality.md) measures every goal on every scenario."""
    m = closed_loop_run.metrics
    assert m is not None, closed_loop_run.proc.stderr[-2000:]
    _figures(m)
    h_c, textured = m["clearance_m"], m["obstacle_textured_height_m"]
    inv = m["runs"]["inverse_depth"]
    verdict = m["criteria"]["inverse_depth"]
    print(f"  goals: clearance ratio {verdict['clearance_ratio']} (0.9: {verdict['goal_clearance_ok']}), "
          f"flat excess {verdict['flat_excess_m']} m (1.0: {verdict['goal_flat_height_ok']})")
    print(f"  required: clearance ratio >= 0.8 on every lap: {verdict['issue_clearance_ok']}")
    assert verdict["laps_judged"] == CLOSED_LOOP_LAPS
    for lap in inv["laps"]:
        assert lap["min_clearance_m"] >= 0.9 * h_c - TRACKING_TOLERANCE_M, f"lap {lap['lap']}: clearance {lap['min_clearance_m']} m"
    height, roof = inv["laps"][-1]["mapped_obstacle_height_m"], m["obstacle"]["height_m"]
    assert 0.8 * textured <= height <= 1.2 * roof, f"mapped {height} m vs textured {textured} m, roof {roof} m"
    assert verdict["issue_height_ok"]


@pytest.mark.slow
def test_cartesian_maps_the_building_worse_on_the_same_path(same_path_run):
    """The paper's claim: the Cartesian run maps the building worse. Worse = a larger height error
    averaged over the laps (report.mean_height_error; the paper compares them lap by lap), both runs
    flying the same path at the nominal altitude; the error is against the roof (12 m), which the
    building's outline lets both map above its texture (9 m)."""
    m = same_path_run.metrics
    assert m is not None, same_path_run.proc.stderr[-2000:]
    roof = m["obstacle"]["height_m"]
    inv, cart = m["runs"]["inverse_depth"], m["runs"]["cartesian"]
    err_inv, err_cart = report.mean_height_error(inv["laps"], roof), report.mean_height_error(cart["laps"], roof)
    print(f"  mean height error over the laps, same path: inverse depth {err_inv:.2f} m, Cartesian {err_cart:.2f} m")
    assert err_cart > err_inv
