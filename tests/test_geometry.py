"""Frames and camera model: conventions hold and conversions invert each other."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.method.geometry import (
    CameraMount,
    PinholeCamera,
    euler_to_matrix,
    euler_to_quat,
    matrix_to_euler,
    matrix_to_quat,
    quat_to_matrix,
    skew,
    so3_exp,
)

angles = st.tuples(
    st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1)
)


@given(angles)
@settings(max_examples=200, deadline=None)
def test_euler_quat_matrix_agree(rpy):
    R = euler_to_matrix(*rpy)
    q = euler_to_quat(*rpy)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    np.testing.assert_allclose(euler_to_matrix(*matrix_to_euler(R)), R, atol=1e-9)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_ned_frd_conventions():
    # Yaw 90 deg: the nose points east.
    R = euler_to_matrix(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # Pitch up 10 deg: the nose points above the horizon (negative NED z).
    R = euler_to_matrix(0.0, np.radians(10), 0.0)
    assert (R @ [1, 0, 0])[2] < 0


def test_camera_mount_pitched_down_looks_down():
    mount = CameraMount.from_euler_deg(0, -45, 0)
    axis = mount.R_bc @ [1, 0, 0]
    np.testing.assert_allclose(axis, [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-12)
    # Image "down" (camera z) tilts toward the tail and down.
    assert (mount.R_bc @ [0, 0, 1])[0] < 0


def test_so3_exp_and_skew():
    rng = np.random.default_rng(0)
    for _ in range(50):
        w = rng.normal(size=3)
        v = rng.normal(size=3)
        np.testing.assert_allclose(skew(w) @ v, np.cross(w, v), atol=1e-12)
        R = so3_exp(w)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R @ w, w, atol=1e-12)  # axis is fixed
    np.testing.assert_allclose(so3_exp(np.zeros(3)), np.eye(3))


def test_projection_ray_roundtrip_and_paper_eq4():
    cam = PinholeCamera(600.0, 610.0, 320.0, 240.0, 640, 480)
    uv = np.array([[320.0, 240.0], [10.0, 20.0], [600.0, 470.0]])
    np.testing.assert_allclose(cam.project(cam.ray(uv)), uv, atol=1e-9)
    # eq. 4: u = f_u h_y / h_x
    np.testing.assert_allclose(cam.project(np.array([2.0, 1.0, -0.5])), [320 + 600 * 0.5, 240 - 610 * 0.25])
    assert np.all(np.isnan(cam.project(np.array([-1.0, 0.0, 0.0]))))
    assert not cam.in_image(np.array([np.nan, 3.0]))
    assert cam.in_image(np.array([5.0, 5.0]), border_px=4) and not cam.in_image(np.array([3.0, 5.0]), border_px=4)


def test_undistort_inverts_distort():
    cam = PinholeCamera(600.0, 600.0, 320.0, 240.0, 640, 480, distortion=np.array([-0.25, 0.08, 0.001, -0.0005, 0.0]))
    rng = np.random.default_rng(1)
    ideal = rng.uniform([20, 20], [620, 460], size=(200, 2))
    raw = cam.distort(ideal)
    assert np.max(np.abs(raw - ideal)) > 1.0  # the lens really moves points
    np.testing.assert_allclose(cam.undistort(raw), ideal, atol=0.05)


def test_default_camera_matches_paper_fov():
    from companion.config import CompanionConfig
    from companion.method.geometry import camera_from_config

    cam, _ = camera_from_config(CompanionConfig().camera)
    assert cam.vertical_fov_deg == pytest.approx(42.0, abs=0.05)
