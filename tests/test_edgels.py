"""Edgels: points on image edges, measured across the edge only (docs/mapper.md, "Edgels").

The scalar update against its derivation (the 2-D update with an infinite noise along the edge),
the 1-dof gate, the detector on drawn images, the mapper on a straight 3-D edge whose edgels are
never the same point twice, and the rendered building whose plain top only edgels can map.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from companion.config import MapperConfig
from companion.method.geometry import CameraMount, PinholeCamera, euler_to_quat
from companion.method.mapper import Mapper
from companion.method.mapper.features import detect_corners, detect_edgels
from companion.method.mapper.mapper import chi2_one_dof
from companion.method.mapper.update import ekf_update, ekf_update_across
from companion.method.messages import NavState

CAMERA = PinholeCamera(fx=625.3, fy=625.3, cx=319.5, cy=239.5, width=640, height=480)
MOUNT = CameraMount.from_euler_deg(0.0, -30.0, 0.0)


def nav_state(p, t, v=(6.0, 0.0, 0.0), sigma_p=0.02, sigma_att=np.radians(0.05)):
    cov = np.diag([sigma_p**2] * 3 + [0.01] * 3 + [sigma_att**2] * 3)
    return NavState(t, np.asarray(p, float), np.asarray(v, float), euler_to_quat(0.0, 0.0, 0.0), cov)


# ----------------------------------------------------------------------------------------------
# The scalar update and the gate
# ----------------------------------------------------------------------------------------------


def test_update_across_an_edge_is_the_2d_update_with_infinite_noise_along_it():
    rng = np.random.default_rng(3)
    n_feat, dim = 5, 6
    A = rng.normal(size=(n_feat, dim, dim))
    P = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(dim)
    y = rng.normal(size=(n_feat, dim))
    C_y = rng.normal(size=(n_feat, 2, dim))
    C_x = np.zeros((n_feat, 2, 6))
    angle = rng.uniform(0, 2 * np.pi, n_feat)
    n = np.column_stack([np.cos(angle), np.sin(angle)])
    t = np.column_stack([-n[:, 1], n[:, 0]])
    e = rng.normal(size=(n_feat, 2))
    sigma2, along2 = 0.7, 1e10
    y1, P1, ok1 = ekf_update_across(y, P, (e * n).sum(axis=1), np.einsum("ni,nij->nj", n, C_y), np.full(n_feat, sigma2))
    assert ok1.all()
    for k in range(n_feat):  # the 2-D update, R = sigma^2 n n^T + L t t^T with L -> infinity
        R = sigma2 * np.outer(n[k], n[k]) + along2 * np.outer(t[k], t[k])
        y2, P2, ok2 = ekf_update(y[k:k + 1], P[k:k + 1], e[k:k + 1], C_x[k:k + 1], C_y[k:k + 1], np.zeros((6, 6)), R)
        assert ok2.all()
        np.testing.assert_allclose(y1[k], y2[0], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(P1[k], P2[0], rtol=1e-6, atol=1e-6)
    # the variance across the edge falls
    h = np.einsum("ni,nij->nj", n, C_y)
    assert (np.einsum("ni,nij,nj->n", h, P1, h) < np.einsum("ni,nij,nj->n", h, P, h)).all()


def test_update_across_refuses_a_non_positive_innovation_variance():
    y, P = np.zeros((1, 3)), np.zeros((1, 3, 3))
    y1, P1, ok = ekf_update_across(y, P, np.array([1.0]), np.ones((1, 3)), np.array([0.0]))
    assert not ok[0]
    np.testing.assert_array_equal(y1, y)


def test_one_dof_gate_has_the_probability_of_the_two_dof_gate():
    assert chi2_one_dof(9.21) == pytest.approx(2.5758**2, rel=1e-3)  # both 99 %
    for g2 in (2.0, 9.21, 23.0):
        p2 = 1.0 - math.exp(-g2 / 2.0)
        p1 = math.erf(math.sqrt(chi2_one_dof(g2) / 2.0))  # P(|N(0,1)| < sqrt(g1))
        assert p1 == pytest.approx(p2, abs=1e-9)


# ----------------------------------------------------------------------------------------------
# The detector
# ----------------------------------------------------------------------------------------------


def cfg(**kw) -> MapperConfig:
    return dataclasses.replace(MapperConfig(), **{"max_edgels": 40, **kw})


def test_edgels_lie_on_a_plain_faces_outline_with_normals_across_it():
    img = np.full((480, 640), 60, np.uint8)
    cv2.rectangle(img, (100, 120), (540, 360), 160, thickness=-1)  # a plain bright face
    corners, _ = detect_corners(img, cfg(), 8)
    uv, normal, strength = detect_edgels(img, corners, cfg(), 8)
    assert 10 <= len(uv) <= 40
    assert np.all(strength > 0)
    assert np.allclose(np.linalg.norm(normal, axis=1), 1.0)
    for (u, v), (nu, nv) in zip(uv, normal):
        on_vertical = min(abs(u - 99.5), abs(u - 540.5)) <= 1.5 and 118 <= v <= 362
        on_horizontal = min(abs(v - 119.5), abs(v - 360.5)) <= 1.5 and 98 <= u <= 542
        assert on_vertical or on_horizontal, (u, v)
        if on_horizontal and not on_vertical:  # normal across the edge, from dark to bright
            assert abs(nv) > 0.95 and np.sign(nv) == (1 if v < 240 else -1)
        if on_vertical and not on_horizontal:
            assert abs(nu) > 0.95 and np.sign(nu) == (1 if u < 320 else -1)
    # the corners' spacing holds against corners and other edgels
    d = np.linalg.norm(uv[:, None] - np.concatenate([corners, uv])[None], axis=2)
    d[np.arange(len(uv)), len(corners) + np.arange(len(uv))] = np.inf
    assert d.min() >= cfg().min_distance_px


@pytest.mark.parametrize("x0", [300.0, 300.3, 300.5, 300.8])
def test_edgels_sit_on_the_edge_to_a_tenth_of_a_pixel_across_it(x0):
    x = np.arange(640)[None, :].repeat(480, axis=0).astype(float)
    img = np.clip(60 + 100 / (1 + np.exp(-(x - x0) / 0.6)), 0, 255).astype(np.uint8)  # a blurred step at x0
    uv, normal, _ = detect_edgels(img, np.zeros((0, 2)), cfg(), 8)
    assert len(uv) > 10
    np.testing.assert_allclose(uv[:, 0], x0, atol=0.1)
    np.testing.assert_allclose(normal, [[1.0, 0.0]] * len(uv), atol=1e-6)


def test_bins_with_a_corner_take_no_edgels():
    rng = np.random.default_rng(1)
    img = np.full((480, 640), 90, np.uint8)
    for _ in range(600):  # dense squares: corners everywhere on the left half
        x, y = int(rng.integers(10, 300)), int(rng.integers(10, 470))
        cv2.rectangle(img, (x, y), (x + 6, y + 6), int(rng.choice([20, 200])), thickness=-1)
    cv2.line(img, (330, 0), (330, 479), 200, thickness=3)  # one long edge on the plain right half
    cv2.line(img, (250, 240), (250, 479), 255, thickness=3)  # and one among the corners
    c = cfg(max_detections=1000)
    corners, _ = detect_corners(img, c, 8)
    uv, _, _ = detect_edgels(img, corners, c, 8)
    def bins(xy):
        return (np.clip(xy[:, 1] * c.bins_y / 480, 0, c.bins_y - 1).astype(int) * c.bins_x
                + np.clip(xy[:, 0] * c.bins_x / 640, 0, c.bins_x - 1).astype(int))
    assert len(uv) > 0
    assert not np.isin(bins(uv), bins(corners)).any()
    assert np.all(np.abs(uv[:, 0] - 330) < 4)  # on the line in the plain half only


def test_a_masks_outline_and_a_black_border_make_no_edgels():
    from companion.method.mapper.features import HarrisDetector

    img = np.full((480, 640), 120, np.uint8)
    img[:, :200] = 15  # an airframe part, masked
    img[:20, :] = 0  # a black border (undistortion)
    cv2.rectangle(img, (300, 200), (500, 330), 220, thickness=-1)  # a real plain face
    mask = np.ones_like(img)
    mask[:, :200] = 0
    detector = HarrisDetector(cfg(), 640, 480, 8, mask=mask)
    corners, _ = detector(img)
    uv, _, _ = detect_edgels(img, corners, cfg(), 8, detector.valid_region(img))
    assert len(uv) > 0
    assert np.all((uv[:, 0] > 290) & (uv[:, 0] < 510) & (uv[:, 1] > 190) & (uv[:, 1] < 340)), uv
    # without the mask the airframe's outline is an edge
    uv_all, _, _ = detect_edgels(img, corners, cfg(), 8)
    assert np.any(np.abs(uv_all[:, 0] - 199.5) < 2)


def test_no_edgels_when_off_or_on_a_blank_frame():
    img = np.full((480, 640), 128, np.uint8)
    assert len(detect_edgels(img, np.zeros((0, 2)), cfg(), 8)[0]) == 0
    cv2.rectangle(img, (100, 100), (300, 300), 250, thickness=-1)
    assert len(detect_edgels(img, np.zeros((0, 2)), cfg(max_edgels=0), 8)[0]) == 0


def whole_frame_edgels(gray, corners, c, border_px, valid):
    """The detector written the plain way, for its test: the whole frame blurred, Canny on each run
    of bins without a corner, the Sobel gradient at every edge pixel, a full stable sort."""
    from companion.method.mapper import features as F

    H, W = gray.shape
    m = F.effective_margin(c, border_px)
    no_corner = np.bincount(F.bin_of(corners, W, H, c.bins_x, c.bins_y), minlength=c.bins_x * c.bins_y) == 0
    smooth = cv2.GaussianBlur(gray, (0, 0), F.EDGEL_BLUR_SIGMA_PX)
    high = 4.0 * c.edgel_min_step_grey
    edges = np.zeros((H, W), np.uint8)
    xe = -(-np.arange(c.bins_x + 1) * W // c.bins_x)
    ye = -(-np.arange(c.bins_y + 1) * H // c.bins_y)
    for by in range(c.bins_y):
        for bx in range(c.bins_x):
            if not no_corner[by * c.bins_x + bx]:
                continue
            b1 = bx + 1  # the run of bins without a corner that starts here (Canny's hysteresis spans it)
            if bx > 0 and no_corner[by * c.bins_x + bx - 1]:
                continue
            while b1 < c.bins_x and no_corner[by * c.bins_x + b1]:
                b1 += 1
            y0, y1, x0, x1 = ye[by], ye[by + 1], xe[bx], xe[b1]
            Y0, Y1, X0, X1 = max(y0 - 3, 0), min(y1 + 3, H), max(x0 - 3, 0), min(x1 + 3, W)
            crop = cv2.Canny(np.ascontiguousarray(smooth[Y0:Y1, X0:X1]), 0.5 * high, high, L2gradient=True)
            edges[y0:y1, x0:x1] = crop[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0]
    edges[:m], edges[H - m:], edges[:, :m], edges[:, W - m:] = 0, 0, 0, 0
    if valid is not None:
        edges[valid == 0] = 0
    iy, ix = np.nonzero(edges)
    sm = smooth.astype(np.float64)
    gx = (sm[iy - 1, ix + 1] - sm[iy - 1, ix - 1]) + 2 * (sm[iy, ix + 1] - sm[iy, ix - 1]) + (sm[iy + 1, ix + 1] - sm[iy + 1, ix - 1])
    gy = (sm[iy + 1, ix - 1] - sm[iy - 1, ix - 1]) + 2 * (sm[iy + 1, ix] - sm[iy - 1, ix]) + (sm[iy + 1, ix + 1] - sm[iy - 1, ix + 1])
    g = np.column_stack([gx, gy]) / 8.0
    strength = np.sqrt((g * g).sum(axis=1))
    top = np.argsort(-strength, kind="stable")[: 16 * c.max_edgels]
    cell = max(1, int(c.min_distance_px // 2))
    _, first = np.unique((iy[top] // cell) * (W // cell + 1) + ix[top] // cell, return_index=True)
    pick = top[np.sort(first)]
    xy = np.column_stack([ix[pick], iy[pick]]).astype(float)
    keep = np.flatnonzero(F.suppress_within(np.concatenate([corners, xy]), c.min_distance_px)[len(corners):])
    keep = keep[F._bin_rank(xy[keep], W, H, c.bins_x, c.bins_y) < c.per_bin][: c.max_edgels]
    normal = g[pick[keep]] / strength[pick[keep], None]
    return F._refine_across(smooth, xy[keep], normal), normal, strength[pick[keep]]


def test_edgels_of_rendered_frames_are_those_of_the_whole_frame_computation():
    """Real OpenCV on rendered frames (the default circuit): the detector blurs and differentiates
    only the bins without a corner, crop by crop, and sorts only the strongest pixels; its edgels
    are those of the plain whole-frame computation, to the last bit (a crop padded by the blur's
    reach has the whole frame's pixels)."""
    from benchmarks.common import render_flight
    from companion.method.mapper.features import HarrisDetector, as_gray

    flight = render_flight(40)
    c = dataclasses.replace(flight.cfg.mapper, max_edgels=40)
    H, W = flight.images[0].shape[:2]
    detector = HarrisDetector(c, W, H, flight.cfg.camera.border_px)
    total = 0
    for image in flight.images[::4]:
        gray = as_gray(image)
        corners, _ = detector(gray)
        corners = corners[: len(corners) // 3]  # fewer corners: more bins without one
        valid = detector.valid_region(gray)
        got = detect_edgels(gray, corners, c, flight.cfg.camera.border_px, valid)
        want = whole_frame_edgels(gray, corners, c, flight.cfg.camera.border_px, valid)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        total += len(got[0])
    assert total > 100


# ----------------------------------------------------------------------------------------------
# The mapper on a straight 3-D edge
# ----------------------------------------------------------------------------------------------

EDGE_NORTH, EDGE_ALT = 45.0, 8.0  # a horizontal edge across the route, 8 m up


def edge_measurements(p_c, R_nc, rng, spacing_m=1.5):
    """Edgels on the edge's image: points of the 3-D edge at a random offset each frame (never the
    same point twice), 0.3 px noise across the edge, unit normals from the edge's image direction."""
    east = np.arange(-12.0, 12.0, spacing_m) + rng.uniform(0, spacing_m)
    pts = np.column_stack([np.full_like(east, EDGE_NORTH), east, np.full_like(east, -EDGE_ALT)])
    uv = CAMERA.project((pts - p_c) @ R_nc)
    uv2 = CAMERA.project((pts + [0.0, 0.1, 0.0] - p_c) @ R_nc)
    d = (uv2 - uv) / np.linalg.norm(uv2 - uv, axis=1, keepdims=True)
    normal = np.column_stack([-d[:, 1], d[:, 0]])
    uv = uv + rng.normal(0.0, 0.3, (len(uv), 1)) * normal
    keep = CAMERA.in_image(uv)
    return uv[keep], normal[keep]


def fly_over_edge(m: Mapper, rng, frames=90, rate=15.0, speed=6.0):
    emitted, covariances = [], []
    for k in range(frames):
        p = np.array([speed * k / rate, 0.0, -15.0])
        nav = nav_state(p, k / rate)
        p_c, R_nc = m.mount.camera_pose(p, nav.R_nb)
        uv, normal = edge_measurements(p_c, R_nc, rng)
        step = m.step_measurements(nav, uv, normals=normal)
        emitted.append(step.points.positions_ned_m)
        covariances.append(step.points.covariances)
    return np.concatenate(emitted), np.concatenate(covariances)


def test_edge_features_converge_on_a_straight_edge_whose_points_are_never_seen_twice():
    rng = np.random.default_rng(7)
    m = Mapper(cfg(), CAMERA, MOUNT)
    X, cov = fly_over_edge(m, rng)
    assert len(X) >= 5
    error = X - [EDGE_NORTH, 0.0, -EDGE_ALT]
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    # where along the edge a point is, is its first ray's choice (east is free); north and height
    # are measured: within 3 sigma of the truth, and the height within 0.3 m
    assert np.all(np.abs(error[:, 0]) < 3 * sigma[:, 0]) and np.all(np.abs(error[:, 0]) < 1.5)
    assert np.all(np.abs(error[:, 2]) < 3 * sigma[:, 2]) and np.all(np.abs(error[:, 2]) < 0.3)
    assert m.db.edge[m.db.active].all()  # every feature started as an edgel


def test_crossing_is_the_angle_between_the_edge_and_the_translations_image_motion():
    """Against finite differences: a point's pixel moves along the direction the mapper computes
    (the same for any depth), so an edge along it has crossing 0 and one across it crossing 1."""
    m = Mapper(cfg(), CAMERA, MOUNT)
    rng = np.random.default_rng(2)
    for v in ([6.0, 0.0, 0.0], [4.0, 2.0, -1.5], [0.0, 3.0, 0.0]):
        nav = nav_state([0.0, 0.0, -20.0], 0.0)
        p_c, R_nc = MOUNT.camera_pose(nav.position_ned_m, nav.R_nb)
        X = p_c + (np.column_stack([np.ones(20), rng.uniform(-0.5, 0.5, (20, 2))]) * rng.uniform(10, 60, (20, 1))) @ R_nc.T
        uv0 = CAMERA.project((X - p_c) @ R_nc)
        uv1 = CAMERA.project((X - (p_c + 1e-4 * np.asarray(v))) @ R_nc)
        flow = (uv1 - uv0) / np.linalg.norm(uv1 - uv0, axis=1, keepdims=True)
        across = np.column_stack([-flow[:, 1], flow[:, 0]])
        np.testing.assert_allclose(m._flow_crossing(R_nc, v, uv0, flow), 1.0, atol=1e-4)  # normal along the motion
        np.testing.assert_allclose(m._flow_crossing(R_nc, v, uv0, across), 0.0, atol=1e-4)
    assert np.all(m._flow_crossing(R_nc, np.zeros(3), uv0, flow) == 0.0)  # hover


def test_edgels_need_the_camera_to_have_moved_since_the_last_frame():
    """The translation comes from the poses (a pose-only recording maps as the live flight): on the
    first frame, and on a frame taken where the last one was, no edgel is used."""
    img = np.full((480, 640), 60, np.uint8)
    cv2.rectangle(img, (100, 120), (540, 360), 160, thickness=-1)
    m = Mapper(cfg(), CAMERA, MOUNT)
    assert m.step(nav_state([0.0, 0.0, -15.0], 0.0), img).n_edgels == 0
    assert m.step(nav_state([0.0, 0.0, -15.0], 0.05), img).n_edgels == 0
    assert m.step(nav_state([0.3, 0.0, -15.0], 0.1, v=(0.0, 0.0, 0.0)), img).n_edgels > 0


def test_an_edge_feature_is_never_updated_by_a_corner_nor_a_corner_by_an_edgel():
    m = Mapper(cfg(), CAMERA, MOUNT)
    nav = nav_state([0.0, 0.0, -15.0], 0.0)
    uv = np.array([[200.0, 200.0], [400.0, 300.0]])
    normals = np.array([[0.0, 1.0], [0.0, 0.0]])  # an edgel, then a corner
    step = m.step_measurements(nav, uv, normals=normals)
    assert step.n_initialised == 2 and step.n_edgels == 1
    assert m.db.edge[m.db.active].tolist() == [True, False]
    # next frame, the same place: the kinds swapped; neither is matched, neither starts a feature
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.05), uv, normals=normals[::-1])
    assert step.n_matched == 0 and step.n_initialised == 0
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.1), uv, normals=normals)
    assert step.n_matched == 2 and step.n_edge_matched == 1


