"""ArduPilot flavour over real loopback sockets, driven by a plain pymavlink client (not the service)."""

import math
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from drivers.sim.autopilot import Home
from drivers.sim.harness import MavClient, SimVehicleProcess

GUIDED = 4
ACCEPTED, DENIED, FAILED = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_DENIED, mav.MAV_RESULT_FAILED


def ardupilot(client: MavClient, *extra: str) -> SimVehicleProcess:
    return SimVehicleProcess(["--flavour", "ardupilot", "--udp-out", f"127.0.0.1:{client.port}", "--seed", "3", *extra])


def wait_origin(client: MavClient, timeout_s=5.0):
    assert client.wait_statustext(lambda t: "origin set" in t, timeout_s), "no 'origin set' STATUSTEXT"


def test_guided_arm_takeoff_follow_velocity_setpoints_then_stop_3s_after_the_stream_ends():
    client = MavClient.udp_listener()
    with ardupilot(client, "--speedup", "10", "--origin-delay", "1") as sim:
        hb = client.wait_heartbeat()
        assert (hb.type, hb.autopilot, hb.custom_mode) == (mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0)
        assert client.set_interval(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20) == ACCEPTED
        wait_origin(client)
        assert client.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED).result == ACCEPTED
        assert client.recv("HEARTBEAT", 2, lambda m: m.custom_mode == GUIDED) is not None
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
        assert client.recv("HEARTBEAT", 2, lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED) is not None
        assert client.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0).result == ACCEPTED
        assert client.recv("LOCAL_POSITION_NED", 4, lambda m: m.z < -4.8) is not None, "did not climb to 5 m"

        # stream velocity setpoints (type_mask 3527: velocity only) for 8 s of simulated time
        target = (2.0, 1.0, 0.0)
        t_start = client.recv("LOCAL_POSITION_NED", 1).time_boot_ms / 1000
        samples, last = [], None
        while True:
            client.velocity_setpoint(*target)
            m = client.latest("LOCAL_POSITION_NED")
            if m is not None:
                last = m
                if m.time_boot_ms / 1000 - t_start > 3.0:  # settled (2.2 m/s at 3 m/s^2 + catch-up)
                    samples.append((m.vx, m.vy, m.vz))
                if m.time_boot_ms / 1000 - t_start > 8.0:
                    break
            time.sleep(0.01)
        t_stop = last.time_boot_ms / 1000
        err = np.linalg.norm(np.array(samples) - target, axis=1)
        print(f"\nGUIDED velocity following: {len(samples)} samples, mean error {err.mean():.3f} m/s, max {err.max():.3f} m/s")
        assert len(samples) > 20
        assert err.mean() < 0.15 and err.max() < 0.4

        # no more setpoints: still flying the last one before GUID_TIMEOUT (3 s), stopped after it
        before = client.recv("LOCAL_POSITION_NED", 3, lambda m: m.time_boot_ms / 1000 > t_stop + 2.3)
        assert before is not None and math.hypot(before.vx - 2.0, before.vy - 1.0) < 0.6
        after = client.recv("LOCAL_POSITION_NED", 3, lambda m: m.time_boot_ms / 1000 > t_stop + 6.0)
        assert after is not None and math.hypot(after.vx, after.vy) < 0.3, f"still moving: {after}"
        hold = client.recv("LOCAL_POSITION_NED", 3, lambda m: m.time_boot_ms / 1000 > t_stop + 9.0)
        assert math.hypot(hold.x - after.x, hold.y - after.y) < 1.0  # holding where it stopped
        assert client.recv("HEARTBEAT", 2).custom_mode == GUIDED
        assert sim.stop() == 0


