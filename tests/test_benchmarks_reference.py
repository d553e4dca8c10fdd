"""The benchmark's per-feature loop reference (benchmarks/reference_loop.py) computes exactly what
the batched mapper computes: predictions, Jacobians, innovation covariances, Mahalanobis
distances, gating and matching, and EKF updates agree to 1e-9 on random inputs, and a whole mapper
run on the loop equations makes the same decisions as the batched one. Nothing here is timed."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not an installed package
from benchmarks import reference_loop as ref  # noqa: E402
from companion.config import MapperConfig
from companion.method.geometry import CameraMount, PinholeCamera, euler_to_matrix, matrix_to_quat, so3_exp
from companion.method.mapper import Mapper, inverse_depth, matching, update
from companion.method.mapper.projection import CameraPose
from companion.method.messages import NavState

CAMERA = PinholeCamera(fx=625.3, fy=610.0, cx=319.5, cy=241.0, width=640, height=480)
MOUNT = CameraMount.from_euler_deg(0.0, -45.0, 0.0, offset_m=(0.4, 0.05, 0.15))
RTOL, ATOL = 1e-9, 1e-9
SEEDS = st.integers(0, 2**32 - 1)


def random_spd(rng, n, dim, scale):
    A = rng.normal(0.0, scale, (n, dim, dim))
    return A @ np.swapaxes(A, -1, -2) + np.eye(dim) * scale**2 * 0.1


def random_case(rng, n=25, behind=0):
    """A camera pose, features seen from it (plus ``behind`` features behind the camera), their
    covariances, P_x and R_img."""
    R_nb = so3_exp(rng.normal(0.0, 0.6, 3))
    pose = CameraPose.from_body(rng.normal(0.0, 20.0, 3), R_nb, MOUNT)
    R_ref = np.stack([so3_exp(rng.normal(0.0, 1.0, 3)) for _ in range(n)])
    # Points in front: ray inside the field of view, range 3..80 m, anchors near the camera.
    uv = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n)])
    rays = CAMERA.ray(uv) @ pose.R_nc.T
    if behind:
        rays[:behind] *= -1.0
    X = pose.p_c + rays * rng.uniform(3.0, 80.0, (n, 1))
    anchor = pose.p_c + rng.normal(0.0, 2.0, (n, 3))
    m_ref = np.einsum("nji,nj->ni", R_ref, X - anchor)
    psi, theta = inverse_depth.angles_from_vector(m_ref)
    y = np.column_stack([anchor, psi, theta, 1.0 / np.linalg.norm(X - anchor, axis=1)])
    P_y = random_spd(rng, n, 6, 0.05)
    P_x = random_spd(rng, 1, 6, 0.03)[0]
    R_img = np.diag(rng.uniform(0.5, 2.0, 2) ** 2)
    return pose, y, R_ref, P_y, P_x, R_img


def test_loop_reference_is_a_per_feature_loop_of_its_own():
    """The reference must not call the batched code it is compared with."""
    import inspect

    source = inspect.getsource(ref)
    for name in ("inverse_depth.measurement_model", "inverse_depth.measurement_jacobian", "matching.", "update.ekf_update"):
        assert name not in source


@settings(max_examples=25, deadline=None)
@given(SEEDS)
def test_predictions_and_jacobians_equal_the_batched_model(seed):
    rng = np.random.default_rng(seed)
    pose, y, R_ref, _, _, _ = random_case(rng, n=30, behind=5)
    uv_b, h_b = inverse_depth.measurement_model(y, R_ref, pose, CAMERA)
    uv_l, h_l = ref.measurement_model(y, R_ref, pose, CAMERA)
    np.testing.assert_allclose(h_l, h_b, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(uv_l, uv_b, rtol=RTOL, atol=ATOL)  # NaN where the batched code has NaN
    assert np.isnan(uv_l[:5]).all() and np.isfinite(uv_l[5:]).all()
    front = h_b[:, 0] > 0
    C_x_b, C_y_b = inverse_depth.measurement_jacobian(y[front], R_ref[front], pose, CAMERA, h_b[front])
    C_x_l, C_y_l = ref.measurement_jacobian(y[front], R_ref[front], pose, CAMERA)
    np.testing.assert_allclose(C_x_l, C_x_b, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(C_y_l, C_y_b, rtol=RTOL, atol=ATOL)


def test_loop_jacobian_matches_finite_differences_of_the_loop_model():
    """Independent of the batched code: the loop's own Jacobian is the derivative of its own model."""
    rng = np.random.default_rng(3)
    pose, y, R_ref, _, _, _ = random_case(rng, n=6)
    eps = 1e-6
    for j in range(len(y)):
        C_x, C_y = ref.measurement_jacobian_one(y[j], R_ref[j], pose, CAMERA)
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            up, _ = ref.measurement_model_one(y[j] + d, R_ref[j], pose, CAMERA)
            dn, _ = ref.measurement_model_one(y[j] - d, R_ref[j], pose, CAMERA)
            np.testing.assert_allclose((up - dn) / (2 * eps), C_y[:, k], rtol=1e-5, atol=1e-4)
        for k in range(6):  # vehicle error: position, then attitude (R_true = Exp(dtheta) R_est)
            d = np.zeros(6)
            d[k] = eps

            def perturbed(dx):
                R_nb = so3_exp(dx[3:]) @ pose.R_nb
                return CameraPose.from_body(pose.p + dx[:3], R_nb, MOUNT)

            up, _ = ref.measurement_model_one(y[j], R_ref[j], perturbed(d), CAMERA)
            dn, _ = ref.measurement_model_one(y[j], R_ref[j], perturbed(-d), CAMERA)
            np.testing.assert_allclose((up - dn) / (2 * eps), C_x[:, k], rtol=1e-5, atol=1e-4)


