"""NavState assembly and covariance models: conversions checked against finite differences and
Monte Carlo, model selection and provenance strings, floors, rejection counters, truth pose."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import NavConfig
from companion.method.geometry import euler_to_matrix, euler_to_quat, matrix_to_quat, quat_to_matrix
from companion.method.navigation.assembler import ARDUPILOT_EARTH_RADIUS_M, GeoOrigin, NavAssembler, TRUTH_PAIR_WINDOW_S, geodetic_to_ned
from companion.method.navigation.covariance import (
    apply_floors,
    covariance_block,
    covariance_problem,
    euler_covariance_to_rotvec,
    euler_rate_jacobian_ned,
    quat_to_euler,
    reported_covariance,
    rotvec_covariance_to_euler,
    upper_triangle_to_matrix,
)

CFG = NavConfig()
NAN = float("nan")


def so3_log(R):
    """Rotation vector of a rotation matrix (test helper, angles < pi)."""
    c = max(-1.0, min(1.0, (np.trace(R) - 1) / 2))
    angle = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    return angle / (2 * math.sin(angle)) * w


def triu(P):
    rows, cols = np.triu_indices(P.shape[0])
    return P[rows, cols]


def msg(kind, **fields):
    return {"mavpackettype": kind, **fields}


def lpn(t_ms, p=(1.0, 2.0, -10.0), v=(0.5, 0.0, 0.0)):
    return msg("LOCAL_POSITION_NED", time_boot_ms=t_ms, x=p[0], y=p[1], z=p[2], vx=v[0], vy=v[1], vz=v[2])


def aq(t_ms, q=(1.0, 0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0)):
    return msg("ATTITUDE_QUATERNION", time_boot_ms=t_ms, q1=q[0], q2=q[1], q3=q[2], q4=q[3], rollspeed=rates[0], pitchspeed=rates[1], yawspeed=rates[2])


def odometry(t_us, q=(1.0, 0, 0, 0), v=(0.0, 0.0, 0.0), pose=None, twist=None, child=1, frame=1, p=(0.0, 0.0, -5.0)):
    nan21 = [NAN] * 21
    return msg(
        "ODOMETRY", time_usec=t_us, frame_id=frame, child_frame_id=child, x=p[0], y=p[1], z=p[2], q=list(q),
        vx=v[0], vy=v[1], vz=v[2], rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0,
        pose_covariance=nan21 if pose is None else list(pose), velocity_covariance=nan21 if twist is None else list(twist),
        reset_counter=0, estimator_type=0,
    )  # fmt: skip


def px4_diag21(d):
    """PX4's ODOMETRY layout: only the six variances set, everything else NaN (ODOMETRY.hpp)."""
    out = [NAN] * 21
    for idx, value in zip((0, 6, 11, 15, 18, 20), d):
        out[idx] = value
    return out


# --------------------------------------------------------------------------------------------
# Conversions
# --------------------------------------------------------------------------------------------


def test_upper_triangle_is_row_major_as_mavlink_lays_it_out():
    P = np.arange(36, dtype=float).reshape(6, 6)
    P = P + P.T
    np.testing.assert_array_equal(upper_triangle_to_matrix(triu(P), 6), P)
    vals = upper_triangle_to_matrix(np.arange(21.0), 6)
    assert vals[0, 5] == 5 and vals[1, 1] == 6 and vals[2, 2] == 11 and vals[3, 3] == 15 and vals[5, 5] == 20
    with pytest.raises(ValueError, match="21 values"):
        upper_triangle_to_matrix(np.zeros(20), 6)


@settings(deadline=None, max_examples=40)
@given(roll=st.floats(-3.1, 3.1), pitch=st.floats(-1.4, 1.4), yaw=st.floats(-3.1, 3.1))
def test_euler_jacobian_matches_finite_differences(roll, pitch, yaw):
    E = euler_rate_jacobian_ned(roll, pitch, yaw)
    R0 = euler_to_matrix(roll, pitch, yaw)
    h = 1e-6
    for i in range(3):
        e = np.array([roll, pitch, yaw])
        e[i] += h
        dtheta = so3_log(euler_to_matrix(*e) @ R0.T) / h
        np.testing.assert_allclose(E[:, i], dtheta, atol=2e-5)


