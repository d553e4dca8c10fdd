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
from companion.method.mapper.flow_depth import FlowDepth, FlowRanger, cell_rises, range_sigma, triangulate_midpoint
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


@pytest.fixture(scope="module")
def approach():
    """Frames of a level flight north towards the mast at 25 m, from 45 m to 12 m before its face,
    with the true poses, and the renderer's depth of each frame."""
    from drivers.sim.renderer import Renderer, RenderOptions
    from drivers.sim.world import World

    world = World.load("mast")
    cfg = flight_config(world, "mast", "inverse_depth", 1, RATE_HZ)
    camera, mount = camera_from_config(cfg.camera)
    renderer = Renderer(world, camera, RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, seed=1))
    frames = []
    n = FACE_N - 45.0
    while n <= FACE_N - 12.0:
        p = np.array([n, 0.0, -ALT_M])
        p_c, R_nc = mount.camera_pose(p, np.eye(3))
        image, depth = renderer.render(p_c, R_nc, return_depth=True)
        frames.append((p, p_c, R_nc, image, depth))
        n += SPEED_MPS / RATE_HZ
    return world, cfg, camera, mount, frames


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
    X, sig, rays = flow.ranged(_gray(image), p_c, R_nc)
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
                grid.raise_floors(rises.floors)
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
