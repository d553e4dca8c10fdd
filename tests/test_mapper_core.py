"""Mapper core: batched EKF update, matching, database rules and degenerate input (seed 000, section II)."""

import dataclasses

import numpy as np
import pytest

from companion.config import MapperConfig
from companion.method.geometry import CameraMount, PinholeCamera, euler_to_quat
from companion.method.mapper import Mapper, cartesian, inverse_depth
from companion.method.mapper.mapper import ConsistencyScale, tilt_covariance
from companion.method.mapper.matching import gate_and_match, innovation_covariance, mahalanobis_distances
from companion.method.mapper.projection import CameraPose
from companion.method.mapper.update import ekf_update
from companion.method.messages import NavState

CAMERA = PinholeCamera(fx=625.3, fy=625.3, cx=319.5, cy=239.5, width=640, height=480)
MOUNT = CameraMount.from_euler_deg(0.0, -45.0, 0.0, offset_m=(0.3, 0.0, 0.1))
R_IMG = np.eye(2)


def nav_state(p=(0.0, 0.0, -15.0), rpy=(0.0, 0.0, 0.0), sigma_p=0.05, sigma_att=np.radians(0.2), t=0.0, cov=None):
    if cov is None:
        cov = np.diag([sigma_p**2] * 3 + [0.01] * 3 + [sigma_att**2] * 3)
    return NavState(t, np.asarray(p, float), np.zeros(3), euler_to_quat(*rpy), cov)


def mapper(**cfg) -> Mapper:
    return Mapper(dataclasses.replace(MapperConfig(), **cfg), CAMERA, MOUNT)


def snapshot(m: Mapper):
    db = m.db
    return [a.copy() for a in (db.y, db.P, db.R_ref, db.origin, db.confidence, db.active, db.ids, db.updates, db.converged)]