def test_euler_covariance_to_rotvec_against_monte_carlo():
    rng = np.random.default_rng(7)
    roll, pitch, yaw = 0.3, -0.5, 2.0
    q = euler_to_quat(roll, pitch, yaw)
    sig = np.radians([2.0, 1.5, 4.0])
    corr = np.array([[1.0, 0.3, -0.2], [0.3, 1.0, 0.1], [-0.2, 0.1, 1.0]])
    P_rpy = np.outer(sig, sig) * corr
    n = 40000
    de = rng.multivariate_normal(np.zeros(3), P_rpy, size=n)
    R0 = euler_to_matrix(roll, pitch, yaw)
    Rs = euler_to_matrix(roll + de[:, 0], pitch + de[:, 1], yaw + de[:, 2])
    samples = np.array([so3_log(R @ R0.T) for R in Rs])
    empirical = np.cov(samples.T)
    predicted = euler_covariance_to_rotvec(P_rpy, q)
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    np.testing.assert_allclose(empirical / scale, predicted / scale, atol=0.03)  # 40k samples: ~1% noise


def test_rotvec_to_euler_is_the_inverse():
    q = euler_to_quat(-0.2, 0.7, -1.0)
    P = np.diag([1e-4, 2e-4, 5e-4]) + 1e-5
    np.testing.assert_allclose(euler_covariance_to_rotvec(rotvec_covariance_to_euler(P, q), q), P, atol=1e-15)
    assert quat_to_euler(q) == pytest.approx((-0.2, 0.7, -1.0))


def test_reported_covariance_unknown_nan_offdiag_and_problems():
    assert reported_covariance([NAN] * 21, 6) == (None, None)
    P, problem = reported_covariance(px4_diag21([1, 2, 3, 4, 5, 6]), 6)
    assert problem is None
    np.testing.assert_array_equal(P, np.diag([1.0, 2, 3, 4, 5, 6]))
    bad = px4_diag21([1, -2, 3, 4, 5, 6])
    assert reported_covariance(bad, 6) == (None, "negative variance")
    partial = px4_diag21([1, 2, 3, NAN, NAN, NAN])  # PX4 velocity_covariance: no angular-rate variances
    P, problem = reported_covariance(partial, 6)
    assert problem is None
    np.testing.assert_array_equal(covariance_block(P, slice(0, 3))[0], np.diag([1.0, 2, 3]))
    assert covariance_block(P, slice(3, 6)) == (None, None)  # unknown, not a problem
    not_psd, _ = reported_covariance(triu(np.array([[1.0, 2.0], [2.0, 1.0]])), 2)
    assert covariance_block(not_psd, slice(0, 2)) == (None, "covariance not positive semi-definite")
    inf = px4_diag21([1, 2, 3, 4, 5, 6])
    inf[1] = float("inf")
    assert reported_covariance(inf, 6) == (None, "non-finite covariance")
    assert covariance_problem(np.diag([1.0, np.inf])) == "non-finite covariance"


def test_a_huge_variance_does_not_hide_a_correlation_above_one():
    """Judged on the correlation matrix: a vertical variance of 1e18 must not excuse a horizontal correlation of
    -2.3 (found by the link fuzz), while a rank-deficient but valid matrix and float32 rounding pass."""
    P = np.diag([0.01, 0.01, 1.5e18])
    P[0, 1] = P[1, 0] = -0.0234
    assert covariance_problem(P) == "covariance not positive semi-definite"
    P[0, 1] = P[1, 0] = 0.01  # correlation exactly 1: singular, still a covariance
    assert covariance_problem(P) is None
    assert covariance_problem(P.astype(np.float32).astype(float)) is None
    zero_axis = np.diag([0.0, 1.0])
    assert covariance_problem(zero_axis) is None
    zero_axis[0, 1] = zero_axis[1, 0] = 1e-3  # a zero variance cannot covary
    assert covariance_problem(zero_axis) == "covariance not positive semi-definite"


