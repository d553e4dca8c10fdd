"""Rises seen by dense optical flow (docs/mapper.md, "Rises seen by dense flow"): the geometry
against its derivation, and real OpenCV flow on rendered frames of the mast scenario, whose shaded
face the corner detector does not see until the vehicle is a few metres from it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from benchmarks.common import camera_from_config
from companion.desk.quality.scenarios import flight_config
from companion.method.geometry import matrix_to_quat
from companion.method.mapper import Mapper
from companion.method.mapper.flow_depth import (FlowDepth, FlowRanger, RangedPoints, SurfaceLooks, cell_rises, flat_cells,
                                                 range_sigma, surface_heights, triangulate_midpoint)
from companion.method.messages import NavState
from companion.method.terrain import TerrainGrid

RATE_HZ = 15.0
SPEED_MPS = 4.8
ALT_M = 25.0
MAST_NE = np.array([200.0, 0.0])  # config/scenarios/mast.yaml: 3 x 3 m, 35 m high
FACE_N = 198.5


def test_the_midpoint_is_the_point_both_lines_of_sight_pass_through():
    """Lines of sight from two centres through known points give back each point's range along the
    first line exactly, and the angle between the two lines; parallel lines give no range."""
    rng = np.random.default_rng(3)
    c1, c2 = np.array([0.0, 0.0, -25.0]), np.array([-3.0, 0.4, -24.6])
    X = np.column_stack([rng.uniform(10, 60, 200), rng.uniform(-20, 20, 200), rng.uniform(-15, 0, 200)])
    r1 = (X - c1) / np.linalg.norm(X - c1, axis=1, keepdims=True)
    r2 = (X - c2) / np.linalg.norm(X - c2, axis=1, keepdims=True)
    a, parallax = triangulate_midpoint(c1, r1, c2, r2)
    np.testing.assert_allclose(a, np.linalg.norm(X - c1, axis=1), rtol=1e-9)
    np.testing.assert_allclose(np.cos(parallax), np.einsum("ij,ij->i", r1, r2), atol=1e-12)
    a, _ = triangulate_midpoint(c1, r1[:3], c2, r1[:3])
    assert np.isnan(a).all()


def test_the_range_sigma_is_the_spread_of_ranges_from_noisy_lines_of_sight():
    """Both lines turned by independent errors of sigma (each direction): the ranges' standard
    deviation is sqrt(2) r sigma / parallax to within 10 %, over parallaxes of 1 to 6 degrees."""
    rng = np.random.default_rng(5)
    sigma = 0.7 / 625.0  # 0.7 px at the mast scenario's focal length
    c1 = np.zeros(3)
    for r, baseline in ((40.0, 1.0), (25.0, 3.0), (15.0, 1.5)):
        X = np.array([r, 0.0, 0.0])
        c2 = np.array([-baseline * 0.8, 0.0, baseline * 0.6])
        n = 20000
        d1 = X - c1
        d2 = X - c2
        d1, d2 = d1 / np.linalg.norm(d1), d2 / np.linalg.norm(d2)

        def turned(d):
            e = rng.normal(0.0, sigma, (n, 3))
            e -= np.outer(e @ d, d)  # perpendicular to the line: two components of sigma each
            v = d + e
            return v / np.linalg.norm(v, axis=1, keepdims=True)

        a, parallax = triangulate_midpoint(c1, turned(d1), c2, turned(d2))
        alpha = math.acos(float(d1 @ d2))
        predicted = float(range_sigma(np.array([r]), np.array([alpha]), sigma)[0])
        # the error across the plane of the two lines moves neither range: one of each line's two
        # components counts, and the measured spread is the formula's
        assert abs(np.std(a) / predicted - 1.0) < 0.1, (r, baseline, np.std(a), predicted)


def test_a_cell_rises_above_the_ground_around_it_and_flat_ground_does_not():
    """Flat ground with noise and one cell holding a mast's face (points from 0 to 12 m): only the
    mast's cell rises, by its second highest point; the ground's cells stay within their noise."""
    rng = np.random.default_rng(8)
    g = rng.uniform(-15, 15, (6000, 2))
    h = rng.normal(0.0, 0.3, 6000)
    face = np.column_stack([np.full(40, 0.5), np.full(40, 0.5)])
    fh = np.linspace(0.0, 12.0, 40)
    top, rise, ij = cell_rises(np.r_[g[:, 0], face[:, 0]], np.r_[g[:, 1], face[:, 1]], np.r_[h, fh], 1.0, 5.0)
    mast = (ij[:, 0] == 0) & (ij[:, 1] == 0)
    assert mast.sum() == 1
    assert np.r_[h, fh][top[mast]][0] == pytest.approx(fh[-2])
    assert rise[mast][0] > 10.0
    assert np.all(rise[~mast] < 2.0)


# ------------------------------------------------------------------------------------------
# Rendered frames: a straight approach to the mast at its scenario's height and speed
# ------------------------------------------------------------------------------------------


def _level_flight(alt_m: float, from_m: float, to_m: float):
    """The mast scenario flown level north at ``alt_m`` from ``from_m`` to ``to_m`` before the face:
    its configuration, camera, mount, world, and per frame (position, camera centre, attitude, image,
    the renderer's depth), with the true poses."""
    from drivers.sim.renderer import Renderer, RenderOptions
    from drivers.sim.world import World

    world = World.load("mast")
    cfg = flight_config(world, "mast", "inverse_depth", 1, RATE_HZ)
    camera, mount = camera_from_config(cfg.camera)
    renderer = Renderer(world, camera, RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, seed=1))
    frames = []
    n = FACE_N - from_m
    while n <= FACE_N - to_m:
        p = np.array([n, 0.0, -alt_m])
        p_c, R_nc = mount.camera_pose(p, np.eye(3))
        image, depth = renderer.render(p_c, R_nc, return_depth=True)
        frames.append((p, p_c, R_nc, image, depth))
        n += SPEED_MPS / RATE_HZ
    return cfg, camera, mount, world, frames


