"""PX4 flavour over real loopback sockets with a plain pymavlink client: OFFBOARD rules, covariance honesty."""

import math
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from drivers.sim.autopilot import Home
from drivers.sim.harness import MavClient, SimVehicleProcess
from drivers.sim.navigation_error import normalised_error_squared

ACCEPTED, REJECTED = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_TEMPORARILY_REJECTED
OFFBOARD = 6 << 16
HOLD = (4 << 16) | (3 << 24)


def px4(*extra: str) -> SimVehicleProcess:
    return SimVehicleProcess(["--flavour", "px4", "--tcp-listen", "127.0.0.1:0", "--seed", "5", *extra])


def connect(sim: SimVehicleProcess) -> MavClient:
    client = MavClient(f"tcp:127.0.0.1:{sim.endpoints['tcp']}")
    hb = client.wait_heartbeat()
    assert hb.autopilot == mav.MAV_AUTOPILOT_PX4 and hb.type == mav.MAV_TYPE_QUADROTOR
    return client


def wait_position(client: MavClient, timeout_s=5.0):
    assert client.recv("LOCAL_POSITION_NED", timeout_s) is not None, "no local position"


def set_offboard(client: MavClient):
    return client.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0).result


def chi2_quantile(p: float, dof: float) -> float:
    """Wilson-Hilferty chi-square quantile (no scipy); accurate to ~1 % here."""
    lo, hi = -10.0, 10.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p else (lo, mid)
    z = 0.5 * (lo + hi)
    return dof * (1 - 2 / (9 * dof) + z * math.sqrt(2 / (9 * dof))) ** 3


def test_offboard_is_refused_without_a_setpoint_stream_accepted_with_one_and_lost_without_it():
    with px4("--speedup", "5", "--origin-delay", "0.5") as sim:
        client = connect(sim)
        wait_position(client)  # streams are on by default, as on a PX4 onboard link
        assert client.recv("HEARTBEAT", 2).custom_mode == HOLD
        # no setpoints yet: refused, stays in Hold
        assert set_offboard(client) == REJECTED
        assert client.wait_statustext(lambda t: "Offboard is currently not possible" in t)
        assert client.recv("HEARTBEAT", 2).custom_mode == HOLD
        # stream setpoints (climb at 1 m/s), then switch: accepted; arm in offboard; it takes off
        for _ in range(10):
            client.velocity_setpoint(0.0, 0.0, -1.0)
            time.sleep(0.02)
        assert set_offboard(client) == ACCEPTED
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
        climbed = None
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and climbed is None:
            client.velocity_setpoint(0.0, 0.0, -1.0)
            m = client.latest("LOCAL_POSITION_NED")
            if m is not None and m.z < -3.0:
                climbed = m
            time.sleep(0.02)
        assert climbed is not None and abs(climbed.vz + 1.0) < 0.3
        hb = client.latest("HEARTBEAT") or client.recv("HEARTBEAT", 2)
        assert hb.custom_mode == OFFBOARD and hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        # the stream stops: after COM_OF_LOSS_T (1 s) the failsafe switches to Hold and says so
        t_stop = climbed.time_boot_ms / 1000
        hold = client.recv("HEARTBEAT", 3, lambda m: m.custom_mode == HOLD)
        assert hold is not None and hold.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert client.wait_statustext(lambda t: t.startswith("Failsafe activated: offboard"))
        later = client.recv("LOCAL_POSITION_NED", 3, lambda m: m.time_boot_ms / 1000 > t_stop + 4.0)
        assert abs(later.vz) < 0.3  # holding, no longer climbing
        assert sim.stop() == 0