@settings(deadline=None, max_examples=50)
@given(seed=st.integers(0, 2**32 - 1), floor=st.floats(0.0, 2.0))
def test_floors_raise_marginals_and_keep_psd(seed, floor):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(9, 4)) * rng.uniform(0.01, 3.0)
    P = A @ A.T  # rank 4: PSD, singular
    F = apply_floors(P, np.full(9, floor))
    assert np.all(np.diag(F) >= floor**2 - 1e-12)
    assert np.linalg.eigvalsh(F).min() >= -1e-9
    off = ~np.eye(9, dtype=bool)
    np.testing.assert_array_equal(F[off], P[off])  # correlations untouched


def test_geodetic_to_ned_uses_ardupilot_scaling():
    k = ARDUPILOT_EARTH_RADIUS_M * math.pi / 180
    origin = GeoOrigin(47.0, 8.0, 400.0, "GPS_GLOBAL_ORIGIN")
    lat = 47.0 + 100.0 / k
    lon = 8.0 + 50.0 / (k * math.cos(math.radians(0.5 * (lat + 47.0))))
    np.testing.assert_allclose(geodetic_to_ned(lat, lon, 410.0, origin), [100.0, 50.0, -10.0], atol=1e-9)


# --------------------------------------------------------------------------------------------
# Assembly and model selection
# --------------------------------------------------------------------------------------------


def test_position_and_attitude_make_a_state_with_floors_only():
    a = NavAssembler(CFG)
    assert a.update(lpn(1000), 5.0) is None  # no attitude yet
    s = a.update(aq(1000), 5.0)
    assert s is not None and s.covariance_source == "floors"
    np.testing.assert_allclose(s.position_ned_m, [1, 2, -10])
    floors = np.r_[[0.3] * 3, [0.1] * 3, [math.radians(0.5)] * 3] ** 2
    np.testing.assert_allclose(np.diag(s.covariance), floors)
    assert a.time_basis.startswith("arrival")


def test_time_map_places_states_on_the_companion_clock_and_halves_are_carried():
    a = NavAssembler(CFG, time_map=lambda t: t + 100.0)
    yaw_rate = 0.5
    a.update(aq(1000, rates=(0, 0, yaw_rate)), 101.01)  # arrival times: a few ms after the stamps
    s = a.update(lpn(1040, v=(2.0, 0, 0)), 101.05)
    assert s.t_s == pytest.approx(101.04)
    # attitude carried 40 ms forward by its body rates
    assert quat_to_euler(s.quaternion_wxyz)[2] == pytest.approx(yaw_rate * 0.04, abs=1e-9)
    s = a.update(aq(1060, rates=(0, 0, yaw_rate)), 101.07)
    np.testing.assert_allclose(s.position_ned_m, [1 + 2.0 * 0.02, 2, -10], atol=1e-12)  # position carried 20 ms
    assert a.time_basis.startswith("autopilot clock")


def test_halves_too_far_apart_are_not_combined_and_older_halves_are_superseded():
    a = NavAssembler(CFG, time_map=lambda t: t)
    a.update(aq(1000), 1.0)
    assert a.update(lpn(1000 + int(CFG.max_skew_s * 1000) + 50), 1.2) is None
    b = NavAssembler(CFG, time_map=lambda t: t)
    b.update(lpn(1000), 1.0)
    assert b.update(aq(1010), 1.02) is not None
    assert b.update(aq(1005), 1.03) is None and b.superseded == 1


