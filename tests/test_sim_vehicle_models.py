"""The simulated vehicle without sockets: dynamics, navigation error, stream schedule, determinism."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import SimConfig, replace
from companion.method.geometry import matrix_to_euler
from drivers.sim.ardupilot import GUIDED, ArduPilotCopter
from drivers.sim.dynamics import GRAVITY_MPS2, MultirotorLimits, PointMassMultirotor, Setpoint, sqrt_controller
from drivers.sim.mavlink_endpoint import StreamSchedule
from drivers.sim.navigation_error import GaussMarkovNavError, NavErrorSpec, normalised_error_squared
from drivers.sim.px4 import PX4Multicopter

NAN = float("nan")
DT = 1.0 / 400.0


def chi2_quantile(p: float, dof: float) -> float:
    """Wilson-Hilferty approximation of the chi-square quantile (good to ~1 % for dof >= 3)."""
    # inverse standard normal by bisection on erf (no scipy)
    lo, hi = -10.0, 10.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p:
            lo = mid
        else:
            hi = mid
    z = 0.5 * (lo + hi)
    return dof * (1 - 2 / (9 * dof) + z * math.sqrt(2 / (9 * dof))) ** 3


def hover(altitude=10.0, **limits) -> PointMassMultirotor:
    m = PointMassMultirotor(MultirotorLimits(**limits))
    sp = Setpoint(position_ned_m=(NAN, NAN, -altitude))
    for _ in range(int(12 / DT)):
        m.step(DT, sp)
    assert not m.landed and abs(m.p[2] + altitude) < 0.05
    return m


# ---- dynamics -------------------------------------------------------------------------------------


def test_velocity_setpoint_is_followed_and_the_reference_respects_the_acceleration_limits():
    m = hover()
    sp = Setpoint(velocity_ned_mps=(6.0, -2.0, NAN), position_ned_m=(NAN, NAN, -10.0))
    ref_acc, truth_acc, errors = [], [], []
    for k in range(int(10 / DT)):
        m.step(DT, sp)
        ref_acc.append(math.hypot(m.a_d[0], m.a_d[1]))
        truth_acc.append(math.hypot(m.accel[0], m.accel[1]))
        if k * DT > 5.0:
            errors.append(math.dist(m.v[:2], (6.0, -2.0)))
    assert max(ref_acc) <= 3.0 + 1e-9  # the shaped reference never asks for more than accel_h
    assert max(truth_acc) <= GRAVITY_MPS2 * math.tan(math.radians(35)) + 1.0  # tilt limit (+ drag)
    # the position-stabilised velocity loop catches up the lag of the drag with a small overshoot
    assert max(errors) < 0.15, f"velocity error after 5 s {max(errors):.3f} m/s"
    assert errors[-1] < 0.05, f"velocity error after 10 s {errors[-1]:.3f} m/s"
    assert abs(m.p[2] + 10.0) < 0.1


def test_acceleration_tilts_the_nose_down_by_atan_a_over_g():
    m = hover()
    sp = Setpoint(velocity_ned_mps=(8.0, 0.0, NAN), position_ned_m=(NAN, NAN, -10.0))
    pitches, accels, speeds = [], [], []
    for _ in range(int(1.5 / DT)):
        m.step(DT, sp)
        pitches.append(float(matrix_to_euler(m.rotation_body_to_ned())[1]))
        accels.append(m.accel[0])
        speeds.append(m.v[0])
    # mid-acceleration the vehicle pitches forward (nose down, negative pitch) ~ atan(a/g),
    # where the thrust's horizontal part also overcomes the drag (0.3 / s * v)
    i = len(pitches) // 2
    expected = -math.atan2(accels[i] + 0.3 * speeds[i], GRAVITY_MPS2)
    assert pitches[i] < -0.1
    assert abs(pitches[i] - expected) < math.radians(3)


def test_position_hold_against_wind_leans_into_it_and_does_not_drift():
    m = hover()
    hold = list(m.p)
    sp = Setpoint.hold(hold)
    for _ in range(int(30 / DT)):
        m.step(DT, sp, wind_ned_mps=(0.0, 5.0, 0.0))
    assert math.dist(m.p, hold) < 0.1  # the integrator takes out the steady wind
    assert m.thrust[1] < -0.5  # thrust points west, into the wind blowing east
    roll = float(matrix_to_euler(m.rotation_body_to_ned())[0])
    assert roll < -0.05  # leaning left (west) with the nose north


def test_takeoff_climb_respects_the_climb_limit_and_landing_ends_on_the_ground():
    m = PointMassMultirotor(MultirotorLimits(climb_mps=2.0))
    assert m.landed
    sp = Setpoint(position_ned_m=(NAN, NAN, -5.0))
    climb = []
    for _ in range(int(8 / DT)):
        m.step(DT, sp)
        climb.append(-m.v[2])
    assert max(climb) < 2.0 + 0.1 and not m.landed and abs(m.p[2] + 5) < 0.1
    land = Setpoint(velocity_ned_mps=(NAN, NAN, 1.0), position_ned_m=(0.0, 0.0, NAN))
    for _ in range(int(10 / DT)):
        m.step(DT, land)
    assert m.landed and m.p[2] == 0.0 and m.v == [0.0, 0.0, 0.0]


def test_disarmed_on_the_ground_nothing_moves_and_disarmed_in_the_air_it_falls():
    m = PointMassMultirotor()
    for _ in range(400):
        m.step(DT, Setpoint(velocity_ned_mps=(5.0, 0.0, -3.0)), armed=False)
    assert m.p == [0.0, 0.0, 0.0] and m.landed
    m = hover(5.0)
    for _ in range(400):
        m.step(DT, Setpoint.hold(m.p), armed=False)
    assert m.v[2] > 5.0  # free fall (less drag) after one second


def test_yaw_follows_velocity_when_asked_and_holds_otherwise():
    m = hover()
    for _ in range(int(6 / DT)):
        m.step(DT, Setpoint(velocity_ned_mps=(0.0, 4.0, 0.0), yaw_follows_velocity=True))
    assert abs(m.yaw - math.pi / 2) < 0.02
    yaw = m.yaw
    for _ in range(int(3 / DT)):
        m.step(DT, Setpoint(velocity_ned_mps=(-4.0, 0.0, 0.0)))
    assert m.yaw == yaw


@settings(deadline=None, max_examples=60)
@given(e=st.floats(-500, 500), k=st.floats(0.1, 5), a=st.floats(0.2, 10))
def test_sqrt_controller_is_odd_monotone_and_never_demands_more_than_the_braking_speed(e, k, a):
    v = sqrt_controller(e, k, a)
    assert sqrt_controller(-e, k, a) == pytest.approx(-v)
    assert abs(v) <= k * abs(e) + 1e-9  # never faster than the linear law
    assert abs(v) <= math.sqrt(2 * a * abs(e)) + 1e-9  # can stop within the remaining distance
    assert sqrt_controller(e + 1e-3, k, a) >= v - 1e-12  # monotone


# ---- navigation error ------------------------------------------------------------------------------


SPEC = NavErrorSpec(sigma=(0.5, 0.5, 0.8, 0.25, 0.25, 0.4, 0.01, 0.01, 0.03), att_tau_s=(1.0, 1.0, 1.0))


def test_navigation_error_has_the_stationary_sigmas_correlation_times_and_consistent_velocity():
    nav = GaussMarkovNavError(SPEC, np.random.default_rng(4))
    dt = 0.02
    samples = []
    for _ in range(60000):
        nav.step(dt)
        samples.append(nav.e.copy())
    e = np.array(samples)
    ratio = e.std(axis=0) / np.array(SPEC.sigma)
    assert np.all(np.abs(ratio - 1) < 0.12), ratio
    # position/velocity: critically damped, w = sigma_v / sigma_p = 0.5 /s -> R(1/w) = 2/e
    lag = int(round(2.0 / dt))
    r = np.mean(e[:-lag, 0] * e[lag:, 0]) / np.var(e[:, 0])
    assert abs(r - 2 / math.e) < 0.12
    # the velocity error is the rate of the position error (and uncorrelated with it at one instant)
    rate = np.diff(e[:, 0]) / dt
    assert np.corrcoef(rate, e[1:, 3])[0, 1] > 0.99
    assert abs(np.corrcoef(e[:, 0], e[:, 3])[0, 1]) < 0.05
    # attitude: critically damped, w = 2 / tau = 2 /s -> R(1/w) = 2/e, R(tau) = 3/e^2
    for lag_s, expected in ((0.5, 2 / math.e), (1.0, 3 / math.e**2)):
        lag = int(round(lag_s / dt))
        r = np.mean(e[:-lag, 6:] * e[lag:, 6:], axis=0) / np.var(e[:, 6:], axis=0)
        assert np.all(np.abs(r - expected) < 0.12), (lag_s, r)


def test_attitude_error_is_smooth_from_frame_to_frame():
    """A real EKF's attitude error wanders over seconds; between two camera frames it moves by about
    sigma * w * dt, not by the random-walk step sigma * sqrt(2 dt / tau) of a first-order process
    (0.23 deg of yaw at 15 Hz for 2 deg and 10 s)."""
    sigma_yaw, tau, dt = math.radians(2.0), 10.0, 1.0 / 15.0
    spec = NavErrorSpec(sigma=(0.5, 0.5, 0.8, 0.1, 0.1, 0.1, math.radians(0.5), math.radians(0.5), sigma_yaw),
                        att_tau_s=(tau,) * 3)
    nav = GaussMarkovNavError(spec, np.random.default_rng(11))
    yaw = []
    for _ in range(30000):
        nav.step(dt)
        yaw.append(nav.e[8])
    yaw = np.array(yaw)
    assert abs(yaw.std() / sigma_yaw - 1) < 0.2  # same stationary sigma (the series is correlated: loose)
    step_rms = np.sqrt(np.mean(np.diff(yaw) ** 2))
    first_order_step = sigma_yaw * math.sqrt(2 * dt / tau)
    assert step_rms < 0.2 * first_order_step
    assert step_rms == pytest.approx(sigma_yaw * (2 / tau) * dt, rel=0.25)


def test_nees_of_the_error_against_the_reported_covariance_is_chi_square_9():
    # many independent vehicles, one sample each: NEES ~ chi2(9) exactly
    nees = []
    for seed in range(2000):
        nav = GaussMarkovNavError(SPEC, np.random.default_rng(seed))
        nav.step(0.37)
        nees.append(normalised_error_squared(nav.e, SPEC.covariance))
    nees = np.array(nees)
    assert chi2_quantile(0.005, 9 * 2000) / 2000 < nees.mean() < chi2_quantile(0.995, 9 * 2000) / 2000
    inside = np.mean((nees > chi2_quantile(0.025, 9)) & (nees < chi2_quantile(0.975, 9)))
    assert 0.93 < inside < 0.97


def test_nav_error_spec_rejects_bad_values():
    with pytest.raises(ValueError, match="sigma\\[2\\]"):
        NavErrorSpec(sigma=(0.5, 0.5, -1.0) + (0.1,) * 6)
    with pytest.raises(ValueError, match="att_tau_s\\[0\\]"):
        NavErrorSpec(sigma=(0.5,) * 9, att_tau_s=(0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="9 sigmas"):
        NavErrorSpec(sigma=(0.5,) * 3)
    with pytest.raises(ValueError, match="rate of the position error"):
        NavErrorSpec(sigma=(0.0, 0.5, 0.5) + (0.1,) * 6)


# ---- stream schedule ---------------------------------------------------------------------------------


def test_schedule_sends_at_the_requested_rate_on_a_shared_grid():
    s = StreamSchedule()
    s.set_interval(30, 0.1, now_s=0.013)
    s.set_interval(108, 0.1, now_s=0.047)
    s.set_interval(33, 0.25, now_s=0.0)
    counts = {30: 0, 108: 0, 33: 0}
    together = 0
    for k in range(1, 4001):
        due = s.pop_due(k / 400.0)
        for m in due:
            counts[m] += 1
        together += 30 in due and 108 in due
    assert counts[30] == 100 and counts[108] == 100 and counts[33] == 40
    assert together == 100  # same rate -> same physics step, so a client can pair them
    s.set_interval(30, None, now_s=10.0)
    assert all(30 not in s.pop_due(10.0 + k / 400) for k in range(1, 800))


def test_schedule_rejects_a_non_finite_interval():
    with pytest.raises(ValueError, match="finite"):
        StreamSchedule().set_interval(30, math.inf, 0.0)


# ---- autopilot, in process -----------------------------------------------------------------------------


class _Link:
    def __init__(self):
        self.name = "test"
        self.schedule = StreamSchedule()


def _msg(m, src=(255, 190)):
    """Give a constructed message a sender, as a parsed one would have."""
    enc = mav.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    return mav.MAVLink(None).parse_buffer(m.pack(enc))[0]


def _cmd(ap, link, command, *params):
    p = list(params) + [0.0] * (7 - len(params))
    ap.outbox.clear()
    ap.handle(_msg(mav.MAVLink_command_long_message(1, 1, command, 0, *p)), link)
    acks = [m for _, m in ap.outbox if m.get_type() == "COMMAND_ACK"]
    return acks[-1].result


def _fly_guided(ap, link, steps_s=20.0):
    assert _cmd(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert _cmd(ap, link, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 8) == mav.MAV_RESULT_ACCEPTED
    ap.run_for(6.0)
    traj = []
    for k in range(int(steps_s * 10)):
        sp = mav.MAVLink_set_position_target_local_ned_message(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 3527, 0, 0, 0,
                                                                3 * math.cos(k / 30), 3 * math.sin(k / 30), 0, 0, 0, 0, 0, 0)
        ap.handle(_msg(sp), link)
        ap.run_for(0.1)
        traj.append((list(ap.vehicle.p), ap.nav.e.copy()))
    return traj


def test_same_seed_and_commands_give_the_same_flight_and_another_seed_another_error():
    sim = replace(SimConfig(), origin_delay_s=0.5, gust_sigma_mps=1.0)
    runs = []
    for seed in (5, 5, 6):
        ap = ArduPilotCopter(sim, seed=seed)
        ap.run_for(1.0)
        runs.append(_fly_guided(ap, _Link(), 5.0))
    assert len(runs[0]) == len(runs[1]) == 50
    assert all(p0 == p1 and np.array_equal(e0, e1) for (p0, e0), (p1, e1) in zip(runs[0], runs[1]))
    assert not all(np.array_equal(e0, e2) for (_, e0), (_, e2) in zip(runs[0], runs[2]))


def test_ardupilot_gps_accuracies_cover_the_position_error_and_test_ratios_stay_small():
    # the harsh model with w = 1 /s: the error decorrelates in seconds, so 300 s of samples average well
    sim = replace(SimConfig(), origin_delay_s=0.5, nav_error_model="harsh", nav_vel_sigma_mps=0.5)
    ap = ArduPilotCopter(sim, seed=11)
    ap.run_for(1.0)
    nees, ratios = [], []
    for _ in range(1500):
        ap.run_for(0.2)
        gps = ap.build(mav.MAVLINK_MSG_ID_GPS_RAW_INT)
        pos = ap.build(mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
        est = ap.estimate()["p"]
        err = est - np.array(ap.vehicle.p)
        P = np.diag([(gps.h_acc / 1000) ** 2] * 2 + [(gps.v_acc / 1000) ** 2])
        nees.append(normalised_error_squared(err, P))
        ekf = ap.build(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT)
        ratios.append(max(ekf.velocity_variance, ekf.pos_horiz_variance, ekf.pos_vert_variance))
        assert ekf.flags == 0x033F and gps.fix_type == 3
        assert abs(pos.lat * 1e-7 - ap.home.ned_to_global(*est)[0]) < 2e-7
    mean = float(np.mean(nees))
    # GPS accuracy includes the receiver's white noise, so it is honest and slightly conservative
    assert 1.8 < mean < 3.3, mean
    assert np.quantile(ratios, 0.95) < 0.5


def test_ardupilot_refuses_guided_and_arming_without_a_position_estimate():
    """As a real Copter 4.6 SITL: disarmed, GUIDED is accepted before GPS; arming in it is not, and
    armed (STABILIZE) the switch to GUIDED is refused."""
    ap = ArduPilotCopter(replace(SimConfig(), origin_delay_s=30.0))
    link = _Link()
    ap.run_for(1.0)
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED  # STABILIZE needs no GPS
    assert _cmd(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_FAILED   # armed: requires position
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_ACCEPTED
    assert _cmd(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED  # disarmed: any mode
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_FAILED   # PreArm: Need Position Estimate
    assert ap.build(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED) is None
    assert ap.build(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT).flags == 0x00A7


def test_ardupilot_origin_comes_before_the_use_of_gps():
    """Real 4.6 SITL order: origin (GPS_GLOBAL_ORIGIN and HOME_POSITION to every link) at 20 s, EKF
    using GPS at 41 s; in between no LOCAL_POSITION_NED, EKF flags 0x00A7, no arming in GUIDED, and
    REQUEST_MESSAGE(HOME_POSITION) before the origin is ACCEPTED with nothing sent."""
    ap = ArduPilotCopter(replace(SimConfig(), origin_delay_s=2.0, gps_delay_s=3.0))
    link = _Link()
    ap.run_for(1.0)
    assert _cmd(ap, link, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    assert ap.build(mav.MAVLINK_MSG_ID_HOME_POSITION) is None and ap.build(mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) is None
    ap.run_for(1.5)  # t = 2.5 s: origin, no GPS use yet
    assert ap.origin_set and not ap.position_valid
    assert ap.build(mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) is not None and ap.build(mav.MAVLINK_MSG_ID_HOME_POSITION) is not None
    assert ap.build(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED) is None
    assert ap.build(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT).flags == 0x00A7
    assert _cmd(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_FAILED
    ap.run_for(3.0)  # t = 5.5 s: using GPS
    assert ap.position_valid
    assert ap.build(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED) is not None
    assert ap.build(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT).flags == 0x033F
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED


def test_malformed_setpoints_stop_guided_and_are_counted_never_raised():
    sim = replace(SimConfig(), origin_delay_s=0.2)
    ap = ArduPilotCopter(sim)
    link = _Link()
    ap.run_for(0.5)
    traj = _fly_guided(ap, link, 2.0)
    assert math.hypot(*ap.vehicle.v[:2]) > 2.0 and traj
    bad = mav.MAVLink_set_position_target_local_ned_message(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 3527, 0, 0, 0,
                                                             float("nan"), 1e9, 0, 0, 0, 0, 0, 0)
    ap.handle(_msg(bad), link)
    ap.run_for(5.0)
    assert math.hypot(*ap.vehicle.v[:2]) < 0.3  # invalid input -> stop (ModeGuided::init)
    wrong_frame = mav.MAVLink_set_position_target_local_ned_message(0, 1, 1, mav.MAV_FRAME_GLOBAL, 3527, 0, 0, 0,
                                                                     3, 0, 0, 0, 0, 0, 0, 0)
    ap.handle(_msg(wrong_frame), link)
    ap.run_for(3.0)
    assert math.hypot(*ap.vehicle.v[:2]) < 0.3


def test_px4_odometry_reports_the_injected_variances_and_nan_elsewhere():
    sim = replace(SimConfig(), flavour="px4", origin_delay_s=0.1)
    ap = PX4Multicopter(sim)
    ap.run_for(0.5)
    odo = ap.build(mav.MAVLINK_MSG_ID_ODOMETRY)
    sig = ap.nav.spec.sigma
    diag = {0: sig[0], 6: sig[1], 11: sig[2], 15: sig[6], 18: sig[7], 20: sig[8]}
    for i, v in enumerate(odo.pose_covariance):
        assert (v == pytest.approx(diag[i] ** 2)) if i in diag else math.isnan(v)
    for i, v in enumerate(odo.velocity_covariance):
        assert (v == pytest.approx(sig[3 + (0, 6, 11).index(i)] ** 2)) if i in (0, 6, 11) else math.isnan(v)
    assert odo.frame_id == mav.MAV_FRAME_LOCAL_NED and odo.child_frame_id == mav.MAV_FRAME_LOCAL_NED


def _px4_offboard(ap, link):
    sp = mav.MAVLink_set_position_target_local_ned_message(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 0b1001_1111_1000,
                                                            10.0, 5.0, -8.0, 0, 0, 0, 0, 0, 0, 1.0, 0)
    for _ in range(5):
        ap.handle(_msg(sp), link)
        ap.run_for(0.1)
    assert _cmd(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mav.MAV_RESULT_ACCEPTED
    assert _cmd(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    for _ in range(200):
        ap.handle(_msg(sp), link)
        ap.run_for(0.1)


def test_px4_offboard_position_setpoint_with_yaw_is_reached_in_the_reported_frame():
    ap = PX4Multicopter(replace(SimConfig(), flavour="px4", origin_delay_s=0.2))
    link = _Link()
    ap.run_for(0.5)
    _px4_offboard(ap, link)  # position only (type_mask ignores velocity, acceleration, yaw rate)
    est = ap.estimate()
    assert np.linalg.norm(est["p"] - [10.0, 5.0, -8.0]) < 0.2  # the controller flies its estimate
    assert abs(ap.vehicle.yaw - 1.0) < 0.02
    truth_error = np.linalg.norm(np.array(ap.vehicle.p) - [10.0, 5.0, -8.0])
    assert truth_error < 5 * max(ap.nav.spec.sigma[:3])  # and misses in truth by the navigation error


def test_ardupilot_body_frame_velocity_and_global_position_targets():
    ap = ArduPilotCopter(replace(SimConfig(), origin_delay_s=0.2))
    link = _Link()
    ap.run_for(0.5)
    _fly_guided(ap, link, 0.1)
    # turn to face east, then "forward" in MAV_FRAME_BODY_NED is east
    assert _cmd(ap, link, mav.MAV_CMD_CONDITION_YAW, 90, 30, 1, 0) == mav.MAV_RESULT_ACCEPTED
    ap.run_for(4.0)
    assert abs(ap.vehicle.yaw - math.pi / 2) < 0.05
    fwd = mav.MAVLink_set_position_target_local_ned_message(0, 1, 1, mav.MAV_FRAME_BODY_NED, 0b0000_1111_1100_0111,
                                                             0, 0, 0, 3.0, 0, 0, 0, 0, 0, 0, 0)
    for _ in range(40):
        ap.handle(_msg(fwd), link)
        ap.run_for(0.1)
    v = ap.estimate()["v"]
    assert abs(v[1] - 3.0) < 0.2 and abs(v[0]) < 0.2, v
    # SET_POSITION_TARGET_GLOBAL_INT, relative altitude: fly to a point 20 m north of home, 12 m up
    lat, lon, _ = ap.home.ned_to_global(20.0, 0.0, 0.0)
    tgt = mav.MAVLink_set_position_target_global_int_message(0, 1, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                              0b0000_1111_1111_1000, int(lat * 1e7), int(lon * 1e7), 12.0,
                                                              0, 0, 0, 0, 0, 0, 0, 0)
    ap.handle(_msg(tgt), link)
    ap.run_for(25.0)
    assert np.linalg.norm(ap.estimate()["p"] - [20.0, 0.0, -12.0]) < 0.3


def test_ardupilot_rtl_climbs_returns_home_lands_and_disarms():
    ap = ArduPilotCopter(replace(SimConfig(), origin_delay_s=0.2))
    link = _Link()
    ap.run_for(0.5)
    _fly_guided(ap, link, 10.0)  # circles at 3 m/s, 8 m up, some tens of metres from home
    assert math.hypot(*ap.vehicle.p[:2]) > 5.0
    assert _cmd(ap, link, mav.MAV_CMD_NAV_RETURN_TO_LAUNCH) == mav.MAV_RESULT_ACCEPTED
    assert ap.build(mav.MAVLINK_MSG_ID_HEARTBEAT).custom_mode == 6
    top = 0.0
    for _ in range(900):
        ap.run_for(0.1)
        top = max(top, -ap.vehicle.p[2])
        if not ap.armed:
            break
    assert top > 14.5  # climbed to RTL_ALT (15 m) first
    assert not ap.armed and ap.landed
    assert math.hypot(*ap.estimate()["p"][:2]) < 1.0  # landed at home (in the estimate's frame)
