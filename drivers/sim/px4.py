"""PX4 multicopter flavour of the simulated autopilot (behaviour of PX4 v1.14-v1.16).

What it imitates, and from where (details and links in docs/sim.md):

* HEARTBEAT autopilot PX4, custom_mode = main mode << 16 | sub mode << 24
  (px4_custom_mode.h: MANUAL 1, ALTCTL 2, POSCTL 3, AUTO 4 with sub modes READY 1, TAKEOFF 2,
  LOITER 3, MISSION 4, RTL 5, LAND 6; ACRO 5, OFFBOARD 6, STABILIZED 7); set with
  MAV_CMD_DO_SET_MODE (param2 main, param3 sub). Refusals are TEMPORARILY_REJECTED with a
  STATUSTEXT, as commander does.
* OFFBOARD only while setpoints stream: the last SET_POSITION_TARGET_* must be younger than
  COM_OF_LOSS_T (commander_params.c default 1.0 s; PX4 docs: stream > 2 Hz before switching);
  if the stream then stops for COM_OF_LOSS_T the offboard-loss failsafe switches to Hold
  (COM_OBL_RC_ACT; without RC the position-mode fallback is Hold). Offboard may take off.
  type_mask per axis; frames LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED.
* Streams on by default, like a PX4 MAVLink instance in "onboard" mode (mavlink_main.cpp,
  MAVLINK_MODE_ONBOARD), rates trimmed; SET_MESSAGE_INTERVAL changes them; REQUEST_DATA_STREAM is
  ignored (deprecated in PX4). ODOMETRY (streams/ODOMETRY.hpp): frame LOCAL_NED, velocity NED,
  pose/velocity covariance NaN except the diagonal variances; ESTIMATOR_STATUS with
  pos_horiz/vert_accuracy and test ratios; ALTITUDE; HIL_STATE_QUATERNION carries the truth
  (PX4 SITL's groundtruth stream), SIM_STATE too (a simulator extension).
* Arming needs a global position in Hold / Takeoff / Offboard (Offboard also a live stream);
  force with param2 = 21196. NAV_TAKEOFF climbs to MIS_TAKEOFF_ALT (2.5 m) at MPC_TKO_SPEED,
  then Hold. Auto-disarm: COM_DISARM_PRFLT (10 s) if never airborne, COM_DISARM_LAND (2 s)
  after landing.
"""

from __future__ import annotations

import math
import struct

from pymavlink.dialects.v20 import ardupilotmega as mav

from drivers.sim.autopilot import LOCAL_FRAMES, NAN, Behaviour, Param, SimAutopilot, log
from drivers.sim.dynamics import Setpoint

# px4_custom_mode.h
MANUAL, ALTCTL, POSCTL, AUTO, ACRO, OFFBOARD, STABILIZED = 1, 2, 3, 4, 5, 6, 7
READY, TAKEOFF, LOITER, MISSION, RTL, LAND = 1, 2, 3, 4, 5, 6
MODE_NAMES = {(AUTO, TAKEOFF): "Takeoff", (AUTO, LOITER): "Hold", (AUTO, MISSION): "Mission", (AUTO, RTL): "Return",
              (AUTO, LAND): "Land", (OFFBOARD, 0): "Offboard", (MANUAL, 0): "Manual", (ALTCTL, 0): "Altitude",
              (POSCTL, 0): "Position", (ACRO, 0): "Acro", (STABILIZED, 0): "Stabilized", (AUTO, READY): "Ready"}
HOLD = (AUTO, LOITER)
FORCE_MAGIC = 21196.0

ESTIMATOR_FLAGS_GPS = (mav.ESTIMATOR_ATTITUDE | mav.ESTIMATOR_VELOCITY_HORIZ | mav.ESTIMATOR_VELOCITY_VERT
                       | mav.ESTIMATOR_POS_HORIZ_REL | mav.ESTIMATOR_POS_HORIZ_ABS | mav.ESTIMATOR_POS_VERT_ABS
                       | mav.ESTIMATOR_PRED_POS_HORIZ_REL | mav.ESTIMATOR_PRED_POS_HORIZ_ABS)
