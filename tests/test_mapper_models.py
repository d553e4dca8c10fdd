"""Feature parameterisations: measurement model, analytic Jacobians, initialisation (seed 000, eqs. 1-5, 13-17)."""

import numpy as np
import pytest

from companion.method.geometry import CameraMount, PinholeCamera, euler_to_matrix, so3_exp
from companion.method.mapper import cartesian, inverse_depth
from companion.method.mapper.depth_prior import flat_ground_ranges, prior_ranges
from companion.method.mapper.projection import CameraPose

CAMERA = PinholeCamera(fx=625.3, fy=610.0, cx=319.5, cy=239.5, width=640, height=480)
MODELS = [inverse_depth, cartesian]


def random_pose(rng: np.random.Generator, mount: CameraMount) -> CameraPose:
    R_nb = euler_to_matrix(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-np.pi, np.pi))
    return CameraPose.from_body(rng.normal(0, 20, 3) + [0, 0, -15], R_nb, mount)


def random_mount(rng: np.random.Generator) -> CameraMount:
    return CameraMount.from_euler_deg(
        rng.uniform(-10, 10), rng.uniform(-80, 10), rng.uniform(-30, 30), offset_m=rng.normal(0, 0.5, 3)
    )


def visible_features(model, rng, pose, n):
    """Features initialised from random pixels with random ranges, then moved a little (a state
    that is not exactly the initial one)."""
    uv = rng.uniform([40, 40], [600, 440], size=(n, 2))
    ranges = rng.uniform(3.0, 80.0, n)
    P_x = np.diag([0.1] * 3 + [1e-4] * 3)
    y, _, R_ref = model.initialise_features(uv, ranges, pose, CAMERA, np.eye(2), 0.05 if model is inverse_depth else 0.5, P_x)
    y = y + rng.normal(0, 0.01, y.shape) * (1.0 if model is inverse_depth else 10.0)
    if model is inverse_depth:
        y[:, inverse_depth.RHO] = np.abs(y[:, inverse_depth.RHO])
    return y, R_ref


def perturbed_pose(pose: CameraPose, mount: CameraMount, dx: np.ndarray) -> CameraPose:
    """Vehicle state ``[p + dx[:3], Exp(dx[3:]) R_nb]`` (the mapper's error convention)."""
    return CameraPose.from_body(pose.p + dx[:3], so3_exp(dx[3:]) @ pose.R_nb, mount)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_jacobians_match_central_differences(model):
    rng = np.random.default_rng(7)
    eps = 1e-6
    for _ in range(40):
        mount = random_mount(rng)
        pose = random_pose(rng, mount)
        y, R_ref = visible_features(model, rng, pose, 5)
        _, h_c = model.measurement_model(y, R_ref, pose, CAMERA)
        keep = h_c[:, 0] > 0.05 * np.linalg.norm(h_c, axis=1)
        y, R_ref = y[keep], R_ref[keep]
        C_x, C_y = model.measurement_jacobian(y, R_ref, pose, CAMERA)
        D = y.shape[1]
        for k in range(D):
            d = np.zeros(D)
            d[k] = eps
            up, _ = model.measurement_model(y + d, R_ref, pose, CAMERA)
            dn, _ = model.measurement_model(y - d, R_ref, pose, CAMERA)
            num = (up - dn) / (2 * eps)
            np.testing.assert_allclose(C_y[:, :, k], num, rtol=1e-5, atol=1e-4 * (1 + np.abs(num).max()))
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            up, _ = model.measurement_model(y, R_ref, perturbed_pose(pose, mount, d), CAMERA)
            dn, _ = model.measurement_model(y, R_ref, perturbed_pose(pose, mount, -d), CAMERA)
            num = (up - dn) / (2 * eps)
            np.testing.assert_allclose(C_x[:, :, k], num, rtol=1e-5, atol=1e-4 * (1 + np.abs(num).max()))


def test_inverse_depth_lever_arm_cancels_in_attitude_jacobian():
    """The derivation: dh/d(dtheta) = R_nc^T [rho (a - p) + m]x uses the body origin p, not p_c."""
    rng = np.random.default_rng(3)
    mount = CameraMount.from_euler_deg(0, -45, 0, offset_m=(1.5, 0.2, 0.4))
    pose = random_pose(rng, mount)
    y, R_ref = visible_features(inverse_depth, rng, pose, 4)
    C_x, _ = inverse_depth.measurement_jacobian(y, R_ref, pose, CAMERA)
    mount0 = CameraMount.from_euler_deg(0, -45, 0)
    # Same camera pose reached with no offset (body origin moved to the camera): the attitude column
    # must differ, because rotating the body now swings the camera about a different point.
    pose0 = CameraPose.from_body(pose.p_c, pose.R_nb, mount0)
    C_x0, _ = inverse_depth.measurement_jacobian(y, R_ref, pose0, CAMERA)
    np.testing.assert_allclose(C_x[:, :, :3], C_x0[:, :, :3], atol=1e-9)
    assert np.abs(C_x[:, :, 3:] - C_x0[:, :, 3:]).max() > 1e-3


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_initialise_then_predict_returns_the_pixel(model):
    rng = np.random.default_rng(11)
    for _ in range(20):
        mount = random_mount(rng)
        pose = random_pose(rng, mount)
        uv = rng.uniform([0, 0], [639, 479], size=(30, 2))
        ranges = rng.uniform(0.5, 500.0, 30)
        y, P, R_ref = model.initialise_features(uv, ranges, pose, CAMERA, np.eye(2), 0.1, np.eye(6) * 1e-3)
        pred, _ = model.measurement_model(y, R_ref, pose, CAMERA)
        np.testing.assert_allclose(pred, uv, atol=1e-8)
        X, _ = model.point_from_state(y, R_ref)
        np.testing.assert_allclose(np.linalg.norm(X - pose.p_c, axis=1), ranges, rtol=1e-10)
        assert np.all(np.linalg.eigvalsh(P) > 0)