@pytest.fixture(scope="module")
def approach():
    """Frames of a level flight north towards the mast at 25 m, from 45 m to 12 m before its face,
    with the true poses, and the renderer's depth of each frame."""
    cfg, camera, mount, world, frames = _level_flight(ALT_M, 45.0, 12.0)
    return world, cfg, camera, mount, frames


@pytest.fixture(scope="module")
def low_approach():
    """The mast scenario flown at 15 m (the suite's cruise height over flat ground), from 30 m to 12 m
    before the face: rendered frames with the true poses."""
    cfg, camera, mount, _, frames = _level_flight(15.0, 30.0, 12.0)
    return cfg, camera, mount, [(p, image) for p, _, _, image, _ in frames]


def _gray(image):
    import cv2

    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _on_mast(X: np.ndarray) -> np.ndarray:
    return (np.abs(X[:, 0] - MAST_NE[0]) < 2.0) & (np.abs(X[:, 1] - MAST_NE[1]) < 2.0) & (-X[:, 2] > 0.5)


def test_the_flow_ranges_the_shaded_face_to_its_sigma(approach):
    """Ten frames apart (3.2 m of baseline), 21 m before the face (where what needs a climb has come
    into view): the lattice points the flow puts on the mast lie at the renderer's own range to
    within their sigma (90 % within 3 sigma, the median error under 1 m), and so do the ground's."""
    world, cfg, camera, _, frames = approach
    mcfg = dataclasses.replace(cfg.mapper, flow_frames_apart=(10,))
    flow = FlowDepth(mcfg, camera)
    k = next(i for i, f in enumerate(frames) if FACE_N - f[0][0] <= 21.0)
    for p, p_c, R_nc, image, _ in frames[k - 10 : k]:
        flow.ranged(_gray(image), p_c, R_nc)
    _, p_c, R_nc, image, _ = frames[k]
    ranged = flow.ranged(_gray(image), p_c, R_nc)
    X, sig, rays = ranged.positions_ned_m, ranged.range_sigma_m, ranged.rays_ned
    truth = world.raycast(p_c, rays)
    err = np.linalg.norm(X - p_c, axis=1) - truth
    on = _on_mast(X)
    assert on.sum() >= 30, "the face gets ranged points"
    for part in (on, ~on):
        assert np.median(np.abs(err[part])) < 1.0
        assert np.quantile(np.abs(err[part]) / sig[part], 0.9) < 3.0