def test_ardupilot_ekf_status_and_gps_model():
    a = NavAssembler(CFG)
    a.update(msg("GPS_RAW_INT", fix_type=3, h_acc=1200, v_acc=2000, vel_acc=300), 1.0)
    a.update(msg("EKF_STATUS_REPORT", flags=0x3FF & ~1024 & ~128, velocity_variance=0.1, pos_horiz_variance=0.2, pos_vert_variance=1.0, compass_variance=0.0, terrain_alt_variance=0.0), 1.0)
    a.update(lpn(1000), 1.0)
    s = a.update(aq(1000), 1.0)
    assert s.covariance_source == "EKF_STATUS_REPORT+GPS_RAW_INT+floors"
    sig = np.sqrt(np.diag(s.covariance))
    np.testing.assert_allclose(sig[:2], 1.2 / math.sqrt(2))  # ratio 0.2 < 0.5: unscaled GPS h_acc
    np.testing.assert_allclose(sig[2], 2.0 * (1.0 / 0.5))  # vertical ratio 1.0: doubled
    np.testing.assert_allclose(sig[3:6], 0.3)
    np.testing.assert_allclose(sig[6:9], math.radians(0.5))
    assert a.last_covariance_blocks["position"] == "EKF_STATUS_REPORT+GPS_RAW_INT+floors"
    # Without GPS accuracy the floors are the base.
    b = NavAssembler(CFG)
    b.update(msg("EKF_STATUS_REPORT", flags=47, velocity_variance=1.0, pos_horiz_variance=0.0, pos_vert_variance=0.0, compass_variance=math.sqrt(3), terrain_alt_variance=0.0), 1.0)
    b.update(lpn(1000), 1.0)
    s = b.update(aq(1000), 1.0)
    assert s.covariance_source == "EKF_STATUS_REPORT+floors"
    sig = np.sqrt(np.diag(s.covariance))
    np.testing.assert_allclose(sig[3:6], 0.1 * 2)
    np.testing.assert_allclose(sig[8], math.radians(0.5) * 2)  # heading scaled by the compass ratio
    np.testing.assert_allclose(sig[6:8], math.radians(0.5))


def test_px4_odometry_covariance_with_body_frame_velocity():
    a = NavAssembler(CFG)
    yaw = math.radians(90)
    q = euler_to_quat(0.0, 0.0, yaw)
    pose = px4_diag21([4.0, 4.0, 9.0, 1e-4, 1e-4, 4e-4])
    twist = px4_diag21([0.25, 0.04, 0.01, NAN, NAN, NAN])  # as PX4 sends it: no angular-rate variances
    s = a.update(odometry(5_000_000, q=q, v=(1.0, 0.0, 0.0), pose=pose, twist=twist, child=12), 2.0)
    assert s.covariance_source == "ODOMETRY"
    np.testing.assert_allclose(s.velocity_ned_mps, [0.0, 1.0, 0.0], atol=1e-12)  # forward = east at yaw 90
    np.testing.assert_allclose(np.diag(s.covariance)[:3], [4, 4, 9])
    np.testing.assert_allclose(np.diag(s.covariance)[3:6], [0.04, 0.25, 0.01], atol=1e-12)  # rotated with the body
    np.testing.assert_allclose(s.covariance[6:9, 6:9], np.diag([1e-4, 1e-4, 4e-4]), atol=1e-15)  # level: E = I up to yaw
    assert s.covariance[0, 1] == 0.0  # PX4's NaN off-diagonals read as unknown correlation


def test_odometry_attitude_covariance_is_rotated_into_ned():
    a = NavAssembler(CFG)
    roll, pitch, yaw = 0.2, 0.4, 1.0
    q = euler_to_quat(roll, pitch, yaw)
    P = np.diag([1.0, 1.0, 1.0, 3e-4, 2e-4, 1e-3])
    P[0, 3] = P[3, 0] = 0.005
    s = a.update(odometry(1_000_000, q=q, pose=triu(P)), 1.0)
    E = euler_rate_jacobian_ned(roll, pitch, yaw)
    np.testing.assert_allclose(s.covariance[6:9, 6:9], E @ P[3:, 3:] @ E.T, atol=1e-12)
    np.testing.assert_allclose(s.covariance[0:3, 6:9], P[:3, 3:] @ E.T, atol=1e-12)
    assert np.linalg.eigvalsh(s.covariance).min() > 0


def test_odometry_unknown_covariance_falls_back_and_bad_frames_are_rejected():
    a = NavAssembler(CFG)
    s = a.update(odometry(1_000_000), 1.0)
    assert s.covariance_source == "floors"
    assert a.update(odometry(2_000_000, frame=0), 1.0) is None
    assert a.update(odometry(2_000_000, child=4), 1.0) is None  # ENU velocity: not supported
    assert a.rejections.counts == {"ODOMETRY: unsupported frame_id": 1, "ODOMETRY: unsupported child_frame_id": 1}