@settings(max_examples=25, deadline=None)
@given(SEEDS)
def test_innovation_covariance_and_distances_equal_the_batched_matching(seed):
    rng = np.random.default_rng(seed)
    pose, y, R_ref, P_y, P_x, R_img = random_case(rng, n=20)
    uv, h = inverse_depth.measurement_model(y, R_ref, pose, CAMERA)
    C_x, C_y = inverse_depth.measurement_jacobian(y, R_ref, pose, CAMERA, h)
    S_b = matching.innovation_covariance(C_x, C_y, P_x, P_y, R_img)
    S_l = ref.innovation_covariance(C_x, C_y, P_x, P_y, R_img)
    np.testing.assert_allclose(S_l, S_b, rtol=RTOL, atol=ATOL)
    S_b[3] = [[1.0, 2.0], [2.0, 1.0]]  # indefinite: no distance (inf) in both
    z = np.vstack([uv[:12] + rng.normal(0.0, 2.0, (12, 2)), rng.uniform(0, 640, (15, 2))])
    Z_b = matching.mahalanobis_distances(z, uv, S_b)
    Z_l = ref.mahalanobis_distances(z, uv, S_b)
    np.testing.assert_allclose(Z_l, Z_b, rtol=RTOL, atol=ATOL)
    assert np.isinf(Z_l[3]).all()