def test_the_mast_gets_floors_twenty_metres_before_its_face_and_the_ground_none(approach):
    """Frame by frame along the approach: by 20 m before the face the mast's cells hold floors of
    8 m or more (what needs a climb from 25 m at 15 m clearance starts at 11.5 m and comes into view
    at about 22 m); no floor anywhere else stands above the flat ground's 0.5 m."""
    _, cfg, camera, _, frames = approach
    flow = FlowDepth(cfg.mapper, camera)
    highest_on_mast, elsewhere = -np.inf, []
    for p, p_c, R_nc, image, _ in frames:
        rises = flow.step(_gray(image), p_c, R_nc)
        F = rises.floors_ned_m
        on = _on_mast(F)
        if FACE_N - p[0] >= 20.0 and on.any():
            highest_on_mast = max(highest_on_mast, float((-F[on, 2]).max()))
        elsewhere.extend((-F[~on, 2]).tolist())
    assert highest_on_mast >= 8.0
    assert not elsewhere or max(elsewhere) <= 0.5


def test_the_flow_stage_hands_the_rises_to_the_map_as_floors_no_feature_owns(approach):
    """The corner mapper and, beside it, the flow stage (:class:`FlowRanger`, as the service and the
    quality suite run them), fed the approach with the true poses: the flow's floors are rows of
    feature id -1, and the terrain grid fed both holds the mast's cell at 8 m or more while the
    vehicle is still 15 m from the face; the corners alone leave the mast's cells without a floor or
    a height."""
    _, cfg, camera, mount, frames = approach

    def fly(on: bool):
        mapper = Mapper(cfg.mapper, camera, mount, border_px=cfg.camera.border_px)
        flow = FlowRanger(cfg.mapper, camera, mount) if on else None
        grid = TerrainGrid.from_config(cfg.terrain)
        owned = unowned = ranged = measured = 0
        for k, (p, _, _, image, _) in enumerate(frames):
            nav = NavState(k / RATE_HZ, p, np.array([SPEED_MPS, 0.0, 0.0]), matrix_to_quat(np.eye(3)), np.diag([0.01] * 3 + [0.01] * 3 + [1e-6] * 3))
            step = mapper.step(nav, image)
            grid.add_evidence(step.points, step.free_space, step.floors)
            if flow is not None:
                rises = flow.step(nav, image)
                owned += int(np.count_nonzero(rises.floors.feature_ids != -1))
                unowned += int(np.count_nonzero(rises.floors.feature_ids == -1))
                ranged += rises.n_ranged
                measured += rises.measured
                grid.add_flow(rises.surface, rises.floors)
            if FACE_N - p[0] <= 15.0:
                break
        corridor = grid.corridor(np.array([FACE_N - 0.5, 0.0]), np.array([1.0, 0.0]), 3.0, 1.6)
        top = np.fmax(np.nan_to_num(corridor.height_m, nan=-np.inf), corridor.floor_m).max()
        assert owned == 0  # every floor the flow gives is a row no feature owns
        return k + 1, measured, unowned, ranged, top

    frames_flown, measured, unowned, ranged, top = fly(True)
    assert measured == math.ceil(frames_flown / cfg.mapper.flow_every_frames)
    assert ranged > 1000 and unowned > 0 and top >= 8.0
    _, _, unowned, ranged, top = fly(False)
    assert not top > 2.0


def test_a_vote_count_no_window_can_hold_is_refused_naming_both_settings(approach):
    _, cfg, camera, mount, _ = approach
    bad = dataclasses.replace(cfg.mapper, flow_rises=True, flow_persist_frames=6, flow_persist_window=5)
    with pytest.raises(ValueError, match="flow_persist_frames.*flow_persist_window"):
        FlowRanger(bad, camera, mount)