def test_local_position_cov_and_attitude_cov_models():
    a = NavAssembler(CFG)
    A = np.random.default_rng(3).normal(size=(9, 9)) * 0.3
    P9 = A @ A.T + np.eye(9)
    a.update(msg("LOCAL_POSITION_NED_COV", covariance=list(triu(P9))), 1.0)
    q = euler_to_quat(0.1, -0.2, 0.3)
    P3 = np.diag([1e-3, 2e-3, 3e-3])
    a.update(msg("ATTITUDE_QUATERNION_COV", q=list(q), covariance=list(P3.reshape(-1))), 1.0)
    a.update(lpn(1000), 1.0)
    s = a.update(aq(1000, q=q), 1.0)
    assert s.covariance_source == "LOCAL_POSITION_NED_COV+ATTITUDE_QUATERNION_COV"
    np.testing.assert_allclose(s.covariance[:6, :6], P9[:6, :6])
    np.testing.assert_allclose(s.covariance[6:, 6:], euler_covariance_to_rotvec(P3, q))
    assert np.all(s.covariance[:6, 6:] == 0)


def test_estimator_status_model():
    a = NavAssembler(CFG)
    a.update(msg("ESTIMATOR_STATUS", flags=0b111111, vel_ratio=0.1, pos_horiz_ratio=0.1, pos_vert_ratio=0.1, mag_ratio=2.0, hagl_ratio=0, tas_ratio=0, pos_horiz_accuracy=2.0, pos_vert_accuracy=3.0), 1.0)
    a.update(lpn(1000), 1.0)
    s = a.update(aq(1000), 1.0)
    assert s.covariance_source == "ESTIMATOR_STATUS+floors"
    np.testing.assert_allclose(np.diag(s.covariance)[:3], [2.0, 2.0, 9.0])  # eph^2 split over north/east
    np.testing.assert_allclose(math.sqrt(s.covariance[8, 8]), math.radians(0.5) * 4)
    assert a.health(1.0) == (True, "ESTIMATOR_STATUS flags good")


def test_floors_bound_tiny_reported_covariances():
    a = NavAssembler(CFG)
    s = a.update(odometry(1_000_000, pose=px4_diag21([1e-6] * 6), twist=px4_diag21([1e-6] * 6)), 1.0)
    sig = np.sqrt(np.diag(s.covariance))
    np.testing.assert_allclose(sig, np.r_[[0.3] * 3, [0.1] * 3, [math.radians(0.5)] * 3])
    assert s.covariance_source == "ODOMETRY"


def test_yaw_floor_raises_the_heading_sigma_only():
    """nav.yaw_sigma_floor_deg: ArduPilot reports no attitude covariance, so the floors are the
    sigmas the mapper assumes; the simulator injects 0.5 deg of tilt and 2 deg of yaw error."""
    cfg = NavConfig(yaw_sigma_floor_deg=2.0)
    a = NavAssembler(cfg)
    s = a.update(odometry(1_000_000, pose=px4_diag21([1e-6] * 6), twist=px4_diag21([1e-6] * 6)), 1.0)
    sig = np.sqrt(np.diag(s.covariance))
    np.testing.assert_allclose(sig[6:9], np.radians([0.5, 0.5, 2.0]))
    np.testing.assert_allclose(a.floor_sigmas[6:9], np.radians([0.5, 0.5, 2.0]))
    # Below the attitude floor it changes nothing: the attitude floor applies to every axis.
    np.testing.assert_allclose(NavAssembler(NavConfig(yaw_sigma_floor_deg=0.2)).floor_sigmas[6:9], np.radians([0.5] * 3))


def test_rejected_covariances_fall_back_and_are_counted():
    a = NavAssembler(CFG)
    bad = np.eye(9)
    bad[0, 1] = bad[1, 0] = 5.0  # not PSD
    a.update(msg("LOCAL_POSITION_NED_COV", covariance=list(triu(bad))), 1.0)
    neg = -np.eye(9)
    a.update(msg("LOCAL_POSITION_NED_COV", covariance=list(triu(neg))), 1.0)
    a.update(odometry(1_000_000, pose=px4_diag21([1, 1, 1, 1, 1, -1])), 1.0)
    s = a.update(aq(1_000), 1.0)
    assert s.covariance_source == "floors"
    assert a.rejections.counts == {
        "LOCAL_POSITION_NED_COV: covariance not positive semi-definite": 1,
        "LOCAL_POSITION_NED_COV: negative variance": 1,
        "ODOMETRY: pose negative variance": 1,
    }