def test_reported_covariance_is_honest_nees_within_chi_square_bounds():
    # the harsh model's fast-decorrelating errors (w = sigma_v / sigma_p = 2 /s horizontally, 1.25 /s
    # vertically, attitude tau 0.5 s) so that a 100 s run holds ~50 independent samples
    with px4("--speedup", "30", "--origin-delay", "0.5", "--set", "nav_error_model=harsh", "--set", "nav_pos_sigma_h_m=0.25", "--set", "nav_pos_sigma_v_m=0.4",
             "--set", "nav_vel_sigma_mps=0.5", "--set", "nav_att_tau_s=0.5", "--set", "gust_sigma_mps=1.0") as sim:
        client = connect(sim)
        # quiet the default streams, keep ODOMETRY and the truth at the same 10 Hz (same physics step)
        for msg_id in (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                       mav.MAVLINK_MSG_ID_ALTITUDE, mav.MAVLINK_MSG_ID_VFR_HUD, mav.MAVLINK_MSG_ID_GPS_RAW_INT):
            assert client.set_interval(msg_id, 0) == ACCEPTED  # 0 = back to the default rate (still on)
            assert client.set_interval(msg_id, -1) == ACCEPTED  # -1 = off
        assert client.set_interval(mav.MAVLINK_MSG_ID_ODOMETRY, 10) == ACCEPTED
        assert client.set_interval(mav.MAVLINK_MSG_ID_SIM_STATE, 10) == ACCEPTED
        wait_position(client)
        origin = None
        while origin is None:
            assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN).result == ACCEPTED
            origin = client.recv("GPS_GLOBAL_ORIGIN", 2)
        home = Home(origin.latitude * 1e-7, origin.longitude * 1e-7, origin.altitude * 1e-3)
        # PX4 reads COM_OF_LOSS_T from its parameters: give the sped-up client some slack
        client.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 5.0, mav.MAV_PARAM_TYPE_REAL32)
        assert client.recv("PARAM_VALUE", 2, lambda m: m.param_id == "COM_OF_LOSS_T").param_value == 5.0
        client.velocity_setpoint(0, 0, -2.0)
        assert set_offboard(client) == ACCEPTED
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED

        errors, covs, last_odo = [], [], None
        t0 = t = None
        deadline = time.monotonic() + 20.0  # 100 s simulated take ~4 s on an idle machine
        while time.monotonic() < deadline:
            m = client.recv(["ODOMETRY", "SIM_STATE"], 0.05)
            if m is None:
                continue
            if m.get_type() == "ODOMETRY":
                last_odo = m
                t = m.time_usec * 1e-6
                t0 = t if t0 is None else t0
                if t - t0 > 100.0:
                    break
                # fly circles at 4 m/s, 10 m up, yawing with the track (tilt and heading both vary)
                a = 0.25 * (t - t0)
                climb = -2.0 if m.z > -10 else 0.0
                client.velocity_setpoint(4 * math.cos(a), 4 * math.sin(a), climb, yaw=a + math.pi / 2)
                continue
            if last_odo is None or m.get_seq() != (last_odo.get_seq() + 1) % 256:
                continue  # pair ODOMETRY with the SIM_STATE sent right after it (same step)
            o, last_odo = last_odo, None
            n, e, d = home.global_to_ned(m.lat_int * 1e-7, m.lon_int * 1e-7, m.alt)
            q_true = np.array([m.q1, m.q2, m.q3, m.q4])
            R_true, R_est = quat_to_R(q_true), quat_to_R(np.array(o.q))
            dR = R_true @ R_est.T  # = Exp(e_att)
            e_att = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
            err = np.r_[o.x - n, o.y - e, o.z - d, o.vx - m.vn, o.vy - m.ve, o.vz - m.vd, -e_att]
            pc, vc = o.pose_covariance, o.velocity_covariance
            assert all(math.isnan(pc[i]) for i in range(21) if i not in (0, 6, 11, 15, 18, 20))
            covs.append(np.diag([pc[0], pc[6], pc[11], vc[0], vc[6], vc[11], pc[15], pc[18], pc[20]]))
            errors.append(err)
        assert sim.stop() == 0

    errors, covs = np.array(errors), np.array(covs)
    span = t - t0
    assert len(errors) > 5 * span and span > 60.0, (len(errors), span)
    nees = normalised_error_squared(errors, covs)
    blocks = {name: normalised_error_squared(errors[:, s], covs[:, s, s]) for name, s in
              (("position", slice(0, 3)), ("velocity", slice(3, 6)), ("attitude", slice(6, 9)))}
    # consecutive samples are correlated: count one independent sample per 2 s (>= 2 time constants)
    n_eff = span / 2.0
    lo, hi = chi2_quantile(0.001, 9 * n_eff) / n_eff, chi2_quantile(0.999, 9 * n_eff) / n_eff
    inside = np.mean((nees > chi2_quantile(0.025, 9)) & (nees < chi2_quantile(0.975, 9)))
    print(f"\nNEES over {len(nees)} samples: mean {nees.mean():.2f} (9 dof, bounds {lo:.2f}..{hi:.2f}), "
          f"{100 * inside:.1f} % inside the 95 % interval; " +
          ", ".join(f"{k} {v.mean():.2f}" for k, v in blocks.items()) + " (3 dof each)")
    assert lo < nees.mean() < hi
    assert 0.88 < inside < 0.99
    b_lo, b_hi = chi2_quantile(0.001, 3 * n_eff) / n_eff, chi2_quantile(0.999, 3 * n_eff) / n_eff
    for name, v in blocks.items():
        assert b_lo < v.mean() < b_hi, (name, v.mean())


def quat_to_R(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_px4_streams_by_default_and_estimator_status_matches_odometry():
    with px4("--speedup", "5", "--origin-delay", "0.5") as sim:
        client = connect(sim)
        odo = client.recv("ODOMETRY", 3)
        est = client.recv("ESTIMATOR_STATUS", 3, lambda m: m.pos_horiz_accuracy == m.pos_horiz_accuracy)
        alt = client.recv("ALTITUDE", 2)
        ext = client.recv("EXTENDED_SYS_STATE", 2)
        assert odo is not None and est is not None and alt is not None
        assert ext.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
        assert math.isclose(est.pos_horiz_accuracy ** 2, odo.pose_covariance[0], rel_tol=1e-5)
        assert math.isclose(est.pos_vert_accuracy ** 2, odo.pose_covariance[11], rel_tol=1e-5)
        assert est.flags & mav.ESTIMATOR_POS_HORIZ_ABS and max(est.vel_ratio, est.pos_horiz_ratio) < 1.0
        # REQUEST_DATA_STREAM is deprecated in PX4 and ignored; SET_MESSAGE_INTERVAL for HEARTBEAT refused
        assert client.set_interval(mav.MAVLINK_MSG_ID_HEARTBEAT, 5) == mav.MAV_RESULT_FAILED
        # PX4 parameters: integers go bytewise (MAV_SYS_ID = 1 as int32 bits)
        client.mav.param_request_read_send(1, 1, b"MAV_SYS_ID", -1)
        p = client.recv("PARAM_VALUE", 2, lambda m: m.param_id == "MAV_SYS_ID")
        assert p.param_type == mav.MAV_PARAM_TYPE_INT32
        assert np.frombuffer(np.float32(p.param_value).tobytes(), np.int32)[0] == 1
        assert sim.stop() == 0