def test_inverse_depth_initial_angles_are_zero_on_the_optical_axis():
    mount = CameraMount.from_euler_deg(0, -45, 0)
    pose = CameraPose.from_body(np.zeros(3), np.eye(3), mount)
    y, _, R_ref = inverse_depth.initialise_features(
        np.array([[CAMERA.cx, CAMERA.cy]]), np.array([10.0]), pose, CAMERA, np.eye(2), 0.05, np.eye(6) * 1e-4
    )
    np.testing.assert_allclose(y[0, 3:5], 0.0, atol=1e-12)
    np.testing.assert_allclose(R_ref[0][:, 2], pose.R_nc[:, 0], atol=1e-12)  # reference z = optical axis


def _init_monte_carlo(model, sigma, seed):
    rng = np.random.default_rng(seed)
    mount = CameraMount.from_euler_deg(2, -45, 5, offset_m=(0.8, -0.3, 0.2))
    pose = CameraPose.from_body(np.array([3.0, -2.0, -15.0]), euler_to_matrix(0.05, -0.1, 0.7), mount)
    uv = np.array([[100.0, 80.0], [320.0, 240.0], [600.0, 450.0]])
    ranges = np.array([12.0, 21.0, 35.0])
    R_img = np.diag([1.5**2, 1.0**2])
    P_x = np.diag([0.3**2, 0.2**2, 0.4**2, 0.01**2, 0.008**2, 0.02**2])
    P_x[0, 4] = P_x[4, 0] = 0.3 * 0.008 * 0.5
    y0, P0, R_ref = model.initialise_features(uv, ranges, pose, CAMERA, R_img, sigma, P_x)
    n = 8000
    L = np.linalg.cholesky(P_x)
    samples = np.empty((n,) + y0.shape)
    for k in range(n):
        dx = L @ rng.normal(size=6)
        dz = rng.normal(size=(3, 2)) * np.sqrt(np.diag(R_img))
        pose_k = perturbed_pose(pose, mount, dx)
        if model is inverse_depth:
            # The depth prior is a belief about rho with its own spread sigma_rho.
            r_k = 1.0 / (1.0 / ranges + sigma * rng.normal(size=3))
        else:
            r_k = ranges
        y_k, _, _ = model.initialise_features(uv + dz, r_k, pose_k, CAMERA, R_img, sigma, P_x, R_ref=R_ref)
        if model is cartesian:
            # Depth spread along the (perturbed) ray, as the Cartesian prior assumes.
            m = (y_k - pose_k.p_c) / r_k[:, None]
            y_k = y_k + (sigma * ranges * rng.normal(size=3))[:, None] * m
        samples[k] = y_k
    return y0, P0, samples


@pytest.mark.parametrize("model,sigma", [(inverse_depth, 0.01), (cartesian, 0.05)], ids=["inverse_depth", "cartesian"])
def test_initial_covariance_matches_monte_carlo(model, sigma):
    """Eq. 17 (first order) against the sample covariance of the initialisation function."""
    y0, P0, samples = _init_monte_carlo(model, sigma, 5)
    for j in range(3):
        d = samples[:, j, :] - y0[j]
        if model is inverse_depth:
            d[:, 3] = np.angle(np.exp(1j * d[:, 3]))
        C = d.T @ d / len(d)
        sd = np.sqrt(np.diag(P0[j]))
        # Sigmas within 4% and correlations within 0.05 (sampling error: ~0.8% and ~0.011).
        np.testing.assert_allclose(np.sqrt(np.diag(C)), sd, rtol=0.04)
        corr_mc = C / np.outer(np.sqrt(np.diag(C)), np.sqrt(np.diag(C)))
        corr_an = P0[j] / np.outer(sd, sd)
        np.testing.assert_allclose(corr_mc, corr_an, atol=0.05)