def test_bad_states_are_rejected_with_reasons():
    a = NavAssembler(CFG)
    assert a.update(lpn(1000, p=(NAN, 0, 0)), 1.0) is None
    assert a.update(lpn(1000, p=(0, 0, 1e9)), 1.0) is None
    assert a.update(aq(1000, q=(1.01, 0, 0, 0)), 1.0) is None
    assert a.update(aq(1000, q=(0, 0, 0, 0)), 1.0) is None
    assert a.update(msg("LOCAL_POSITION_NED", x=1.0), 1.0) is None  # malformed: fields missing
    assert a.rejections.counts == {
        "LOCAL_POSITION_NED: non-finite position": 1,
        "LOCAL_POSITION_NED: position out of range": 1,
        "ATTITUDE_QUATERNION: non-unit quaternion": 2,
        "LOCAL_POSITION_NED: malformed": 1,
    }
    a.update(lpn(1000), 1.0)
    s = a.update(aq(1000, q=(1.0004, 0, 0, 0)), 1.0)  # slightly off: normalised
    assert s is not None and np.linalg.norm(s.quaternion_wxyz) == pytest.approx(1.0, abs=1e-15)


def test_old_evidence_is_not_used():
    a = NavAssembler(CFG)
    a.update(msg("ESTIMATOR_STATUS", flags=63, vel_ratio=0, pos_horiz_ratio=0, pos_vert_ratio=0, mag_ratio=0, hagl_ratio=0, tas_ratio=0, pos_horiz_accuracy=2.0, pos_vert_accuracy=3.0), 0.0)
    a.update(lpn(1000), CFG.covariance_max_age_s + 0.1)
    s = a.update(aq(1000), CFG.covariance_max_age_s + 0.1)
    assert s.covariance_source == "floors"


def test_health_from_ekf_flags_names_the_problem():
    a = NavAssembler(CFG)
    a.update(msg("EKF_STATUS_REPORT", flags=1 | 2 | 4 | 32 | 128, velocity_variance=0, pos_horiz_variance=0, pos_vert_variance=0, compass_variance=0, terrain_alt_variance=0), 1.0)
    ok, why = a.health(1.0)
    assert not ok and "POS_HORIZ_REL" in why and "CONST_POS_MODE" in why
    a.update(msg("EKF_STATUS_REPORT", flags=47, velocity_variance=0, pos_horiz_variance=0, pos_vert_variance=0, compass_variance=0, terrain_alt_variance=0), 2.0)
    assert a.health(2.0)[0]
    assert a.health(10.0) == (True, "no estimator status (health unknown)")


def test_unix_time_usec_needs_system_time():
    a = NavAssembler(CFG, time_map=lambda t: t - 13.02)
    unix_us = 1_700_000_000_000_000
    s = a.update(odometry(unix_us), 7.0)
    assert s.t_s == 7.0  # cannot map yet: arrival time
    a.update(msg("SYSTEM_TIME", time_unix_usec=unix_us + 1_000_000, time_boot_ms=20_000), 7.5)
    s = a.update(odometry(unix_us + 2_000_000), 8.0)
    assert s.t_s == pytest.approx(21.0 - 13.02)
    assert a.time_basis_changes == 1  # arrival time -> synchronised