ESTIMATOR_FLAGS_NO_GPS = (mav.ESTIMATOR_ATTITUDE | mav.ESTIMATOR_VELOCITY_VERT | mav.ESTIMATOR_POS_VERT_ABS
                          | mav.ESTIMATOR_CONST_POS_MODE)

# Default stream rates (Hz): MAVLINK_MODE_ONBOARD of mavlink_main.cpp, the fast ones trimmed so a
# sped-up simulation stays affordable in Python.
ONBOARD_STREAMS_HZ = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 20.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 20.0,
    mav.MAVLINK_MSG_ID_ODOMETRY: 20.0,
    mav.MAVLINK_MSG_ID_ALTITUDE: 10.0,
    mav.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mav.MAVLINK_MSG_ID_VFR_HUD: 10.0,
}


class PX4Multicopter(SimAutopilot):
    FLAVOUR = "px4"
    AUTOPILOT = mav.MAV_AUTOPILOT_PX4
    EXTERNAL_CAN_TAKE_OFF = True
    STREAMABLE = {
        **SimAutopilot.COMMON_STREAMABLE,
        mav.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: "msg_hil_state_quaternion",
        mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: "msg_autopilot_version",
        mav.MAVLINK_MSG_ID_HOME_POSITION: "msg_home_position",
        mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "msg_extended_sys_state",
        mav.MAVLINK_MSG_ID_ODOMETRY: "msg_odometry",
        mav.MAVLINK_MSG_ID_ESTIMATOR_STATUS: "msg_estimator_status",
        mav.MAVLINK_MSG_ID_ALTITUDE: "msg_altitude",
    }

    def __init__(self, sim, home=None, sysid: int = 1, seed: int | None = None):
        super().__init__(sim, home, sysid, seed)
        self.mode = HOLD
        self.loss_reported = False

    # ---- parameters ----------------------------------------------------------------------------

    def default_params(self) -> list[Param]:
        f, i = mav.MAV_PARAM_TYPE_REAL32, mav.MAV_PARAM_TYPE_INT32
        return [
            Param("MAV_SYS_ID", float(self.sysid), i),
            Param("COM_OF_LOSS_T", 1.0, f),      # s: offboard setpoint loss (commander_params.c)
            Param("COM_OBL_RC_ACT", 0.0, i),     # 0 = Position mode; without RC PX4 falls back to Hold
            Param("COM_DISARM_PRFLT", 10.0, f),  # s: disarm if not taken off
            Param("COM_DISARM_LAND", 2.0, f),    # s: disarm after landing
            Param("COM_DL_LOSS_T", 10.0, i),     # s: data link loss
            Param("MIS_TAKEOFF_ALT", 2.5, f),    # m above home
            Param("MPC_TKO_SPEED", 1.5, f),      # m/s
            Param("MPC_LAND_SPEED", 0.7, f),     # m/s
            Param("RTL_RETURN_ALT", 60.0, f),    # m above home
            Param("EKF2_GPS_P_GATE", 5.0, f),    # sigma
            Param("EKF2_GPS_V_GATE", 5.0, f),
        ]

    def encode_param(self, p: Param) -> float:
        # PX4 sends integer parameters bytewise (the int32 bits reinterpreted as a float)
        if p.ptype == mav.MAV_PARAM_TYPE_INT32:
            return struct.unpack("<f", struct.pack("<i", int(p.value)))[0]
        return float(p.value)

    def decode_param(self, value: float, ptype: int) -> float:
        if ptype == mav.MAV_PARAM_TYPE_INT32:
            return float(struct.unpack("<i", struct.pack("<f", value))[0])
        return float(value)

    def land_speed_mps(self) -> float:
        return self.param("MPC_LAND_SPEED")

    def rtl_altitude_m(self) -> float:
        return self.param("RTL_RETURN_ALT")

    def link_timeout_s(self) -> float:
        return self.param("COM_DL_LOSS_T")

    def firmware_version(self):
        return (1, 15, 0)

    def capabilities(self) -> int:
        return (super().capabilities() | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET)

    def default_interval_s(self, msg_id: int):
        hz = ONBOARD_STREAMS_HZ.get(msg_id)
        return 1.0 / hz if hz else None

    def refuse_stream(self, msg_id: int) -> int:
        return mav.MAV_RESULT_FAILED  # MavlinkReceiver::set_message_interval returns an error

    def cmd_set_message_interval(self, params, link, frame) -> int:
        if int(params[0]) == mav.MAVLINK_MSG_ID_HEARTBEAT:
            return mav.MAV_RESULT_FAILED  # PX4 does not let a client change the heartbeat
        return super().cmd_set_message_interval(params, link, frame)

    # ---- modes -----------------------------------------------------------------------------------

    def custom_mode(self) -> int:
        main, sub = self.mode
        return (main << 16) | (sub << 24)

    def heartbeat_base_mode(self) -> int:
        flags = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.mode[0] in (AUTO, OFFBOARD):
            flags |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.mode[0] == AUTO:
            flags |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        if self.armed:
            flags |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        return flags

    def offboard_signal(self) -> bool:
        """A setpoint arrived within COM_OF_LOSS_T (commander's offboard proof of life)."""
        return self.t_s - self.external_t_s <= self.param("COM_OF_LOSS_T")

    def _reject(self, text: str) -> int:
        self.statustext(mav.MAV_SEVERITY_CRITICAL, text)
        return mav.MAV_RESULT_TEMPORARILY_REJECTED

    def set_mode(self, main: int, sub: int) -> int:
        key = (main, sub if main == AUTO else 0)
        name = MODE_NAMES.get(key)
        if name is None:
            return self._reject(f"Switching to mode {main}.{sub} is not supported")
        if key == self.mode:
            return mav.MAV_RESULT_ACCEPTED
        if main in (MANUAL, ALTCTL, POSCTL, ACRO, STABILIZED):
            return self._reject(f"Switching to {name} is currently not possible: no manual control")
        if key == (AUTO, MISSION):
            return self._reject("Switching to Mission is currently not possible: no mission")
        if key == (AUTO, READY):
            return self._reject("Switching to Ready is not possible")
        if not self.position_valid and key != (AUTO, LAND):
            return self._reject(f"Switching to {name} is currently not possible: no global position")
        if key == (OFFBOARD, 0) and not self.offboard_signal():
            return self._reject("Switching to Offboard is currently not possible")
        if key == (AUTO, TAKEOFF):
            if not self.armed or not self.landed:
                return self._reject("Takeoff denied: not armed on the ground")
            self.mode = key
            self._start_takeoff(NAN)
            return mav.MAV_RESULT_ACCEPTED
        self.mode = key
        self.loss_reported = False
        if key == (OFFBOARD, 0):
            self.enter(Behaviour.EXTERNAL)
        elif key == (AUTO, RTL):
            self.enter(Behaviour.RTL)
        elif key == (AUTO, LAND):
            self.enter(Behaviour.LAND)
        else:
            self.enter(Behaviour.HOLD)
        return mav.MAV_RESULT_ACCEPTED

    def cmd_do_set_mode(self, params, link, frame) -> int:
        if not int(params[0]) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_UNSUPPORTED
        return self.set_mode(int(params[1]), int(params[2]))

    def on_set_mode(self, msg, link) -> None:
        if msg.target_system == self.sysid and msg.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self.set_mode((msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF)

    def cmd_nav_land(self, params, link, frame) -> int:
        return self.set_mode(AUTO, LAND)

    def cmd_nav_return_to_launch(self, params, link, frame) -> int:
        return self.set_mode(AUTO, RTL)

    def cmd_do_reposition(self, params, link, frame) -> int:
        """Go to lat/lon/alt and hold there (MAVSDK's goto_location; PX4 switches to Hold)."""
        if not self.position_valid or not self.armed or self.landed:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        lat, lon, alt = params[4], params[5], params[6]
        if frame is not None:  # COMMAND_INT: degE7
            lat, lon = lat * 1e-7, lon * 1e-7
        if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in (lat, lon, alt)):
            return mav.MAV_RESULT_DENIED
        self.mode = HOLD
        self.enter(Behaviour.HOLD)
        self.goto_ned = list(self.home.global_to_ned(lat, lon, alt))
        if math.isfinite(params[3]):
            self.hold_yaw = math.radians(params[3])
        return mav.MAV_RESULT_ACCEPTED

    # ---- arming and takeoff ---------------------------------------------------------------------

    def cmd_component_arm_disarm(self, params, link, frame) -> int:
        forced = abs(params[1] - FORCE_MAGIC) < 0.5
        if params[0] >= 0.5:
            if self.armed:
                return mav.MAV_RESULT_ACCEPTED
            if not forced:
                if self.mode not in (HOLD, (OFFBOARD, 0), (AUTO, TAKEOFF)):
                    return self._reject(f"Arming denied: not possible in {MODE_NAMES[self.mode]}")
                if not self.position_valid:
                    return self._reject("Arming denied: no global position")
                if self.mode == (OFFBOARD, 0) and not self.offboard_signal():
                    return self._reject("Arming denied: offboard signal lost")
            self.set_armed(True, "by command")
            self.statustext(mav.MAV_SEVERITY_INFO, "Armed by external command")
            self.enter(self.behaviour)
            return mav.MAV_RESULT_ACCEPTED
        if not self.armed:
            return mav.MAV_RESULT_ACCEPTED
        if not self.landed and not forced:
            return self._reject("Disarming denied: not landed")
        self.set_armed(False, "by command")
        self.statustext(mav.MAV_SEVERITY_INFO, "Disarmed by external command")
        return mav.MAV_RESULT_ACCEPTED

    def cmd_nav_takeoff(self, params, link, frame) -> int:
        if not self.position_valid:
            return self._reject("Takeoff denied: no global position")
        if not self.armed:
            return self._reject("Takeoff denied: disarmed")
        if not self.landed:
            return self._reject("Takeoff denied: already flying")
        self.mode = (AUTO, TAKEOFF)
        self._start_takeoff(params[6])
        return mav.MAV_RESULT_ACCEPTED

    def _start_takeoff(self, amsl_alt: float) -> None:
        # param7 is an AMSL altitude in PX4 (NaN = MIS_TAKEOFF_ALT above home)
        above_home = self.param("MIS_TAKEOFF_ALT")
        if isinstance(amsl_alt, (int, float)) and math.isfinite(amsl_alt):
            above_home = amsl_alt - (self.home.alt_m - self.home.start_down_m)
        self.takeoff(max(above_home, 0.5), self.param("MPC_TKO_SPEED"))

    def on_takeoff_complete(self) -> None:
        self.mode = HOLD
        self.enter(Behaviour.HOLD)

    def check_auto_disarm(self) -> None:
        if not self.armed or not self.landed or self.landed_since_s < 0:
            return
        on_ground = self.t_s - max(self.landed_since_s, self.armed_since_s)
        limit = self.param("COM_DISARM_LAND") if self.has_flown else self.param("COM_DISARM_PRFLT")
        if limit > 0 and on_ground > limit and self.behaviour is not Behaviour.TAKEOFF:
            self.set_armed(False, "auto-disarm")
            self.statustext(mav.MAV_SEVERITY_INFO, "Disarmed by auto preflight disarming" if not self.has_flown
                            else "Disarmed by landing")
            if self.behaviour in (Behaviour.LAND, Behaviour.RTL):
                self.mode = HOLD
                self.enter(Behaviour.HOLD)

    # ---- offboard setpoints ------------------------------------------------------------------------

    def on_set_position_target_local_ned(self, msg, link) -> None:
        self.note_setpoint()
        if msg.coordinate_frame not in LOCAL_FRAMES:
            self.setpoints_ignored += 1
            return
        self._offboard_target(self.decode_position_target(msg))

    def _offboard_target(self, tgt) -> None:
        values = [x for x in tgt.position + tgt.velocity + tgt.accel if x == x]
        if not values or not all(math.isfinite(x) and abs(x) < 1e5 for x in values):
            self.setpoints_ignored += 1
            return
        sp = Setpoint(position_ned_m=tuple(tgt.position), velocity_ned_mps=tuple(tgt.velocity),
                      accel_ned_mps2=tuple(tgt.accel), yaw_rad=tgt.yaw, yaw_rate_rps=tgt.yaw_rate)
        # Outside offboard the stream only counts as proof of life (PX4 records it regardless)
        self.accept_external(sp, "px4")

    def check_setpoint_failsafe(self) -> None:
        if self.mode == (OFFBOARD, 0) and not self.offboard_signal():
            self.mode = HOLD
            self.enter(Behaviour.HOLD)
            if not self.loss_reported:
                self.loss_reported = True
                self.statustext(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated: offboard signal lost, Hold")
            log.info("t=%.2f offboard loss after %.2f s: Hold", self.t_s, self.t_s - self.external_t_s)

    def on_ping(self, msg, link) -> None:
        # a ping request (target 0/0) is answered to its sender
        if msg.target_system == 0 and msg.target_component == 0:
            self.send(link.name, mav.MAVLink_ping_message(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()))

    # ---- PX4 telemetry ------------------------------------------------------------------------

    def msg_odometry(self):
        """ODOMETRY as streams/ODOMETRY.hpp fills it: NaN off the diagonal, variances on it."""
        if not self.position_valid:
            return None
        est = self.estimate()
        w = self._body_rates()
        var = [s * s for s in self.nav.spec.sigma]
        pose_cov = [NAN] * 21
        vel_cov = [NAN] * 21
        # upper-triangular row-major 6x6: diagonal indices 0, 6, 11, 15, 18, 20
        for k, idx in enumerate((0, 6, 11)):
            pose_cov[idx] = var[k]
            vel_cov[idx] = var[3 + k]
        for k, idx in enumerate((15, 18, 20)):
            pose_cov[idx] = var[6 + k]
        p, v, q = est["p"], est["v"], est["q"]
        return mav.MAVLink_odometry_message(
            self.time_usec, mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_LOCAL_NED, float(p[0]), float(p[1]), float(p[2]),
            [float(x) for x in q], float(v[0]), float(v[1]), float(v[2]), float(w[0]), float(w[1]), float(w[2]),
            pose_cov, vel_cov, 0, mav.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100)

    def msg_estimator_status(self):
        s = self.nav.spec.sigma
        if not self.position_valid:
            return mav.MAVLink_estimator_status_message(self.time_usec, ESTIMATOR_FLAGS_NO_GPS, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0,
                                                        NAN, NAN)
        vel, pos_h, pos_v = self.gps.test_ratios(self.param("EKF2_GPS_P_GATE"))
        # PX4 reports the test ratios themselves (innov^2 / (gate^2 var)) and 1-sigma accuracies
        return mav.MAVLink_estimator_status_message(self.time_usec, ESTIMATOR_FLAGS_GPS, vel, pos_h, pos_v, 0.02, 0.0, 0.0,
                                                    float(math.hypot(s[0], s[1]) / math.sqrt(2.0)), float(s[2]))

    def msg_altitude(self):
        est = self.estimate()
        amsl = self.home.alt_m - est["p"][2]
        rel = self.home.start_down_m - est["p"][2]
        return mav.MAVLink_altitude_message(self.time_usec, amsl, amsl, float(-est["p"][2]), rel, NAN, NAN)

    def msg_hil_state_quaternion(self):
        """Ground truth, the way PX4 SITL publishes it (groundtruth topics)."""
        tr = self.truth()
        lat, lon, alt = self.home.ned_to_global(*tr["p"])
        w = self._body_rates()
        f = self.vehicle.specific_force_body()
        v = tr["v"]
        air = math.hypot(v[0] - self.wind.velocity_ned()[0], v[1] - self.wind.velocity_ned()[1])
        mg = [int(round(x / 9.80665 * 1000)) for x in f]
        return mav.MAVLink_hil_state_quaternion_message(
            self.time_usec, [float(x) for x in tr["q"]], float(w[0]), float(w[1]), float(w[2]),
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(v[0] * 100)), int(round(v[1] * 100)), int(round(v[2] * 100)),
            int(round(air * 100)), int(round(air * 100)), *mg)