def test_frames_between_measured_ones_are_kept_for_later_pairs_and_a_refused_pose_forgets_them(approach):
    """With ``flow_every_frames = 2`` every other frame gives nothing but is stored: the pairs are
    still ``flow_frames_apart`` frames apart. A step refused for a bad pose (NaN) forgets the earlier
    frames, so the next frame has nothing to range against."""
    _, cfg, camera, mount, frames = approach
    loose = dataclasses.replace(cfg.mapper, flow_frames_apart=(3,), flow_max_range_sigma_m=5.0)  # 1 m pairs range far points coarsely
    flow = FlowDepth(dataclasses.replace(loose, flow_every_frames=2), camera)
    counts = [flow.step(_gray(image), p_c, R_nc).n_ranged for _, p_c, R_nc, image, _ in frames[:8]]
    assert counts[1::2] == [0, 0, 0, 0] and counts[0] == 0  # skipped frames; the first has no pair
    assert all(c > 100 for c in counts[4::2])  # frames 5 and 7 range against frames 2 and 4
    ranger = FlowRanger(dataclasses.replace(loose, flow_every_frames=1), camera, mount)
    cov = np.diag([0.01] * 6 + [1e-6] * 3)
    for k, (p, _, _, image, _) in enumerate(frames[:5]):
        step = ranger.step(NavState(k / RATE_HZ, p, np.array([SPEED_MPS, 0.0, 0.0]), matrix_to_quat(np.eye(3)), cov), image)
    assert step.measured and step.n_ranged > 100 and not step.refused
    refused = ranger.step(NavState(5 / RATE_HZ, np.array([np.nan, 0.0, -ALT_M]), np.zeros(3), matrix_to_quat(np.eye(3)), cov), frames[5][3])
    assert refused.refused == "nav not finite" and refused.n_ranged == 0
    p = frames[6][0]
    after = ranger.step(NavState(6 / RATE_HZ, p, np.array([SPEED_MPS, 0.0, 0.0]), matrix_to_quat(np.eye(3)), cov), frames[6][3])
    assert after.measured and after.n_ranged == 0


def test_flat_cells_keep_the_ground_and_leave_a_wall_the_ground_beside_it_and_a_mast():
    """One frame's points: flat ground (0.15 m of noise) over 12 x 12 cells, a wall along north 6-7
    m rising 0-8 m, a mast in cell (2, 9) (two of its fourteen points at 6 and 9 m). The flat cells
    are the ground's, at their heights to the noise; not the wall's cells (their points climb the
    face), nor the ground cells beside the wall (a neighbour's median is metres off), nor the mast's."""
    rng = np.random.default_rng(11)
    n_pts, e_pts, h_pts = [], [], []
    for i in range(12):
        for j in range(12):
            if i == 6:  # the wall's cells: points up its face
                n_pts += list(6.0 + rng.uniform(0.0, 1.0, 14)); e_pts += list(j + rng.uniform(0.0, 1.0, 14))
                h_pts += list(rng.uniform(0.0, 8.0, 14))
                continue
            n_pts += list(i + rng.uniform(0.0, 1.0, 14)); e_pts += list(j + rng.uniform(0.0, 1.0, 14))
            h = rng.normal(0.0, 0.15, 14)
            if (i, j) == (2, 9):
                h[:2] = (6.0, 9.0)
            h_pts += list(h)
    ij, median, member = flat_cells(np.array(n_pts), np.array(e_pts), np.array(h_pts), 1.0, 5, 1.0)
    cells = {tuple(c) for c in ij.tolist()}
    assert not any(i == 6 for i, _ in cells)              # the wall
    assert not any(i in (5, 7) for i, _ in cells)          # the ground beside it
    assert (2, 9) not in cells                              # the mast
    interior = {(i, j) for i in range(1, 11) for j in range(1, 11) if i not in (5, 6, 7) and (i, j) != (2, 9)}
    assert len(interior & cells) >= 0.95 * len(interior)
    assert np.abs(median).max() < 0.3
    assert (member >= 0).sum() == 14 * len(cells) and member.max() == len(cells) - 1


