"""NavBuffer: interpolation at frame times (lerp, slerp), refusals with reasons, bounded memory."""

import math
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.method.geometry import euler_to_quat, quat_to_matrix
from companion.method.messages import NavState
from companion.method.navigation.buffer import NavBuffer, quat_slerp


def nav(t, p=(0, 0, 0), v=(0, 0, 0), yaw=0.0, cov=1.0, source="floors"):
    return NavState(t, np.asarray(p, float), np.asarray(v, float), euler_to_quat(0.0, 0.0, yaw), np.eye(9) * cov, source)


def angle_between(q0, q1):
    R = quat_to_matrix(q0).T @ quat_to_matrix(q1)
    return math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))


def test_linear_motion_is_interpolated_exactly():
    buf = NavBuffer(horizon_s=5.0)
    v = np.array([3.0, -1.0, 0.5])
    for i in range(11):
        t = 10.0 + 0.02 * i
        buf.push(nav(t, p=v * t, v=v))
    got = buf.at(10.0731)
    assert got is not None
    np.testing.assert_allclose(got.position_ned_m, v * 10.0731, atol=1e-12)
    np.testing.assert_allclose(got.velocity_ned_mps, v)
    assert got.t_s == 10.0731


def test_attitude_is_slerped_and_covariance_is_a_convex_combination():
    buf = NavBuffer()
    buf.push(nav(0.0, yaw=0.0, cov=1.0, source="A"))
    buf.push(nav(0.1, yaw=math.radians(40), cov=3.0, source="B"))
    got = buf.at(0.025)
    assert angle_between(got.quaternion_wxyz, euler_to_quat(0, 0, math.radians(10))) < 1e-9
    np.testing.assert_allclose(got.covariance, np.eye(9) * 1.5)
    assert got.covariance_source == "A"
    assert buf.at(0.09).covariance_source == "B"


def test_exact_sample_time_returns_the_sample():
    buf = NavBuffer()
    a, b = nav(1.0, p=(1, 2, 3)), nav(1.1, p=(2, 2, 3))
    buf.push(a)
    buf.push(b)
    assert buf.at(1.0) is a and buf.at(1.1) is b


@settings(deadline=None, max_examples=60)
@given(
    e0=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
    e1=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
    alpha=st.floats(0.0, 1.0),
    flip=st.booleans(),
)
def test_slerp_moves_along_the_shortest_arc_at_constant_rate(e0, e1, alpha, flip):
    q0 = euler_to_quat(*e0)
    q1 = euler_to_quat(*e1) * (-1.0 if flip else 1.0)  # q and -q are the same rotation
    q = quat_slerp(q0, q1, alpha)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    total = angle_between(q0, q1)
    assert total <= math.pi + 1e-9
    assert angle_between(q0, q) == pytest.approx(alpha * total, abs=2e-6)
    assert angle_between(q, q1) == pytest.approx((1 - alpha) * total, abs=2e-6)


def test_refusals_say_why():
    buf = NavBuffer(horizon_s=5.0, max_gap_s=0.2, extrapolate_s=0.05)
    r = buf.lookup(1.0)
    assert r.nav is None and "no navigation" in r.reason
    buf.push(nav(1.0))
    buf.push(nav(1.1))
    buf.push(nav(2.0))  # 0.9 s gap
    r = buf.lookup(0.5)
    assert r.nav is None and "before the oldest" in r.reason
    r = buf.lookup(1.5)
    assert r.nav is None and "gap" in r.reason
    r = buf.lookup(2.2)
    assert r.nav is None and "after the newest" in r.reason
    assert not buf.lookup(float("nan"))
    assert buf.lookup(1.05)  # inside the history


def test_short_extrapolation_uses_the_velocity():
    buf = NavBuffer(extrapolate_s=0.05)
    buf.push(nav(1.0, p=(0, 0, -10), v=(2, 0, -1)))
    buf.push(nav(1.1, p=(0.2, 0, -10.1), v=(2, 0, -1)))
    got = buf.at(1.14)
    np.testing.assert_allclose(got.position_ned_m, [0.28, 0, -10.14], atol=1e-12)
    assert buf.at(1.16) is None