def test_paper_singularity_and_the_reference_frame_that_avoids_it():
    """A camera looking north along the horizon: its central ray is the paper's singular direction
    (theta = 90 deg in the inertial frame). In the per-feature reference frame it is (0, 0)."""
    mount = CameraMount.from_euler_deg(0, 0, 0)  # optical axis = nose = north when level
    pose = CameraPose.from_body(np.array([0.0, 0.0, -15.0]), np.eye(3), mount)
    uv = np.array([[CAMERA.cx, CAMERA.cy + 0.3], [CAMERA.cx + 0.2, CAMERA.cy]])
    P_x = np.diag([0.1] * 3 + [1e-4] * 3)
    y, P, R_ref = inverse_depth.initialise_features(uv, np.array([50.0, 50.0]), pose, CAMERA, np.eye(2), 0.05, P_x)
    assert np.all(np.isfinite(P)) and np.linalg.cond(P[0]) < 1e8
    np.testing.assert_allclose(y[:, 3:5], 0.0, atol=1e-3)
    # The paper's chart: angles in the inertial (NED) frame, (0, 0) straight down.
    R_inertial = np.broadcast_to(np.eye(3), (2, 3, 3)).copy()
    y_p, P_p, _ = inverse_depth.initialise_features(uv, np.array([50.0, 50.0]), pose, CAMERA, np.eye(2), 0.05, P_x, R_ref=R_inertial)
    assert np.degrees(abs(y_p[0, 4])) > 89.9  # theta ~ 90 deg
    assert np.sqrt(P_p[0, 3, 3]) > 100 * np.sqrt(P[0, 3, 3])  # psi variance blows up (1/cos theta)
    # Ours: the Jacobians still agree with finite differences there.
    C_x, C_y = inverse_depth.measurement_jacobian(y, R_ref, pose, CAMERA)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        up, _ = inverse_depth.measurement_model(y + d, R_ref, pose, CAMERA)
        dn, _ = inverse_depth.measurement_model(y - d, R_ref, pose, CAMERA)
        np.testing.assert_allclose(C_y[:, :, k], (up - dn) / 2e-6, rtol=1e-5, atol=1e-3)


def test_point_from_state_jacobian():
    rng = np.random.default_rng(2)
    mount = random_mount(rng)
    pose = random_pose(rng, mount)
    y, R_ref = visible_features(inverse_depth, rng, pose, 6)
    _, J = inverse_depth.point_from_state(y, R_ref)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-7
        up, _ = inverse_depth.point_from_state(y + d, R_ref)
        dn, _ = inverse_depth.point_from_state(y - d, R_ref)
        np.testing.assert_allclose(J[:, :, k], (up - dn) / 2e-7, rtol=1e-5, atol=1e-5)


def test_point_at_infinity_is_handled():
    """rho = 0: the model predicts the direction; the point has no finite position."""
    mount = CameraMount.from_euler_deg(0, -10, 0)
    pose = CameraPose.from_body(np.zeros(3), np.eye(3), mount)
    y, _, R_ref = inverse_depth.initialise_features(np.array([[300.0, 200.0]]), np.array([100.0]), pose, CAMERA, np.eye(2), 0.05, np.eye(6) * 1e-4)
    y[0, inverse_depth.RHO] = 0.0
    moved = CameraPose.from_body(np.array([50.0, 20.0, -5.0]), np.eye(3), mount)
    uv, _ = inverse_depth.measurement_model(y, R_ref, moved, CAMERA)
    np.testing.assert_allclose(uv, [[300.0, 200.0]], atol=1e-9)  # no parallax at infinity
    C_x, C_y = inverse_depth.measurement_jacobian(y, R_ref, moved, CAMERA)
    assert np.all(np.isfinite(C_x)) and np.all(np.isfinite(C_y))
    X, J = inverse_depth.point_from_state(y, R_ref)
    assert np.all(np.isnan(X))
    assert inverse_depth.relative_depth_sigma(y, np.eye(6)[None], R_ref, np.zeros((1, 3)))[0] == np.inf


def test_flat_ground_prior():
    rays = np.array([[0.0, 0.0, 1.0], [np.sqrt(0.5), 0.0, np.sqrt(0.5)], [1.0, 0.0, 0.0], [0.0, 0.6, -0.8]])
    r = flat_ground_ranges(np.array([0.0, 0.0, -17.0]), rays, 2.0, 1.0, 200.0)
    np.testing.assert_allclose(r, [15.0, 15.0 * np.sqrt(2), 200.0, 200.0])
    # Camera below the assumed ground: nothing is known, far prior.
    np.testing.assert_allclose(flat_ground_ranges(np.array([0.0, 0.0, -1.0]), rays, 2.0, 1.0, 200.0), 200.0)


def test_depth_prior_falls_back_where_it_knows_nothing_or_fails():
    rays = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    origin = np.array([0.0, 0.0, -10.0])

    def prior(o, r):
        return np.array([4.0, np.nan, -1.0, np.inf])

    ranges, n_fallback = prior_ranges(prior, origin, rays, 0.0, 1.0, 200.0)
    np.testing.assert_allclose(ranges, [4.0, 10.0, 10.0, 200.0])
    assert n_fallback == 2

    def broken(o, r):
        raise RuntimeError("terrain map unavailable")

    ranges, n_fallback = prior_ranges(broken, origin, rays, 0.0, 1.0, 200.0)
    np.testing.assert_allclose(ranges, 10.0)
    assert n_fallback == 4
    ranges, n_fallback = prior_ranges(lambda o, r: np.ones(2), origin, rays, 0.0, 1.0, 200.0)  # wrong shape
    assert n_fallback == 4