def test_a_gate_holding_two_edges_updates_nothing_but_one_edge_seen_twice_does():
    m = Mapper(cfg(), CAMERA, MOUNT)
    down = np.array([[0.0, 1.0]])
    m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.0), np.array([[320.0, 200.0]]), normals=down)
    assert m.db.edge[m.db.active].tolist() == [True]
    # two edgels of one edge (the same distance across it): the feature is updated
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.05), np.array([[312.0, 200.0], [329.0, 200.2]]),
                               normals=np.repeat(down, 2, axis=0))
    assert step.n_edge_matched == 1
    # two parallel edges 4 px apart, both inside the gate: either could be the feature's
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.1), np.array([[320.0, 198.0], [320.0, 202.0]]),
                               normals=np.repeat(down, 2, axis=0))
    assert step.n_edge_matched == 0 and step.n_initialised == 0


def test_edgels_take_slots_before_the_corners_up_to_half_the_database():
    """An edgel where no corner is (a plain face) starts a feature before the corners do, but edge
    features hold at most half the database that way; the corners take the rest."""
    m = Mapper(cfg(max_features=10), CAMERA, MOUNT)
    rng = np.random.default_rng(4)
    corners = np.column_stack([rng.uniform(20, 300, 10), rng.uniform(20, 460, 10)])  # left half
    edgels = np.column_stack([rng.uniform(340, 620, 20), rng.uniform(20, 460, 20)])  # right half
    uv = np.concatenate([corners, edgels])
    normals = np.concatenate([np.zeros((10, 2)), np.tile([[0.0, 1.0]], (20, 1))])
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.0), uv, normals=normals)
    assert step.n_initialised == 10
    assert int(np.count_nonzero(m.db.edge & m.db.active)) == 5