@settings(max_examples=40, deadline=None)
@given(SEEDS, st.integers(0, 30), st.integers(0, 30), st.sampled_from([5.99, 9.21, 50.0]))
def test_gating_matching_and_exclusion_equal_the_batched_code(seed, n, m, gate):
    rng = np.random.default_rng(seed)
    g = rng.uniform(0, 200, (n, 2))
    z = np.vstack([g[: m // 2] + rng.normal(0.0, 3.0, (min(n, m // 2), 2)), rng.uniform(0, 200, (m - min(n, m // 2), 2))])
    if m >= 2:
        z[rng.integers(1, m)] = z[0]  # ties between measurements ...
    S = random_spd(rng, n, 2, 3.0)
    Z = matching.mahalanobis_distances(z, g, S)
    if n and m:
        Z[rng.integers(0, n), :] = Z[0, :]  # ... and between points go to the lower index in both
    p_b, i_b, a_b = matching.gate_and_match(Z, gate)
    p_l, i_l, a_l = ref.gate_and_match(Z, gate)
    np.testing.assert_array_equal(p_l, p_b)
    np.testing.assert_array_equal(i_l, i_b)
    np.testing.assert_array_equal(a_l, a_b)
    np.testing.assert_array_equal(ref.near_stored_features(Z, z, g, 23.0, 10.0),
                                  matching.near_stored_features(Z, z, g, 23.0, 10.0))


@settings(max_examples=25, deadline=None)
@given(SEEDS)
def test_ekf_updates_equal_the_batched_update(seed):
    rng = np.random.default_rng(seed)
    pose, y, R_ref, P_y, P_x, R_img = random_case(rng, n=20)
    uv, h = inverse_depth.measurement_model(y, R_ref, pose, CAMERA)
    C_x, C_y = inverse_depth.measurement_jacobian(y, R_ref, pose, CAMERA, h)
    innovation = rng.normal(0.0, 2.0, (len(y), 2))
    C_y[2] = np.nan  # a corrupt feature keeps its prior, flagged, in both
    y_b, P_b, ok_b = update.ekf_update(y, P_y, innovation, C_x, C_y, P_x, R_img)
    y_l, P_l, ok_l = ref.ekf_update(y, P_y, innovation, C_x, C_y, P_x, R_img)
    np.testing.assert_array_equal(ok_l, ok_b)
    assert not ok_l[2] and ok_l[np.arange(len(y)) != 2].all()
    np.testing.assert_allclose(y_l, y_b, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(P_l, P_b, rtol=RTOL, atol=ATOL)
    np.testing.assert_array_equal(y_l[2], y[2])


# ------------------------------------------------------------------------------------------------
# Whole mapper runs: batched against loop equations on the same measurements
# ------------------------------------------------------------------------------------------------


def measurement_sequence(n_frames=40, seed=5):
    """Ground points seen from a camera flying north at 15 m; (NavState, ideal pixels) per frame."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(0.0, 80.0, 3.0), np.arange(-25.0, 25.0, 3.0), indexing="ij")
    world = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    world[:, :2] += rng.uniform(-1.0, 1.0, (len(world), 2))
    strength = rng.permutation(len(world))
    cov = np.diag([0.05**2] * 3 + [0.1**2] * 3 + [np.radians(0.2) ** 2] * 3)
    out = []
    for k in range(n_frames):
        t = k / 15.0
        p = np.array([6.0 * t, 0.3 * np.sin(t), -15.0])
        R_nb = euler_to_matrix(0.02 * np.sin(1.3 * t), 0.015 * np.sin(0.9 * t), 0.0)
        p_c, R_nc = MOUNT.camera_pose(p, R_nb)
        uv = CAMERA.project((world - p_c) @ R_nc)
        seen = np.flatnonzero(CAMERA.in_image(uv, 8.0))
        seen = seen[np.argsort(strength[seen])][:80]
        z = uv[seen] + rng.normal(0.0, 1.0, (len(seen), 2))
        R_est = so3_exp(-rng.normal(0.0, np.radians(0.2), 3)) @ R_nb
        out.append((NavState(t, p + rng.normal(0.0, 0.05, 3), np.array([6.0, 0, 0]), matrix_to_quat(R_est), cov), z))
    return out


def test_a_mapper_run_on_the_loop_equations_makes_the_batched_decisions():
    cfg = MapperConfig(max_features=30)
    batched = Mapper(cfg, CAMERA, MOUNT)
    looped = Mapper(cfg, CAMERA, MOUNT)
    seq = measurement_sequence()
    matched_total = 0
    with ref.loop_reference(looped) as m:
        assert m.model.measurement_model is ref.measurement_model
        for nav, z in seq:
            a = batched.step_measurements(nav, z)
            b = m.step_measurements(nav, z)
            np.testing.assert_array_equal(b.matched_ids, a.matched_ids)
            np.testing.assert_array_equal(b.initialised_ids, a.initialised_ids)
            np.testing.assert_array_equal(b.removed_ids, a.removed_ids)
            np.testing.assert_array_equal(b.points.feature_ids, a.points.feature_ids)
            np.testing.assert_allclose(b.points.positions_ned_m, a.points.positions_ned_m, rtol=1e-7, atol=1e-7)
            matched_total += a.n_matched
    assert matched_total > 10 * len(seq)  # the run really tracked features
    fa, fb = batched.features(), looped.features()
    np.testing.assert_array_equal(fb.ids, fa.ids)
    np.testing.assert_allclose(fb.states, fa.states, rtol=1e-7, atol=1e-9)
    # and the swap was undone on exit
    import companion.method.mapper.mapper as mapper_module

    assert mapper_module.ekf_update is update.ekf_update
    assert looped.model is inverse_depth


def test_daemon_headline_is_the_median_of_the_runs_p99s():
    """benchmarks/run.py: repeated daemon runs give the median of each p99 (a failed run is left out),
    the details of the run whose frame -> setpoint p99 is the median."""
    from benchmarks.run import median_run

    runs = [{"frame_to_setpoint_ms": {"p99": 20.0, "p50": 9.0}, "jitter_ms": {"p99": 3.0}},
            {"frame_to_setpoint_ms": {"p99": 12.0, "p50": 7.0}, "jitter_ms": {"p99": 6.0}},
            {"error": "no Zenoh session with the daemon"},
            {"frame_to_setpoint_ms": {"p99": 14.0, "p50": 8.0}, "jitter_ms": {"p99": 2.0}}]
    m = median_run(runs)
    assert m["frame_to_setpoint_ms"] == {"p99": 14.0, "p50": 8.0, "p99_of_runs": [12.0, 14.0, 20.0]}
    assert m["jitter_ms"]["p99"] == 3.0 and m["jitter_ms"]["p99_of_runs"] == [2.0, 3.0, 6.0]
    assert m["runs_completed"] == 3
    assert median_run([{"error": "x"}]) == {"error": "x"}