def test_truth_pose_from_sim_state_and_origin_or_home():
    k = ARDUPILOT_EARTH_RADIUS_M * math.pi / 180
    q = euler_to_quat(0.1, 0.0, 0.5)
    lat0, lon0 = 47.0, 8.0
    lat = lat0 + 30.0 / k

    def sim(lat, lon, alt):
        return msg("SIM_STATE", q1=q[0], q2=q[1], q3=q[2], q4=q[3], lat=lat, lon=lon, alt=alt, vn=1.0, ve=2.0, vd=0.0, lat_int=int(round(lat * 1e7)), lon_int=int(round(lon * 1e7)))

    a = NavAssembler(CFG)
    a.update(sim(lat, lon0, 420.0), 1.0)
    assert a.truth_pose() is None  # no origin yet
    a.update(msg("GPS_GLOBAL_ORIGIN", latitude=int(lat0 * 1e7), longitude=int(lon0 * 1e7), altitude=400_000), 1.0)
    a.update(sim(lat, lon0, 420.0), 2.0)
    truth = a.truth_pose()
    np.testing.assert_allclose(truth.position_ned_m, [30.0, 0.0, -20.0], atol=0.02)  # degE7 resolution ~1 cm
    np.testing.assert_allclose(truth.quaternion_wxyz, q)
    assert truth.t_s == 2.0 and truth.origin_source == "GPS_GLOBAL_ORIGIN"

    # HOME_POSITION as the fallback origin: home is at local (5, -3, -1).
    b = NavAssembler(CFG)
    b.update(msg("HOME_POSITION", latitude=int(lat0 * 1e7), longitude=int(lon0 * 1e7), altitude=400_000, x=5.0, y=-3.0, z=-1.0, q=[1, 0, 0, 0], approach_x=0, approach_y=0, approach_z=0), 1.0)
    b.update(sim(lat0, lon0, 400.0), 1.5)
    np.testing.assert_allclose(b.truth_pose().position_ned_m, [5.0, -3.0, -1.0], atol=0.02)
    assert b.truth_pose().origin_source == "HOME_POSITION"


def test_truth_takes_the_time_of_the_attitude_it_followed():
    """SIM_STATE has no timestamp: sent right after the attitude of the same simulator step, it takes
    that attitude's sample time (on the autopilot's clock, like the navigation state a frame is
    paired with), not its arrival, which a loaded process delays; without an attitude just before
    it, the arrival time."""
    a = NavAssembler(CFG, time_map=lambda t_boot: t_boot + 100.0)
    a.update(msg("GPS_GLOBAL_ORIGIN", latitude=470000000, longitude=80000000, altitude=400_000), 0.0)
    sim = msg("SIM_STATE", q1=1.0, q2=0.0, q3=0.0, q4=0.0, lat=47.0, lon=8.0, alt=410.0, vn=0.0, ve=0.0, vd=0.0,
              lat_int=470000000, lon_int=80000000)
    a.update(aq(5_000), 105.040)  # sampled at 105.000, read 40 ms late (a busy process)
    a.update(sim, 105.040)        # in the same read
    truth = a.truth_pose()
    assert truth.t_s == pytest.approx(105.0) and truth.time_source == "ATTITUDE_QUATERNION"
    a.update(sim, 105.040 + 0.5 * TRUTH_PAIR_WINDOW_S)  # read a moment later: the same step
    assert a.truth_pose().t_s == pytest.approx(105.0)
    a.update(sim, 105.040 + 2.0 * TRUTH_PAIR_WINDOW_S)  # no attitude just before: its arrival
    assert a.truth_pose().t_s == pytest.approx(105.040 + 2.0 * TRUTH_PAIR_WINDOW_S)
    assert a.truth_pose().time_source == "arrival"
    assert (a.truth_paired, a.truth_unpaired) == (2, 1)


def test_pymavlink_messages_are_accepted_as_well_as_dicts():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    mav = mavlink2.MAVLink(None, 1, 1)
    a = NavAssembler(CFG)
    m1 = mavlink2.MAVLink_local_position_ned_message(1000, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0)
    q = matrix_to_quat(quat_to_matrix(euler_to_quat(0, 0, 1.0)))
    m2 = mavlink2.MAVLink_attitude_quaternion_message(1000, *q, 0.0, 0.0, 0.0, [0, 0, 0, 0])
    for m in (m1, m2):  # through the wire and back, as the link sees them
        m.pack(mav)
    a.update(mav.decode(bytearray(m1.get_msgbuf())), 1.0)
    s = a.update(mav.decode(bytearray(m2.get_msgbuf())), 1.0)
    assert s is not None
    np.testing.assert_allclose(s.position_ned_m, [1, 2, -3])
    assert quat_to_euler(s.quaternion_wxyz)[2] == pytest.approx(1.0, abs=1e-6)