def test_the_surface_variance_is_the_spread_of_cell_medians_under_pair_pose_errors():
    """A camera 15 m over flat ground moving north, a pair 1 m apart; each trial turns every line of
    sight by the flow's pixel error, moves the second camera by sigma_b per axis and turns it by
    sigma_theta (one error for the whole frame). The cells' median heights scatter about the truth
    as :func:`surface_heights` says: their normalised squared errors average 1 within 20 %, and
    sigma_b or sigma_theta alone each explain their part (none of the three terms is idle)."""
    from companion.config import MapperConfig
    rng = np.random.default_rng(21)
    fx = 600.0
    cfg = MapperConfig(flow_pixel_sigma_px=0.7, flow_cell_m=1.0, flow_surface_min_points=5, flow_surface_flat_m=3.0)
    g = np.stack(np.meshgrid(np.arange(10.0, 22.0, 0.25), np.arange(-6.0, 6.0, 0.25), indexing="ij"), axis=-1).reshape(-1, 2)
    X = np.column_stack([g, np.zeros(len(g))])
    c1, c2 = np.array([0.0, 0.0, -15.0]), np.array([-1.0, 0.0, -15.0])

    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def turn(d, sigma, e=None):
        e = rng.normal(0.0, sigma, d.shape) if e is None else np.broadcast_to(e, d.shape)
        return unit(d + e - np.einsum("ij,ij->i", e, d)[:, None] * d)

    for sigma_b, sigma_deg in ((0.03, 0.03), (0.03, 0.0), (0.0, 0.03)):
        c = dataclasses.replace(cfg, flow_pair_position_sigma_m=sigma_b, flow_pair_attitude_sigma_deg=sigma_deg)
        z2 = []
        for _ in range(150):
            r1 = turn(unit(X - c1), 0.7 / fx)
            c2e = c2 + rng.normal(0.0, sigma_b, 3)  # the navigation's second centre: the pair's error
            r2 = turn(unit(X - c2), 0.7 / fx, rng.normal(0.0, math.radians(sigma_deg), 3))
            a, parallax = triangulate_midpoint(c1, r1, c2e, r2)
            pts = c1 + a[:, None] * r1
            ranged = RangedPoints(pts, a, range_sigma(a, parallax, 0.7 / fx), r1, parallax, np.zeros(len(a), np.int64))
            ij, h, v = surface_heights(ranged, 15.0, c)
            z2.extend((h * h / v).tolist())
        print(sigma_b, sigma_deg, np.mean(z2))
        assert abs(np.mean(z2) - 1.0) < 0.2, (sigma_b, sigma_deg, np.mean(z2))


def test_the_flow_stage_gives_the_ground_before_the_mast_its_height_and_the_mast_none(low_approach):
    """Along the rendered approach at 15 m (true poses), the flat cells the flow stage hands to the
    map (each the mean of three frames' looks): the ground's heights within 3 of their sigmas of
    the truth (0 m) in 95 % of them, five hundred or more along the 18 m; none within a metre of the mast's footprint; points at the cells' centres,
    owned by no feature."""
    cfg, camera, mount, frames = low_approach
    ranger = FlowRanger(cfg.mapper, camera, mount)
    z, per_frame, near_mast = [], [], 0
    for k, (p, image) in enumerate(frames):
        nav = NavState(k / RATE_HZ, p, np.array([SPEED_MPS, 0.0, 0.0]), matrix_to_quat(np.eye(3)), np.diag([0.01] * 6 + [1e-6] * 3))
        step = ranger.step(nav, image)
        pts = step.surface.positions_ned_m
        if not step.measured or len(pts) == 0:
            continue
        assert (step.surface.feature_ids == -1).all()
        np.testing.assert_allclose(pts[:, :2] % 1.0, 0.5)
        per_frame.append(len(pts))
        near_mast += int(np.count_nonzero((np.abs(pts[:, 0] - MAST_NE[0]) < 2.5) & (np.abs(pts[:, 1] - MAST_NE[1]) < 2.5)))
        z.extend((pts[:, 2] / np.sqrt(step.surface.covariances[:, 2, 2])).tolist())
    assert sum(per_frame) >= 500
    assert np.quantile(np.abs(z), 0.95) < 3.0
    assert near_mast == 0