def test_nothing_streams_until_asked_and_covariance_messages_are_denied():
    client = MavClient.udp_listener()
    with ardupilot(client, "--speedup", "5", "--origin-delay", "3") as sim:
        client.wait_heartbeat()
        seen = set()
        deadline = time.monotonic() + 0.3
        while time.monotonic() < deadline:
            m = client.recv(None, 0.1)
            if m is not None:
                seen.add(m.get_type())
        assert seen <= {"HEARTBEAT", "STATUSTEXT"}, seen
        assert client.set_interval(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10) == ACCEPTED
        for msg_id in (mav.MAVLINK_MSG_ID_ODOMETRY, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV,
                       mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT_COV, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION_COV,
                       mav.MAVLINK_MSG_ID_ESTIMATOR_STATUS):
            assert client.set_interval(msg_id, 10) == DENIED, msg_id
        assert client.wait_statustext(lambda t: t == "No ap_message for mavlink id (331)")
        # LOCAL_POSITION_NED only once the EKF origin exists (3 s after boot here)
        first_local = client.recv("LOCAL_POSITION_NED", 3)
        assert first_local is not None and first_local.time_boot_ms >= 3000
        assert client.wait_statustext(lambda t: "origin set" in t)
        assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN).result == ACCEPTED
        origin = client.recv("GPS_GLOBAL_ORIGIN", 2)
        assert origin is not None and origin.latitude != 0
        # what ArduPilot has instead of covariance: EKF test ratios (dimensionless), GPS accuracies (mm)
        assert client.set_interval(mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 5) == ACCEPTED
        assert client.set_interval(mav.MAVLINK_MSG_ID_GPS_RAW_INT, 5) == ACCEPTED
        ekf = client.recv("EKF_STATUS_REPORT", 2, lambda m: m.flags == 0x033F)
        assert ekf is not None and max(ekf.velocity_variance, ekf.pos_horiz_variance, ekf.pos_vert_variance) < 1.0
        gps = client.recv("GPS_RAW_INT", 2, lambda m: m.fix_type == 3)
        assert 300 < gps.h_acc < 3000 and 300 < gps.v_acc < 3000  # mm, from the injected sigmas
        # the older way works too: REQUEST_DATA_STREAM(POSITION) at 4 Hz
        client.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 4, 1)
        stamps = []
        while len(stamps) < 6:
            m = client.recv("GLOBAL_POSITION_INT", 2)
            assert m is not None
            stamps.append(m.time_boot_ms)
        gaps = np.diff(stamps[1:])
        assert np.all(np.abs(gaps - 250) <= 3), gaps
        assert sim.stop() == 0


def test_sim_state_streams_the_truth_beside_the_estimate():
    client = MavClient.udp_listener()
    with ardupilot(client, "--speedup", "10", "--origin-delay", "0.5", "--home=-35.363261,149.165230,584") as sim:
        client.wait_heartbeat()
        assert client.set_interval(mav.MAVLINK_MSG_ID_SIM_STATE, 10) == ACCEPTED
        assert client.set_interval(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10) == ACCEPTED
        wait_origin(client)
        home = Home(-35.363261, 149.165230, 584.0)
        assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, GUIDED).result == ACCEPTED
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
        assert client.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10.0).result == ACCEPTED
        assert client.recv("LOCAL_POSITION_NED", 5, lambda m: m.z < -9.5) is not None
        pitches, pairs, est = [], 0, None
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            client.velocity_setpoint(5.0, 0.0, 0.0)
            m = client.recv(["LOCAL_POSITION_NED", "SIM_STATE"], 0.05)  # every pair, in order
            if m is None:
                continue
            if m.get_type() == "LOCAL_POSITION_NED":
                est = m
                continue
            q = np.array([m.q1, m.q2, m.q3, m.q4])
            assert abs(np.linalg.norm(q) - 1) < 1e-5
            n, e, d = home.global_to_ned(m.lat_int * 1e-7, m.lon_int * 1e-7, m.alt)
            assert abs(m.lat - m.lat_int * 1e-7) < 1e-5 and abs(m.lon - m.lon_int * 1e-7) < 1e-5
            if est is not None:
                # same physics step (same rate -> same grid): truth and estimate differ by the nav error
                assert math.hypot(n - est.x, e - est.y) < 3.0 and abs(d - est.z) < 4.0
                # the velocity error (0.1 m/s sigma per axis, 0.35 m/s at most in these seconds), and
                # accelerating at ~3 m/s^2 a pair can straddle one 10 Hz period: 0.5 m/s more
                assert math.hypot(m.vn - est.vx, m.ve - est.vy) < 0.85
                pairs += 1
            pitches.append((m.pitch, m.vn))
        assert pairs > 10
        # accelerating north the truth pitches nose-down, then levels off as speed settles
        assert min(p for p, _ in pitches) < -0.1
        assert sim.stop() == 0


def test_link_loss_is_reported_but_the_vehicle_keeps_flying():
    client = MavClient.udp_listener()
    with ardupilot(client, "--speedup", "10", "--origin-delay", "0.5") as sim:
        client.wait_heartbeat()
        for _ in range(5):
            client.heartbeat()
            time.sleep(0.02)
        wait_origin(client)
        assert client.command(mav.MAV_CMD_DO_SET_MODE, 1, GUIDED).result == ACCEPTED
        assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
        assert client.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0).result == ACCEPTED
        lost = client.wait_statustext(lambda t: t.startswith("Link lost"), 3)
        assert lost is not None and "255/190" in lost  # FS_GCS_TIMEOUT = 5 s of simulated time
        hb = client.recv("HEARTBEAT", 2)
        assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == GUIDED
        client.heartbeat()
        assert client.wait_statustext(lambda t: t.startswith("Link regained"))
        assert sim.stop() == 0