def assert_same(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def grid_pixels(n_u=6, n_v=5, margin=60):
    u, v = np.meshgrid(np.linspace(margin, 639 - margin, n_u), np.linspace(margin, 479 - margin, n_v))
    return np.column_stack([u.ravel(), v.ravel()])


# ----------------------------------------------------------------------------------------------
# Update (eqs. 6-9)
# ----------------------------------------------------------------------------------------------


def textbook_update(y, P_y, e, C_x, C_y, P_x, R):
    """One feature, full joint state [x, y_j] with P_j = blockdiag(P_x, P_y) (eq. 6), the usual EKF
    gain and covariance; keep the feature block (the vehicle is not corrected)."""
    nx, ny = P_x.shape[0], P_y.shape[0]
    P = np.zeros((nx + ny, nx + ny))
    P[:nx, :nx], P[nx:, nx:] = P_x, P_y
    C = np.hstack([C_x, C_y])
    S = C @ P @ C.T + R
    K = P @ C.T @ np.linalg.inv(S)
    P_new = (np.eye(nx + ny) - K @ C) @ P
    return y + K[nx:] @ e, P_new[nx:, nx:]


@pytest.mark.parametrize("model", [inverse_depth, cartesian], ids=["inverse_depth", "cartesian"])
def test_batched_update_equals_textbook_per_feature_ekf(model):
    rng = np.random.default_rng(4)
    pose = CameraPose.from_body(np.array([1.0, 2.0, -15.0]), np.eye(3), MOUNT)
    uv = rng.uniform([50, 50], [590, 430], (12, 2))
    A = rng.normal(size=(6, 6))
    P_x = A @ A.T * 1e-3
    y, P, R_ref = model.initialise_features(uv, rng.uniform(5, 40, 12), pose, CAMERA, R_IMG, 0.05 if model is inverse_depth else 0.5, P_x)
    moved = CameraPose.from_body(np.array([2.0, 2.3, -15.2]), np.eye(3), MOUNT)
    g, h = model.measurement_model(y, R_ref, moved, CAMERA)
    C_x, C_y = model.measurement_jacobian(y, R_ref, moved, CAMERA, h)
    e = rng.normal(0, 3, (12, 2))
    R = np.array([[1.3, 0.2], [0.2, 0.8]])
    y_new, P_new, ok = ekf_update(y, P, e, C_x, C_y, P_x, R)
    assert ok.all()
    for j in range(12):
        y_ref, P_ref = textbook_update(y[j], P[j], e[j], C_x[j], C_y[j], P_x, R)
        np.testing.assert_allclose(y_new[j], y_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(P_new[j], P_ref, rtol=1e-7, atol=1e-12)
        np.testing.assert_array_equal(P_new[j], P_new[j].T)


def test_joseph_update_keeps_covariance_positive_definite_when_badly_conditioned():
    rng = np.random.default_rng(1)
    n = 200
    Q = np.linalg.qr(rng.normal(size=(n, 6, 6)))[0]
    eig = 10.0 ** rng.uniform(-10, 3, (n, 6))
    P = Q @ (eig[:, :, None] * np.swapaxes(Q, 1, 2))
    C_y = rng.normal(0, 500, (n, 2, 6))
    C_x = rng.normal(0, 50, (n, 2, 6))
    y_new, P_new, ok = ekf_update(np.zeros((n, 6)), P, rng.normal(size=(n, 2)), C_x, C_y, np.eye(6) * 1e-6, R_IMG * 1e-4)
    assert ok.all()
    np.testing.assert_array_equal(P_new, np.swapaxes(P_new, 1, 2))
    assert np.linalg.eigvalsh(P_new).min() > -1e-9 * np.abs(P_new).max()


def test_update_refuses_non_positive_definite_innovation_or_non_finite_result():
    y = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    P = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    C_y = np.broadcast_to(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (3, 2, 3)).copy()
    C_x = np.zeros((3, 2, 6))
    e = np.array([[1.0, 1.0], [np.nan, 0.0], [1.0, 1.0]])
    C_y[2] *= 0.0
    R = np.array([[1.0, 0.0], [0.0, 1.0]])
    y_new, P_new, ok = ekf_update(y, P, e, C_x, C_y, np.zeros((6, 6)), R)
    assert ok.tolist() == [True, False, True]
    np.testing.assert_array_equal(y_new[1], y[1])
    np.testing.assert_array_equal(P_new[1], P[1])
    # S = C P C^T + R with R indefinite: refused, state kept.
    y_bad, P_bad, ok = ekf_update(y, P, np.ones((3, 2)), C_x, C_y * 0, np.zeros((6, 6)), -R)
    assert not ok.any()
    np.testing.assert_array_equal(y_bad, y)
    np.testing.assert_array_equal(P_bad, P)


# ----------------------------------------------------------------------------------------------
# Matching (eqs. 10-12)
# ----------------------------------------------------------------------------------------------


def test_no_false_match_on_well_separated_points():
    rng = np.random.default_rng(8)
    for _ in range(200):
        n = rng.integers(1, 40)
        g = rng.uniform([0, 0], [640, 480], (n, 2))
        keep = np.ones(n, bool)
        for j in range(n):  # at least 40 px apart
            if keep[j] and np.any(np.linalg.norm(g[keep] - g[j], axis=1)[np.flatnonzero(keep) != j] < 40):
                keep[j] = False
        g = g[keep]
        n = len(g)
        sig = rng.uniform(1.0, 3.0, n)
        S = (sig**2)[:, None, None] * np.eye(2)
        seen = rng.random(n) < 0.8
        z_true = g[seen] + rng.normal(0, 1, (seen.sum(), 2)) * sig[seen, None]
        clutter = rng.uniform([0, 0], [640, 480], (5, 2))
        clutter = clutter[np.min(np.linalg.norm(clutter[:, None] - g[None], axis=2), axis=1) > 40]
        z = np.vstack([z_true, clutter])
        order = rng.permutation(len(z))
        z = z[order]
        truth = np.full(len(z), -1)
        truth[np.argsort(order)[: seen.sum()]] = np.flatnonzero(seen)
        Z = mahalanobis_distances(z, g, S)
        pi, mi, ambiguous = gate_and_match(Z, 9.21)
        assert np.all(truth[mi] == pi)  # every accepted pair is right
        assert not ambiguous[truth == -1].any()


def test_ambiguous_measurements_go_to_the_nearest_and_are_flagged():
    g = np.array([[100.0, 100.0]])
    S = np.array([np.eye(2) * 4.0])
    z = np.array([[103.0, 100.0], [101.0, 100.0], [300.0, 300.0]])  # two inside the gate
    pi, mi, ambiguous = gate_and_match(mahalanobis_distances(z, g, S), 9.21)
    assert pi.tolist() == [0] and mi.tolist() == [1]
    assert ambiguous.tolist() == [True, False, False]


def test_two_points_competing_for_one_measurement():
    g = np.array([[100.0, 100.0], [104.0, 100.0]])
    S = np.array([np.eye(2) * 9.0, np.eye(2) * 9.0])
    z = np.array([[101.0, 100.0]])
    pi, mi, ambiguous = gate_and_match(mahalanobis_distances(z, g, S), 9.21)
    assert pi.tolist() == [0] and mi.tolist() == [0]  # the closer point wins, the other is unmatched
    # Point 1's nearest measurement (z1) is nearer still to point 0, which prefers z0: not mutual,
    # so point 1 stays unmatched rather than take a measurement that is probably point 0's, and z1
    # is flagged ambiguous (not initialised).
    g = np.array([[100.0, 100.0], [110.0, 100.0]])
    z = np.array([[101.0, 100.0], [103.0, 100.0]])
    pi, mi, ambiguous = gate_and_match(mahalanobis_distances(z, g, S), 9.21)
    assert list(zip(pi.tolist(), mi.tolist())) == [(0, 0)]
    assert ambiguous.tolist() == [False, True]
    g = np.array([[100.0, 100.0], [104.0, 100.0]])
    # Exact tie: the lower index wins (deterministic).
    z = np.array([[102.0, 100.0]])
    pi, mi, _ = gate_and_match(mahalanobis_distances(z, g, S), 9.21)
    assert pi.tolist() == [0]


def test_gate_uses_the_navigation_covariance():
    """S_j includes C_x P_x C_x^T (eq. 10): a larger P_x widens the search region."""
    pose = CameraPose.from_body(np.array([0.0, 0.0, -15.0]), np.eye(3), MOUNT)
    y, P, R_ref = inverse_depth.initialise_features(np.array([[320.0, 240.0]]), np.array([21.0]), pose, CAMERA, R_IMG, 0.05, np.zeros((6, 6)))
    C_x, C_y = inverse_depth.measurement_jacobian(y, R_ref, pose, CAMERA)
    z = np.array([[330.0, 240.0]])
    g, _ = inverse_depth.measurement_model(y, R_ref, pose, CAMERA)
    small = mahalanobis_distances(z, g, innovation_covariance(C_x, C_y, np.zeros((6, 6)), P, R_IMG))[0, 0]
    P_x = np.diag([0.0] * 3 + [np.radians(1.0) ** 2] * 3)
    big = mahalanobis_distances(z, g, innovation_covariance(C_x, C_y, P_x, P, R_IMG))[0, 0]
    assert small > 9.21 > big


def test_non_positive_definite_search_region_matches_nothing():
    g = np.array([[100.0, 100.0]])
    S = np.array([[[1.0, 2.0], [2.0, 1.0]]])
    Z = mahalanobis_distances(np.array([[100.0, 100.0]]), g, S)
    assert Z[0, 0] == np.inf
    assert len(gate_and_match(Z, 9.21)[0]) == 0


# ----------------------------------------------------------------------------------------------
# Database, confidence index, initialisation index, emission
# ----------------------------------------------------------------------------------------------


def test_first_frame_fills_the_database_in_score_order():
    m = mapper(max_features=10)
    uv = grid_pixels()
    step = m.step_measurements(nav_state(), uv)
    assert (step.n_measurements, step.n_initialised, step.n_active, step.n_matched) == (30, 10, 10, 0)
    assert step.initialised_measurements.tolist() == list(range(10))
    assert step.initialised_ids.tolist() == list(range(10))
    assert np.all(m.features().confidence == 20)  # initialisation index with nothing matched


def test_matched_features_gain_confidence_and_unmatched_lose_it():
    m = mapper(max_features=10)
    nav = nav_state()
    uv = grid_pixels()[:10]
    m.step_measurements(nav, uv)
    step = m.step_measurements(nav, uv[:6])  # same view: 6 seen again, 4 not
    assert step.n_matched == 6 and step.n_initialised == 0
    conf = dict(zip(m.features().ids.tolist(), m.features().confidence.tolist()))
    assert [conf[i] for i in range(10)] == [21] * 6 + [19] * 4
    assert step.init_index == pytest.approx(20 * (1 - 6 / 10))


def test_the_lines_of_sight_carry_their_features_and_the_attitudes_sigma():
    """The free space a step hands the map names the feature of each segment (so the map counts
    features, not frames) and the sigma of their direction: the navigation's attitude covariance,
    its largest axis (docs/terrain.md, "Free space")."""
    m = mapper(max_features=10)
    cov = np.diag([0.05**2] * 3 + [0.01] * 3 + list(np.radians([0.5, 0.7, 2.0]) ** 2))
    uv = grid_pixels()[:10]
    m.step_measurements(nav_state(cov=cov), uv)
    step = m.step_measurements(nav_state(cov=cov), uv[:6])
    fs = step.free_space
    assert len(fs) == 6 and sorted(fs.feature_ids.tolist()) == sorted(step.matched_ids.tolist())
    assert fs.angle_sigma_rad == pytest.approx(np.radians(2.0))


def test_unmatched_measurement_replaces_lowest_confidence_feature_below_the_index():
    m = mapper(max_features=4)
    nav = nav_state()
    old = grid_pixels(2, 2, margin=100)
    m.step_measurements(nav, old)  # 4 features, confidence 20 each
    new = grid_pixels(3, 3, margin=30)[[0, 2, 6]]  # far from the old ones: nothing matches
    step = m.step_measurements(nav, np.vstack([new, old[:1]]))
    # One matched -> index 20 * (1 - 1/4) = 15; the three unmatched old features have 19 > 15: kept.
    assert step.n_matched == 1 and step.n_initialised == 0 and step.n_removed == 0
    for _ in range(4):
        step = m.step_measurements(nav, np.vstack([new, old[:1]]))
    # 19 - 4 = 15 is not below 15: still kept. One more frame: 14 < 15, replaced in score order.
    assert step.n_initialised == 0
    step = m.step_measurements(nav, np.vstack([new, old[:1]]))
    assert step.n_initialised == 3 and step.n_removed == 3 and step.n_active == 4
    assert sorted(step.initialised_ids.tolist()) == [4, 5, 6]  # ids are never reused
    assert step.initialised_measurements.tolist() == [0, 1, 2]


def test_ambiguous_measurement_is_not_initialised():
    m = mapper(max_features=10)
    nav = nav_state()
    m.step_measurements(nav, np.array([[300.0, 200.0]]))
    step = m.step_measurements(nav, np.array([[302.5, 200.0], [300.5, 200.0]]))
    assert step.n_matched == 1 and step.matched_measurements.tolist() == [1]
    assert step.n_ambiguous == 1 and step.n_initialised == 0 and step.n_active == 1


def test_measurement_just_outside_the_gate_of_a_feature_is_not_initialised_as_a_duplicate():
    m = mapper(max_features=10, init_exclusion_chi2=1000.0)
    nav = nav_state(sigma_p=1e-4, sigma_att=1e-6)
    m.step_measurements(nav, np.array([[300.0, 200.0]]))
    s = m.features()
    step = m.step_measurements(nav, np.array([[330.0, 200.0]]))
    assert step.n_matched == 0 and step.n_ambiguous == 0 and step.n_excluded == 1 and step.n_initialised == 0
    step = m.step_measurements(nav, np.array([[600.0, 400.0]]))  # far away: a new feature
    assert step.n_initialised == 1
    assert s.ids.tolist() == [0]


def flight(m: Mapper, world: np.ndarray, n_frames: int, rng, speed=6.0, rate=16.0, start=(0.0, 0.0, -15.0), rpy=(0, 0, 0)):
    """Fly north past ``world`` points (0.5 px noise, accurate navigation); yield (k, step, uv)."""
    for k in range(n_frames):
        p = np.asarray(start, float) + [speed * k / rate, 0.0, 0.0]
        nav = nav_state(p=p, rpy=rpy, sigma_p=0.02, sigma_att=np.radians(0.05), t=k / rate)
        p_c, R_nc = m.mount.camera_pose(p, nav.R_nb)
        uv = CAMERA.project((world - p_c) @ R_nc) + rng.normal(0, 0.5, (len(world), 2))
        yield k, m.step_measurements(nav, uv[CAMERA.in_image(uv)]), uv


def test_converged_feature_is_emitted_once_on_convergence_not_again_when_it_leaves_the_view():
    rng = np.random.default_rng(5)
    world = np.array([[30.0, 0.0, 0.0], [32.0, 5.0, 0.0], [28.0, -4.0, 0.0]])
    m = mapper(max_features=10)
    emitted: dict[int, list[int]] = {}
    removed = []
    for k, step, _ in flight(m, world, 150, rng):
        for fid in step.points.feature_ids.tolist():
            emitted.setdefault(fid, []).append(k)
        removed += step.removed_ids.tolist()
    assert sorted(emitted) == [0, 1, 2]
    for fid, frames in emitted.items():
        assert len(frames) == 1 and fid in removed  # on convergence only (the map would count it twice)
    assert m.features().ids.size == 0


def test_consistency_scale_is_the_running_mean_innovation_squared_over_two():
    """docs/mapper.md, "Calibrated point covariance": 1 until min_updates, then m / 2 within
    [1 / max_factor, max_factor], forgetting with ``memory`` updates."""
    c = ConsistencyScale(memory=1000.0, min_updates=100.0, max_factor=10.0)
    c.add(0.5 * 60, 60)
    assert c.scale == 1.0  # 60 updates: not yet
    c.add(0.5 * 60, 60)
    assert c.scale == pytest.approx(0.25)
    c.add(float("nan"), 50)
    c.add(10.0, 0)
    n_old = 60 * (1 - 1e-3) ** 60 + 60  # the first 60 forgotten by the second 60's updates
    assert c.scale == pytest.approx(0.25) and c.updates == pytest.approx(n_old)  # NaN, none: ignored
    # The filter's innovations grow to what it says (m = 2): after one memory the old mean weighs
    # (1 - 1/1000)^1000 ~ 1/e of what it did, and the scale is most of the way to 1.
    for _ in range(100):
        c.add(2.0 * 10, 10)
    w_old = n_old * (1 - 1e-3) ** 1000
    expected = (0.5 * w_old + 2.0 * (c.updates - w_old)) / c.updates / 2
    assert c.scale == pytest.approx(expected) and 0.85 < c.scale < 1.0
    low = ConsistencyScale(memory=1000.0, min_updates=0.0, max_factor=10.0)
    low.add(0.001, 100)
    assert low.scale == pytest.approx(0.1)
    high = ConsistencyScale(memory=1000.0, min_updates=0.0, max_factor=10.0)
    high.add(1e4, 100)
    assert high.scale == pytest.approx(10.0)


@pytest.mark.parametrize("calibrate, tilt", [(True, True), (False, True), (True, False)])
def test_emitted_points_carry_the_filter_covariance_times_the_consistency_scale(calibrate, tilt):
    """The points sent to the map, and only they, are scaled: the features keep the filter's own.
    The navigation's tilt is added to the points after the scale (it is not the filter's)."""
    rng = np.random.default_rng(5)
    world = np.array([[30.0, 0.0, 0.0], [32.0, 5.0, 0.0], [28.0, -4.0, 0.0], [35.0, -2.0, 0.0]])
    m = mapper(max_features=10, calibration_min_updates=20.0, calibrate_point_covariance=calibrate,
               point_tilt_covariance=tilt)
    checked = 0
    for k, step, _ in flight(m, world, 150, rng):
        assert step.point_covariance_scale == (m.consistency.scale if calibrate else 1.0)
        if len(step.points):
            before = m.features()  # the emitted features are still in the database this step
            i = np.searchsorted(before.ids, step.points.feature_ids)
            expected = before.covariances[i] * step.point_covariance_scale
            if tilt:  # flight(): the camera where the mount puts it, 0.05 deg of attitude sigma per axis
                p = np.array([6.0 * k / 16.0, 0.0, -15.0])
                p_c, _ = m.mount.camera_pose(p, np.eye(3))
                expected = expected + tilt_covariance(step.points.positions_ned_m - p_c, np.eye(3) * np.radians(0.05) ** 2)
            np.testing.assert_allclose(step.points.covariances, expected, rtol=1e-9)
            checked += len(step.points)
    assert checked >= 3
    if calibrate:  # 0.5 px measured, 1 px told
        assert 0.1 <= m.consistency.scale < 0.6


def test_the_tilt_of_the_navigation_turns_a_point_about_the_camera_by_its_lever_arm():
    """tilt_covariance is the first-order covariance of ``c + Exp(-e) (X - c)`` for a roll/pitch
    error ``e`` (docs/mapper.md, "The navigation's tilt"): its Jacobian against finite
    differences of the rotation, the height's sigma the horizontal lever arm times the tilt's
    sigma, nothing for a point straight below the camera, and nothing from the yaw."""
    from companion.method.geometry import so3_exp

    r = np.array([[25.0, 3.0, 15.0], [0.0, 0.0, 15.0], [-8.0, 20.0, 4.0]])  # from the camera, NED
    for lever in r:
        h = 1e-6
        J = np.column_stack([(so3_exp(-h * axis) @ lever - so3_exp(h * axis) @ lever) / (2 * h) for axis in np.eye(3)])
        P = np.diag([0.3, 0.7, 0.0]) * 1e-4  # no yaw: the full Jacobian applies
        np.testing.assert_allclose(tilt_covariance(lever[None], P)[0], J @ P @ J.T, rtol=1e-6, atol=1e-14)
    one_deg = np.diag(np.radians([1.0, 1.0, 5.0])) ** 2
    cov = tilt_covariance(r, one_deg)
    np.testing.assert_allclose(np.sqrt(cov[:, 2, 2]), np.hypot(r[:, 0], r[:, 1]) * np.radians(1.0), rtol=1e-12)
    assert np.sqrt(cov[0, 2, 2]) == pytest.approx(0.44, abs=0.01)   # 25 m ahead, 1 deg: 0.44 m
    assert cov[1, 2, 2] == 0.0                                        # below the camera: no height error
    yaw_only = tilt_covariance(r, np.diag([0.0, 0.0, np.radians(5.0) ** 2]))
    assert np.all(yaw_only == 0.0)


def test_database_never_exceeds_capacity():
    rng = np.random.default_rng(9)
    world = np.column_stack([rng.uniform(10, 80, 300), rng.uniform(-20, 20, 300), np.zeros(300)])
    m = mapper(max_features=20)
    for _, step, _ in flight(m, world, 40, rng):
        assert step.n_active <= 20
        assert m.db.n_active == step.n_active
        ids = m.features().ids
        assert len(np.unique(ids)) == len(ids)


def test_forward_camera_flying_north_along_the_papers_singular_direction():
    """Optical axis horizontal and north: the paper's inertial (psi, theta) chart is singular on
    the central rays; with the per-feature reference frame the wall ahead converges to the truth."""
    rng = np.random.default_rng(2)
    mount = CameraMount.from_euler_deg(0.0, 0.0, 0.0)
    m = Mapper(MapperConfig(), CAMERA, mount)
    wall = np.column_stack([np.full(40, 60.0), rng.uniform(-8, 8, 40), rng.uniform(-19, -11, 40)])
    final = {}
    truth_of = {}
    for k in range(100):
        p = np.array([6.0 * k / 16.0, 0.0, -15.0])
        nav = nav_state(p=p, sigma_p=0.02, sigma_att=np.radians(0.05), t=k / 16.0)
        p_c, R_nc = mount.camera_pose(p, nav.R_nb)
        uv = CAMERA.project((wall - p_c) @ R_nc) + rng.normal(0, 0.5, (40, 2))
        step = m.step_measurements(nav, uv)
        for fid, i in zip(step.initialised_ids.tolist(), step.initialised_measurements.tolist()):
            truth_of[fid] = i
        for fid, X in zip(step.points.feature_ids.tolist(), step.points.positions_ned_m):
            final[fid] = X
    snap = m.features()
    theta = snap.states[:, inverse_depth.THETA]
    assert np.all(np.abs(theta) < np.radians(30))  # far from the chart's own singularity
    for fid, X in zip(snap.ids.tolist(), snap.positions_ned_m):
        final[fid] = X
    errors = np.array([np.linalg.norm(final[f] - wall[truth_of[f]]) for f in final])
    assert len(errors) >= 30
    assert np.median(errors) < 0.5


# ----------------------------------------------------------------------------------------------
# Degenerate input
# ----------------------------------------------------------------------------------------------


def primed_mapper() -> Mapper:
    m = mapper(max_features=10)
    m.step_measurements(nav_state(), grid_pixels()[:8])
    return m


@pytest.mark.parametrize(
    "nav,reason",
    [
        (nav_state(p=(np.nan, 0.0, -15.0)), "nav not finite"),
        (nav_state(t=np.inf), "nav not finite"),
        (nav_state(cov=np.full((9, 9), np.inf)), "nav not finite"),
        (nav_state(cov=np.diag([1.0] * 6 + [-1e-3, 1e-3, 1e-3])), "not positive semi-definite"),
        (nav_state(cov=np.triu(np.ones((9, 9)))), "not symmetric"),
        (NavState(0.0, np.zeros(3), np.zeros(3), np.zeros(4), np.eye(9)), "quaternion"),
        (NavState(0.0, np.zeros(2), np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(9)), "shapes"),
    ],
)
def test_bad_navigation_refuses_the_step_and_leaves_the_database_untouched(nav, reason):
    m = primed_mapper()
    before = snapshot(m)
    step = m.step_measurements(nav, grid_pixels())
    assert reason in step.rejected_reason
    assert step.n_matched == step.n_initialised == step.n_removed == 0 and len(step.points) == 0
    assert step.n_active == 8 and step.n_rejected == 30
    assert_same(before, snapshot(m))
    assert m.step(nav, np.zeros((480, 640), np.uint8)).rejected_reason  # refused before detection


def test_singular_navigation_covariance_is_accepted():
    m = primed_mapper()
    step = m.step_measurements(nav_state(cov=np.zeros((9, 9))), grid_pixels()[:8] + 0.3)
    assert step.rejected_reason == "" and step.n_matched == 8
    assert np.all(np.isfinite(m.db.P[m.db.active]))


def test_zero_measurements():
    m = primed_mapper()
    step = m.step_measurements(nav_state(), np.zeros((0, 2)))
    assert step.rejected_reason == "" and step.n_matched == 0 and step.n_active == 8
    assert np.all(m.features().confidence == 19)
    empty = mapper().step_measurements(nav_state(), np.array([]))
    assert empty.n_active == 0


def test_bad_measurements_are_dropped_and_counted():
    m = primed_mapper()
    uv = np.vstack([grid_pixels()[:8], [[np.nan, 10.0], [np.inf, 5.0], [-3.0, 10.0], [10.0, 480.0], [700.0, 10.0]]])
    step = m.step_measurements(nav_state(), uv)
    assert step.n_dropped == 5 and step.n_rejected == 5 and step.n_matched == 8
    assert step.matched_measurements.max() < 8
    with pytest.raises(ValueError, match="shape"):
        m.step_measurements(nav_state(), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="image"):
        m.step(nav_state(), np.zeros((4, 4, 3, 2)))


def test_feature_at_infinity():
    """rho = 0 is a valid state: it is predicted, matched and updated, but not emitted as a point."""
    m = primed_mapper()
    slot = m.db.active_slots()[0]
    m.db.y[slot, inverse_depth.RHO] = 0.0
    m.db.P[slot, inverse_depth.RHO, inverse_depth.RHO] = 1e-8  # and a confident one at that
    g, _ = inverse_depth.measurement_model(m.db.y[[slot]], m.db.R_ref[[slot]], CameraPose.from_body(np.array([0.0, 0, -15]), np.eye(3), MOUNT), CAMERA)
    for k in range(5):
        step = m.step_measurements(nav_state(p=(0.1 * k, 0.0, -15.0)), np.vstack([g, grid_pixels()[1:8]]))
        assert step.rejected_reason == ""
    snap = m.features()
    i = snap.ids.tolist().index(int(m.db.ids[slot]))
    assert np.all(np.isfinite(snap.states[i])) and abs(snap.states[i, inverse_depth.RHO]) < 1e-6
    assert snap.updates[i] == 5  # matched every frame: no parallax, still at infinity
    assert not snap.converged[i] and snap.relative_depth_sigma[i] > 1e3


def test_corrupt_feature_is_removed_not_propagated():
    m = primed_mapper()
    m.db.P[m.db.active_slots()[2]] = np.nan
    step = m.step_measurements(nav_state(), grid_pixels()[:8])
    assert step.n_removed == 1 and step.n_active >= 7
    assert np.all(np.isfinite(m.db.P[m.db.active]))


def test_failing_depth_prior_falls_back_to_flat_ground():
    m = mapper()

    def broken(origin, rays):
        raise RuntimeError("map not ready")

    m.depth_prior = broken
    step = m.step_measurements(nav_state(), grid_pixels()[:5])
    assert step.n_initialised == 5 and step.n_prior_fallback == 5
    np.testing.assert_allclose(m.features().positions_ned_m[:, 2], 0.0, atol=1e-9)  # on the ground plane

    m2 = Mapper(MapperConfig(), CAMERA, MOUNT, default_ground_alt_m=5.0)  # ground 5 m up
    m2.step_measurements(nav_state(), grid_pixels()[:5])
    np.testing.assert_allclose(m2.features().positions_ned_m[:, 2], -5.0, atol=1e-9)

    m3 = Mapper(MapperConfig(), CAMERA, MOUNT, depth_prior=lambda o, r: np.full(len(r), 7.0))
    step = m3.step_measurements(nav_state(), grid_pixels()[:5])
    assert step.n_prior_fallback == 0
    np.testing.assert_allclose(np.linalg.norm(m3.features().positions_ned_m - m3.db.origin[m3.db.active], axis=1), 7.0)


@pytest.mark.parametrize("model", ["inverse_depth", "cartesian"])
def test_without_the_map_prior_every_feature_starts_on_the_flat_ground(model):
    """mapper.map_depth_prior false: the map's ray cast is not asked (the paper's eq. 16 for every
    feature: the range to the ground plane at terrain.default_ground_alt_m), for both models."""
    asked = []

    def map_prior(origin, rays):
        asked.append(len(rays))
        return np.full(len(rays), 7.0)

    cfg = dataclasses.replace(MapperConfig(), parameterisation=model, map_depth_prior=False)
    m = Mapper(cfg, CAMERA, MOUNT, depth_prior=map_prior)
    step = m.step_measurements(nav_state(), grid_pixels()[:5])
    assert step.n_initialised == 5 and step.n_prior_fallback == 0 and asked == []
    np.testing.assert_allclose(m.features().positions_ned_m[:, 2], 0.0, atol=1e-9)
    with_map = Mapper(dataclasses.replace(cfg, map_depth_prior=True), CAMERA, MOUNT, depth_prior=map_prior)
    with_map.step_measurements(nav_state(), grid_pixels()[:5])
    assert asked == [5]
    X, origin = with_map.features().positions_ned_m, with_map.db.origin[with_map.db.active]
    np.testing.assert_allclose(np.linalg.norm(X - origin, axis=1), 7.0)


def test_step_undistorts_detected_pixels():
    cam = dataclasses.replace(CAMERA, distortion=np.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
    raw = np.array([[40.0, 30.0], [600.0, 450.0], [320.0, 240.0]])
    calls = []

    def detector(image):
        calls.append(image.shape)
        return raw, np.array([3.0, 2.0, 1.0])

    m = Mapper(MapperConfig(), cam, MOUNT, detector=detector)
    nav = nav_state()
    step = m.step(nav, np.zeros((480, 640), np.uint8))
    assert calls == [(480, 640)] and step.n_initialised == 3
    pose = CameraPose.from_body(nav.position_ned_m, nav.R_nb, MOUNT)
    slots = m.db.active_slots()
    pred, _ = inverse_depth.measurement_model(m.db.y[slots], m.db.R_ref[slots], pose, cam)
    np.testing.assert_allclose(pred, cam.undistort(raw), atol=1e-6)
    assert np.abs(pred - raw).max() > 5.0  # the distortion is not negligible here


def test_step_with_the_harris_detector_on_a_real_image():
    """Two views of a textured ground plane through the default detector: corners are found,
    initialised, then matched in the next frame."""
    import cv2

    rng = np.random.default_rng(0)
    texture = np.full((1200, 1200), 128, np.uint8)
    for _ in range(400):
        x, y = rng.integers(0, 1200, 2)
        cv2.rectangle(texture, (int(x), int(y)), (int(x + rng.integers(8, 30)), int(y + rng.integers(8, 30))), int(rng.integers(0, 255)), -1)
    scale = 20.0  # texture pixels per metre, centred on (north 20 m, east 0)

    def render(p):
        # Homography from the ground plane (z = 0) to the image of a camera at p.
        p_c, R_nc = MOUNT.camera_pose(p, np.eye(3))
        K = CAMERA.K
        R_cv = (R_nc @ np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])).T  # NED -> OpenCV camera
        t = -R_cv @ p_c
        G = np.column_stack([R_cv[:, 0], R_cv[:, 1], t])  # ground (n, e, 1) -> camera
        T = np.array([[0, 1 / scale, 0], [1 / scale, 0, 0], [0, 0, 1]]) @ np.array([[1, 0, -600], [0, 1, -600], [0, 0, 1]])
        T = np.array([[1, 0, 20.0], [0, 1, 0], [0, 0, 1]]) @ T
        return cv2.warpPerspective(texture, K @ G @ T, (640, 480), flags=cv2.INTER_LINEAR, borderValue=128)

    m = Mapper(MapperConfig(), CAMERA, MOUNT, border_px=8)
    first = m.step(nav_state(p=(0.0, 0.0, -15.0), sigma_p=0.01, sigma_att=1e-4), render(np.array([0.0, 0.0, -15.0])))
    assert first.n_measurements > 20 and first.n_initialised == min(first.n_measurements, 50)
    second = m.step(nav_state(p=(0.3, 0.0, -15.0), sigma_p=0.01, sigma_att=1e-4), render(np.array([0.3, 0.0, -15.0])))
    assert second.n_matched > 0.6 * first.n_initialised