def test_the_flow_surface_leaves_the_floors_a_feature_point_replaces():
    """A floor of 9 m in a cell (two bounds confirm it): the flow's flat-surface height (``add_flow``) fuses into the cell
    and leaves the floor (no feature's bound foresaw it); a feature's converged point (``insert``)
    replaces it."""
    from companion.method.messages import TerrainFloors, TerrainPoints
    for keep in (True, False):
        grid = TerrainGrid(cell_size_m=1.0)
        grid.insert(TerrainPoints(0.0, np.array([[12.5, 20.5, 0.0]]), np.diag([0.01, 0.01, 0.04])[None]))  # ground near
        grid.raise_floors(TerrainFloors(0.0, np.array([[10.5, 20.5, -9.0], [10.6, 20.5, -9.2]]), feature_ids=np.array([7, 7])))
        pts = TerrainPoints(0.1, np.array([[10.5, 20.5, -0.2]]), np.diag([0.01, 0.01, 0.04])[None])
        stats = grid.add_flow(pts, TerrainFloors.empty(0.1)) if keep else grid.insert(pts)
        h, _, _ = grid.height_at(10.5, 20.5)
        corridor = grid.corridor(np.array([10.0, 20.5]), np.array([1.0, 0.0]), 1.0, 0.4)
        assert stats.inserted == 1 and abs(float(h) - 0.2) < 1e-6  # float32 layers
        assert (np.nanmax(corridor.floor_m) == 9.0) if keep else not np.isfinite(corridor.floor_m).any()


def test_a_cell_goes_to_the_map_as_the_mean_of_three_looks_each_look_once():
    """Cells (0, 0) and (-3, 5) looked at in frames 1-3 with heights and variances: nothing is given
    before the third look, then the information-weighted mean and 1 / sum(1/v); the next three
    looks are the next mean (the first three are not given again). A cell seen twice, then not for
    six frames, is forgotten with its two looks."""
    looks = SurfaceLooks(3)
    a, b, c = np.array([[0, 0]]), np.array([[-3, 5]]), np.array([[7, -2]])
    out = [looks.add(np.vstack([a, b]), np.array([h, -h]), np.array([v, v])) for h, v in ((1.0, 0.25), (0.0, 1.0), (0.4, 0.5))]
    assert len(out[0][0]) == 0 and len(out[1][0]) == 0
    ij, h, v = out[2]
    w = np.array([4.0, 1.0, 2.0])
    order = np.argsort(ij[:, 0])
    np.testing.assert_array_equal(ij[order], [[-3, 5], [0, 0]])
    np.testing.assert_allclose(h[order], [-(4.0 + 0.8) / 7.0, (4.0 + 0.8) / 7.0])
    np.testing.assert_allclose(v, 1.0 / w.sum())
    for _ in range(2):
        assert len(looks.add(a, np.array([2.0]), np.array([1.0]))[0]) == 0
    ij, h, v = looks.add(a, np.array([5.0]), np.array([1.0]))
    np.testing.assert_array_equal(ij, a)
    np.testing.assert_allclose((h, v), ([3.0], [1.0 / 3.0]))
    looks.add(c, np.array([1.0]), np.array([1.0]))
    looks.add(c, np.array([1.0]), np.array([1.0]))
    for _ in range(6):
        looks.add(a, np.array([0.0]), np.array([1.0]))
    assert len(looks.add(c, np.array([1.0]), np.array([1.0]))[0]) == 0  # its two earlier looks were forgotten


def test_a_flat_surface_far_above_its_cell_raises_nothing_a_feature_point_would():
    """A cell mapped at 0 m by five points: two flow surfaces at 4 m (``add_flow``) leave it at 0 m
    and pending nothing (as likely too high as too low); two feature points at 4 m raise it."""
    from companion.method.messages import TerrainFloors, TerrainPoints
    cov = np.diag([0.01, 0.01, 0.04])[None]
    for flow in (True, False):
        grid = TerrainGrid(cell_size_m=1.0)
        for _ in range(5):
            grid.insert(TerrainPoints(0.0, np.array([[10.5, 20.5, 0.0]]), cov))
        high = TerrainPoints(1.0, np.array([[10.5, 20.5, -4.0], [10.5, 20.5, -4.1]]), np.repeat(cov, 2, axis=0))
        stats = grid.add_flow(high, TerrainFloors.empty(1.0)) if flow else grid.insert(high)
        h = float(grid.height_at(10.5, 20.5)[0])
        assert (abs(h) < 0.05 and stats.inserted == 0 and stats.cells_raised == 0) if flow else (h > 3.9 and stats.cells_raised == 1)