def test_normals_must_match_the_measurements():
    m = Mapper(cfg(), CAMERA, MOUNT)
    with pytest.raises(ValueError, match="normals"):
        m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.0), np.zeros((3, 2)) + 100, normals=np.zeros((2, 2)))
    # a normal that is neither zero nor unit is a bad measurement: dropped and counted
    step = m.step_measurements(nav_state([0.0, 0.0, -15.0], 0.0), np.array([[100.0, 100.0]]), normals=np.array([[0.5, 0.0]]))
    assert step.n_dropped == 1 and step.n_initialised == 0


# ----------------------------------------------------------------------------------------------
# A rendered building with a plain top
# ----------------------------------------------------------------------------------------------


def test_a_rendered_plain_roof_is_mapped_from_its_outline_before_the_wall():
    """Real OpenCV on rendered frames: the block_half_textured scenario's 16 m building, windows to
    8 m and plain above, approached at 22 m and 6 m/s with the 30 deg mount. With edgels its roof
    edge is in the map at its height while the vehicle is still 15 m short of the wall; corners
    alone never map anything above 10 m."""
    from companion.desk.quality.scenarios import flight_config
    from companion.method.geometry import camera_from_config
    from drivers.sim.renderer import Renderer, RenderOptions
    from drivers.sim.world import World

    world = World.load("block_half_textured")
    config = flight_config(world, "block_half_textured", "inverse_depth", 1, 15.0)
    camera, mount = camera_from_config(config.camera)
    renderer = Renderer(world, camera, RenderOptions(noise_sigma=config.sim.image_noise_sigma,
                                                     blur_sigma_px=config.sim.image_blur_sigma_px, seed=1))
    results = {}
    for edgels in (0, 40):
        m = Mapper(dataclasses.replace(config.mapper, max_edgels=edgels), camera, mount, border_px=config.camera.border_px)
        tops = []
        for k in range(int(35 / 6.0 * 15)):  # north 40 -> 75 at 15 frames/s
            p = np.array([40.0 + 6.0 * k / 15, 0.0, -22.0])
            nav = nav_state(p, k / 15)
            p_c, R_nc = mount.camera_pose(p, nav.R_nb)
            X = m.step(nav, renderer.render(p_c, R_nc)).points.positions_ned_m
            tops.append(X[(X[:, 0] > 88) & (X[:, 0] < 112) & (np.abs(X[:, 1]) < 10) & (-X[:, 2] > 10)])
        results[edgels] = np.concatenate(tops)
    assert len(results[0]) == 0
    high = results[40]
    assert np.all(-high[:, 2] < 17.0), high  # nothing above the roof (its walls' edges are lower)
    top = high[np.abs(high[:, 1]) < 5.0]  # across the route: the roof's front edge
    assert len(top) >= 3
    assert np.all(np.abs(-top[:, 2] - 16.0) < 1.0), top