def test_out_of_order_rejected_equal_time_replaces_nonfinite_rejected():
    buf = NavBuffer()
    assert buf.push(nav(1.0, p=(1, 0, 0)))
    assert buf.push(nav(1.0, p=(2, 0, 0)))  # same instant: the later assembly wins
    assert buf.latest().position_ned_m[0] == 2
    assert not buf.push(nav(0.9))
    assert not buf.push(nav(2.0, p=(np.nan, 0, 0)))
    assert len(buf) == 1
    assert buf.rejected == {"older than the newest sample": 1, "non-finite state": 1}


def test_memory_is_bounded_by_horizon_and_cap():
    buf = NavBuffer(horizon_s=1.0)
    for i in range(20000):
        buf.push(nav(i * 0.01))
    assert len(buf) <= 102
    assert buf.oldest().t_s <= buf.latest().t_s - 1.0 + 1e-9  # the horizon is still fully covered
    assert buf.at(buf.latest().t_s - 0.999) is not None
    capped = NavBuffer(horizon_s=100.0, max_samples=50)
    for i in range(5000):
        capped.push(nav(i * 0.001))
    assert len(capped) == 50


def test_age_and_clear():
    buf = NavBuffer()
    assert buf.age(5.0) == math.inf
    buf.push(nav(4.0))
    assert buf.age(5.0) == pytest.approx(1.0)
    buf.clear()
    assert buf.latest() is None and len(buf) == 0


def test_concurrent_reader_thread_sees_consistent_states():
    buf = NavBuffer(horizon_s=0.5)
    v = np.array([1.0, 0.0, 0.0])
    errors = []
    stop = threading.Event()

    def reader():
        while not stop.is_set():
            latest = buf.latest()
            if latest is None:
                continue
            got = buf.at(latest.t_s - 0.0123)
            if got is not None and abs(got.position_ned_m[0] - got.t_s) > 1e-9:
                errors.append(got.t_s)

    th = threading.Thread(target=reader)
    th.start()
    try:
        for i in range(20000):
            t = i * 0.001
            buf.push(nav(t, p=v * t, v=v))
    finally:
        stop.set()
        th.join(5)
    assert not errors


@settings(max_examples=30, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(0.0, 0.045))
def test_extrapolation_continues_a_constant_turn(yaw_rate, ahead):
    """Past the newest sample the attitude goes on at the rate of the last samples (>= 10 ms apart),
    as a constant turn does, instead of being held; position at the newest velocity. With one
    sample only, it is held."""
    buf = NavBuffer(extrapolate_s=0.05)
    for k in range(6):  # 50 Hz, turning at yaw_rate
        t = 0.02 * k
        buf.push(nav(t, p=(6.0 * t, 0, -15), v=(6.0, 0, 0), yaw=yaw_rate * t))
    t = 0.1 + ahead
    got = buf.lookup(t).nav
    expected = quat_to_matrix(euler_to_quat(0.0, 0.0, yaw_rate * t))
    np.testing.assert_allclose(quat_to_matrix(got.quaternion_wxyz), expected, atol=1e-9)
    np.testing.assert_allclose(got.position_ned_m, [6.0 * t, 0, -15], atol=1e-12)
    one = NavBuffer(extrapolate_s=0.05)
    one.push(nav(0.0, yaw=0.3))
    np.testing.assert_allclose(one.lookup(0.03).nav.quaternion_wxyz, euler_to_quat(0.0, 0.0, 0.3), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3), st.floats(0.0, 3.0))
def test_so3_log_inverts_so3_exp(axis, angle):
    from companion.method.geometry import so3_exp
    from companion.method.navigation.buffer import so3_log

    a = np.asarray(axis)
    if np.linalg.norm(a) < 1e-3:
        a = np.array([0.0, 0.0, 1.0])
    rotvec = a / np.linalg.norm(a) * angle
    np.testing.assert_allclose(so3_log(so3_exp(rotvec)), rotvec, atol=1e-7)
