"""ArduPilot Copter flavour of the simulated autopilot (behaviour of Copter 4.6 SITL).

What it imitates, and from where (details and links in docs/sim.md):

* HEARTBEAT type QUADROTOR, autopilot ARDUPILOTMEGA, custom_mode = Copter mode number
  (ArduCopter/mode.h: STABILIZE 0, ALT_HOLD 2, AUTO 3, GUIDED 4, LOITER 5, RTL 6, LAND 9,
  POSHOLD 16, BRAKE 17); modes set with MAV_CMD_DO_SET_MODE (param2) or SET_MODE.
* Nothing streams until asked, per link: SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM (the
  stream groups of ArduCopter/GCS_MAVLink_Copter.cpp); an interval for a message ArduPilot has no
  ap_message for is DENIED with "No ap_message for mavlink id (N)" (GCS_Common.cpp). No
  covariance message exists: ODOMETRY, *_COV, ESTIMATOR_STATUS, ALTITUDE are refused.
* The EKF origin comes first (``sim.origin_delay_s``: "EKF3 IMU0 origin set", GPS_GLOBAL_ORIGIN
  and HOME_POSITION sent to every link), the use of GPS ``sim.gps_delay_s`` later ("EKF3 IMU0 is
  using GPS"): only then LOCAL_POSITION_NED, EKF_STATUS_REPORT flags 0x033F (0x00A7 before) and
  arming in GUIDED. A real 4.6 SITL took 20 s and 41 s (docs/sitl.md). EKF_STATUS_REPORT carries
  sqrt of innovation test ratios (AP_NavEKF3_Outputs.cpp getVariances).
* MAV_CMD_REQUEST_MESSAGE for a message that exists but is not available yet (HOME_POSITION
  before the origin) is ACCEPTED and nothing follows (GCS_Common.cpp, as seen on 4.6 SITL).
* GUIDED (ModeGuided): starts holding; SET_POSITION_TARGET_LOCAL_NED honoured only in GUIDED,
  frames LOCAL_NED / LOCAL_OFFSET_NED / BODY_NED / BODY_OFFSET_NED; any ignore bit of a vector
  ignores the whole vector; pos+vel, vel(+acc), acc, pos are the accepted combinations and
  anything else stops the vehicle; velocity and acceleration targets time out after GUID_TIMEOUT
  (3 s): the vehicle stops and holds. Takeoff only by MAV_CMD_NAV_TAKEOFF (param7 = altitude
  above home), armed and landed in GUIDED; setpoints do not lift it off the ground.
* Arming: GUIDED / LOITER / POSHOLD need a position estimate ("PreArm: Need Position
  Estimate"); RTL, LAND, AUTO are not armable; force with param2 = 2989. Disarmed, any mode
  change is accepted (Copter::set_mode: ``ignore_checks = !motors->armed()``): the checks
  move to arming. Auto-disarm after
  DISARM_DELAY (10 s) on the ground, and on landing in LAND / RTL.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mav

from drivers.sim.autopilot import (
    FORCE_SET, IGNORE_AX, IGNORE_AY, IGNORE_AZ, IGNORE_PX, IGNORE_PY, IGNORE_PZ, IGNORE_VX,
    IGNORE_VY, IGNORE_VZ, LOCAL_FRAMES, NAN, Behaviour, Param, SimAutopilot, log,
)
from drivers.sim.dynamics import Setpoint

# Copter mode numbers (ArduCopter/mode.h, enum class Mode::Number)
STABILIZE, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, LAND, POSHOLD, BRAKE = 0, 2, 3, 4, 5, 6, 9, 16, 17
MODE_NAMES = {STABILIZE: "STABILIZE", ALT_HOLD: "ALT_HOLD", AUTO: "AUTO", GUIDED: "GUIDED", LOITER: "LOITER",
              RTL: "RTL", LAND: "LAND", POSHOLD: "POSHOLD", BRAKE: "BRAKE"}
NEEDS_POSITION = {AUTO, GUIDED, LOITER, RTL, POSHOLD, BRAKE}
NOT_ARMABLE = {AUTO, RTL, LAND, BRAKE}
ARM_MAGIC_FORCE = 2989.0     # AP_Arming: MAV_CMD_COMPONENT_ARM_DISARM param2 that skips the checks
DISARM_MAGIC_FORCE = 21196.0

EKF_FLAGS_NO_ORIGIN = 0x00A7  # ATTITUDE | VEL_HORIZ | VEL_VERT | POS_VERT_ABS | CONST_POS_MODE
EKF_FLAGS_GPS = 0x033F        # ATTITUDE | VEL_* | POS_HORIZ_REL | POS_HORIZ_ABS | POS_VERT_ABS | PRED_POS_HORIZ_*

# REQUEST_DATA_STREAM groups (ArduCopter/GCS_MAVLink_Copter.cpp, STREAM_*_msgs), restricted to
# what the simulator can send.
DATA_STREAMS = {
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: (mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_GPS_RAW_INT),
    mav.MAV_DATA_STREAM_POSITION: (mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    mav.MAV_DATA_STREAM_EXTRA1: (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_SIMSTATE),
    mav.MAV_DATA_STREAM_EXTRA2: (mav.MAVLINK_MSG_ID_VFR_HUD,),
    mav.MAV_DATA_STREAM_EXTRA3: (mav.MAVLINK_MSG_ID_SYSTEM_TIME, mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT),
}


class ArduPilotCopter(SimAutopilot):
    FLAVOUR = "ardupilot"
    AUTOPILOT = mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    EXTERNAL_CAN_TAKE_OFF = False
    STREAMABLE = {
        **SimAutopilot.COMMON_STREAMABLE,
        mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: "msg_autopilot_version",
        mav.MAVLINK_MSG_ID_SIMSTATE: "msg_simstate",
        mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT: "msg_ekf_status_report",
        mav.MAVLINK_MSG_ID_HOME_POSITION: "msg_home_position",
        mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "msg_extended_sys_state",
    }
    DENIED = frozenset({
        mav.MAVLINK_MSG_ID_ODOMETRY, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT_COV,
        mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION_COV, mav.MAVLINK_MSG_ID_ESTIMATOR_STATUS, mav.MAVLINK_MSG_ID_ALTITUDE,
        mav.MAVLINK_MSG_ID_HIL_STATE_QUATERNION,
    })

    def __init__(self, sim, home=None, sysid: int = 1, seed: int | None = None):
        super().__init__(sim, home, sysid, seed)
        self.mode = STABILIZE
        self.using_gps = False

    @property
    def position_valid(self) -> bool:
        """The EKF has an origin and uses GPS (``gps_delay_s`` after the origin)."""
        return self.using_gps

    # ---- parameters ----------------------------------------------------------------------------

    def default_params(self) -> list[Param]:
        f, i8, i16 = mav.MAV_PARAM_TYPE_REAL32, mav.MAV_PARAM_TYPE_INT8, mav.MAV_PARAM_TYPE_INT16
        return [
            Param("SYSID_THISMAV", float(self.sysid), i16),
            Param("GUID_TIMEOUT", 3.0, f),       # s: velocity/accel targets expire (ModeGuided::get_timeout_ms)
            Param("DISARM_DELAY", 10.0, i8),     # s: auto-disarm on the ground
            Param("FS_GCS_TIMEOUT", 5.0, f),     # s: GCS heartbeat loss
            Param("WPNAV_SPEED_UP", 250.0, f),   # cm/s: takeoff climb
            Param("WPNAV_SPEED_DN", 150.0, f),   # cm/s
            Param("LAND_SPEED", 50.0, i16),      # cm/s: final descent
            Param("RTL_ALT", 1500.0, i16),       # cm above home
            Param("EK3_POS_I_GATE", 500.0, i16),  # centi-sigma: innovation gates of the test ratios
            Param("EK3_VEL_I_GATE", 500.0, i16),
            Param("EK3_HGT_I_GATE", 500.0, i16),
        ]

    def land_speed_mps(self) -> float:
        return self.param("LAND_SPEED") / 100.0

    def rtl_altitude_m(self) -> float:
        return self.param("RTL_ALT") / 100.0

    def link_timeout_s(self) -> float:
        return self.param("FS_GCS_TIMEOUT")

    def firmware_version(self):
        return (4, 6, 0)

    def capabilities(self) -> int:
        return (super().capabilities() | mav.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mav.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
                | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)

    # ---- modes -----------------------------------------------------------------------------------

    def custom_mode(self) -> int:
        return self.mode

    def heartbeat_base_mode(self) -> int:
        # GCS_MAVLINK_Copter::base_mode: stabilize always; guided for the autonomous modes
        flags = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.mode in (GUIDED, AUTO, RTL, LOITER, LAND, POSHOLD, BRAKE):
            flags |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.mode in (STABILIZE, ALT_HOLD, POSHOLD, LOITER):
            flags |= mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if self.armed:
            flags |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        return flags

    def set_mode(self, mode: int) -> int:
        """Switch to Copter mode ``mode``; MAV_RESULT (FAILED with a STATUSTEXT when refused)."""
        name = MODE_NAMES.get(mode)
        if name is None:
            self.statustext(mav.MAV_SEVERITY_WARNING, f"Unknown mode {mode}")
            return mav.MAV_RESULT_FAILED
        if mode == self.mode:
            return mav.MAV_RESULT_ACCEPTED
        # Copter::set_mode: disarmed, every mode is accepted (the checks are the arming checks)
        if self.armed and mode in NEEDS_POSITION and not self.position_valid:
            self.statustext(mav.MAV_SEVERITY_WARNING, f"Mode change to {name} failed: requires position")
            return mav.MAV_RESULT_FAILED
        if self.armed and mode == AUTO:
            self.statustext(mav.MAV_SEVERITY_WARNING, "Mode change to AUTO failed: no mission")
            return mav.MAV_RESULT_FAILED
        self.mode = mode
        self.external = None  # ModeGuided::init: start with zero velocity (hold)
        if mode == GUIDED:
            self.enter(Behaviour.EXTERNAL)
        elif mode == RTL:
            self.enter(Behaviour.RTL)
        elif mode == LAND:
            self.enter(Behaviour.LAND)
        else:
            self.enter(Behaviour.HOLD)
        return mav.MAV_RESULT_ACCEPTED

    def cmd_do_set_mode(self, params, link, frame) -> int:
        if not int(params[0]) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_UNSUPPORTED
        return self.set_mode(int(params[1]))

    def on_set_mode(self, msg, link) -> None:
        if msg.target_system == self.sysid and msg.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self.set_mode(int(msg.custom_mode))

    def cmd_nav_land(self, params, link, frame) -> int:
        return self.set_mode(LAND)

    def cmd_nav_return_to_launch(self, params, link, frame) -> int:
        return self.set_mode(RTL)

    # ---- arming and takeoff ---------------------------------------------------------------------

    def cmd_component_arm_disarm(self, params, link, frame) -> int:
        if params[0] >= 0.5:
            if self.armed:
                return mav.MAV_RESULT_ACCEPTED
            if abs(params[1] - ARM_MAGIC_FORCE) > 0.5:
                if self.mode in NOT_ARMABLE:
                    self.statustext(mav.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable")
                    return mav.MAV_RESULT_FAILED
                if self.mode in NEEDS_POSITION and not self.position_valid:
                    self.statustext(mav.MAV_SEVERITY_CRITICAL, "PreArm: Need Position Estimate")
                    return mav.MAV_RESULT_FAILED
            self.set_armed(True, "by command")
            self.enter(Behaviour.EXTERNAL if self.mode == GUIDED else self.behaviour)
            return mav.MAV_RESULT_ACCEPTED
        if not self.armed:
            return mav.MAV_RESULT_ACCEPTED
        if not self.landed and abs(params[1] - DISARM_MAGIC_FORCE) > 0.5:
            self.statustext(mav.MAV_SEVERITY_CRITICAL, "Disarm: not landed")
            return mav.MAV_RESULT_FAILED
        self.set_armed(False, "by command")
        return mav.MAV_RESULT_ACCEPTED

    def cmd_nav_takeoff(self, params, link, frame) -> int:
        # GCS_MAVLINK_Copter: takeoff in GUIDED (ModeGuided::do_user_takeoff_start), armed, landed
        if self.mode != GUIDED or not self.armed or not self.landed:
            return mav.MAV_RESULT_FAILED
        alt = params[6]
        if not (isinstance(alt, (int, float)) and math.isfinite(alt) and alt > 0):
            return mav.MAV_RESULT_FAILED
        self.external = None
        self.takeoff(float(alt), self.param("WPNAV_SPEED_UP") / 100.0)
        return mav.MAV_RESULT_ACCEPTED

    def on_takeoff_complete(self) -> None:
        # Guided stays in its takeoff sub-mode holding the altitude until a new target arrives
        self.enter(Behaviour.EXTERNAL)

    def check_auto_disarm(self) -> None:
        if not self.armed or not self.landed or self.landed_since_s < 0:
            return
        on_ground = self.t_s - max(self.landed_since_s, self.armed_since_s)
        if self.behaviour in (Behaviour.LAND, Behaviour.RTL) and self.has_flown and on_ground > 1.0:
            self.set_armed(False, "landed")
            self.statustext(mav.MAV_SEVERITY_INFO, "Disarming motors")
        elif self.param("DISARM_DELAY") > 0 and on_ground > self.param("DISARM_DELAY") and self.behaviour is not Behaviour.TAKEOFF:
            self.set_armed(False, "auto-disarm")
            self.statustext(mav.MAV_SEVERITY_INFO, "Disarming motors")

    # ---- GUIDED setpoints --------------------------------------------------------------------------

    def on_set_position_target_local_ned(self, msg, link) -> None:
        self.note_setpoint()
        if self.mode != GUIDED:
            self.setpoints_ignored += 1
            return
        if msg.coordinate_frame not in LOCAL_FRAMES:
            self.stop_guided()
            return
        self._guided_target(self.decode_position_target(msg))

    def on_set_position_target_global_int(self, msg, link) -> None:
        self.note_setpoint()
        if self.mode != GUIDED:
            self.setpoints_ignored += 1
            return
        rel = msg.coordinate_frame in (mav.MAV_FRAME_GLOBAL_RELATIVE_ALT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        amsl = msg.coordinate_frame in (mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT)
        pos_ignored = bool(msg.type_mask & (IGNORE_PX | IGNORE_PY | IGNORE_PZ))
        if not pos_ignored and not (rel or amsl):
            self.stop_guided()  # unknown altitude frame: input is not valid, stop
            return
        alt = msg.alt + (self.home.alt_m - self.home.start_down_m if rel else 0.0)
        ned = self.home.global_to_ned(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt)
        self._guided_target(self.decode_position_target(msg, local_position=ned))

    def stop_guided(self) -> None:
        """ModeGuided::init(true): invalid input stops the vehicle where it is."""
        self.external = None
        self.enter(Behaviour.EXTERNAL)

    def _guided_target(self, tgt) -> None:
        m = tgt.type_mask
        # GCS_MAVLINK_Copter::handle_message_set_position_target_local_ned: one ignore bit ignores the vector
        pos_ignore = bool(m & (IGNORE_PX | IGNORE_PY | IGNORE_PZ))
        vel_ignore = bool(m & (IGNORE_VX | IGNORE_VY | IGNORE_VZ))
        acc_ignore = bool(m & (IGNORE_AX | IGNORE_AY | IGNORE_AZ))
        if m & FORCE_SET and not acc_ignore:
            self.stop_guided()
            return
        nan3 = (NAN, NAN, NAN)
        pos = nan3 if pos_ignore else tuple(tgt.position)
        vel = nan3 if vel_ignore else tuple(tgt.velocity)
        acc = nan3 if acc_ignore else tuple(tgt.accel)
        if not pos_ignore and not vel_ignore:
            kind = "posvel"
        elif pos_ignore and not vel_ignore:
            kind = "vel"
        elif pos_ignore and vel_ignore and not acc_ignore:
            kind = "accel"
        elif not pos_ignore and vel_ignore and acc_ignore:
            kind = "pos"
        else:
            self.stop_guided()
            return
        used = (() if pos_ignore else pos) + (() if vel_ignore else vel) + (() if acc_ignore else acc)
        if not all(math.isfinite(x) and abs(x) < 1e5 for x in used):
            self.stop_guided()  # sane_vel_or_acc_vector / check_latlng: NaN, inf or absurd -> stop
            return
        sp = Setpoint(position_ned_m=pos, velocity_ned_mps=vel, accel_ned_mps2=acc, yaw_rad=tgt.yaw,
                      yaw_rate_rps=tgt.yaw_rate, yaw_follows_velocity=True)
        if self.behaviour is not Behaviour.EXTERNAL:
            self.enter(Behaviour.EXTERNAL)  # a new target ends the takeoff sub-mode
        self.accept_external(sp, kind)

    def external_setpoint(self):
        sp = self.external
        if sp is None:
            return None
        if self.external_kind in ("vel", "accel", "posvel") and self.t_s - self.external_t_s > self.param("GUID_TIMEOUT"):
            # ModeGuided velaccel/accel_control_run: no update for the timeout -> zero velocity and
            # acceleration (posvel keeps its position target): the vehicle stops and holds there
            if self.external_kind == "posvel":
                return Setpoint(position_ned_m=sp.position_ned_m, yaw_rad=sp.yaw_rad)
            self.external = None
            self.enter(Behaviour.EXTERNAL)
            log.info("t=%.2f GUIDED target timed out after %.1f s: stopping", self.t_s, self.param("GUID_TIMEOUT"))
            return None
        return sp

    def cmd_condition_yaw(self, params, link, frame) -> int:
        if self.mode != GUIDED:
            return mav.MAV_RESULT_FAILED
        angle = math.radians(params[0])
        direction = -1.0 if params[2] < 0 else 1.0
        target = self.vehicle.yaw + direction * angle if params[3] else angle
        self.hold_yaw = target
        if self.external is not None:
            self.external.yaw_rad = target
        return mav.MAV_RESULT_ACCEPTED

    # ---- streams ---------------------------------------------------------------------------------

    def refuse_stream(self, msg_id: int) -> int:
        self.statustext(mav.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msg_id})")
        return mav.MAV_RESULT_DENIED

    def on_request_data_stream(self, msg, link) -> None:
        groups = DATA_STREAMS.keys() if msg.req_stream_id == mav.MAV_DATA_STREAM_ALL else [msg.req_stream_id]
        rate = msg.req_message_rate if msg.start_stop else 0
        for g in groups:
            for msg_id in DATA_STREAMS.get(g, ()):
                link.schedule.set_interval(msg_id, 1.0 / rate if rate > 0 else None, self.t_s)

    # ---- events ----------------------------------------------------------------------------------

    def check_events(self) -> None:
        super().check_events()
        if self.origin_set and not self.using_gps and self.t_s >= self.sim.origin_delay_s + self.sim.gps_delay_s:
            self.using_gps = True
            self.statustext(mav.MAV_SEVERITY_INFO, "EKF3 IMU0 is using GPS")

    def on_origin_set(self) -> None:
        # as 4.6 SITL: the origin, the field elevation and home to every link at once
        self.statustext(mav.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")
        self.statustext(mav.MAV_SEVERITY_INFO, f"Field Elevation Set: {self.home.alt_m:.0f}m")
        self.send(None, self.msg_gps_global_origin())
        self.send(None, self.msg_home_position())
        if self.sim.gps_delay_s <= 0:
            self.using_gps = True
            self.statustext(mav.MAV_SEVERITY_INFO, "EKF3 IMU0 is using GPS")

    def msg_gps_global_origin(self):
        if not self.origin_set:
            return None
        return mav.MAVLink_gps_global_origin_message(int(round(self.home.lat_deg * 1e7)), int(round(self.home.lon_deg * 1e7)),
                                                     int(round(self.home.alt_m * 1000)), self.time_usec)

    def msg_home_position(self):
        if not self.origin_set:
            return None
        lat, lon, alt = self.home.ned_to_global(0.0, 0.0, self.home.start_down_m)
        return mav.MAVLink_home_position_message(int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                                                 0.0, 0.0, self.home.start_down_m, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.time_usec)

    def cmd_request_message(self, params, link, frame) -> int:
        result = super().cmd_request_message(params, link, frame)
        # GCS_MAVLINK::handle_command_request_message: a known message is ACCEPTED even when it
        # cannot be sent yet (HOME_POSITION before the origin); nothing follows the ACK then.
        return mav.MAV_RESULT_ACCEPTED if result == mav.MAV_RESULT_TEMPORARILY_REJECTED else result

    # ---- ArduPilot-only telemetry ------------------------------------------------------------------

    def msg_ekf_status_report(self):
        if not self.position_valid:
            return mav.MAVLink_ekf_status_report_message(EKF_FLAGS_NO_ORIGIN, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0)
        gate = self.param("EK3_POS_I_GATE") / 100.0
        vel, pos_h, pos_v = self.gps.test_ratios(gate)
        # getVariances() reports the square roots of the test ratios
        return mav.MAVLink_ekf_status_report_message(EKF_FLAGS_GPS, math.sqrt(vel), math.sqrt(pos_h), math.sqrt(pos_v),
                                                     0.02, 0.0, 0.0)

    def msg_simstate(self):
        """SIMSTATE (164): SITL's truth in the older message (attitude, IMU, lat/lng)."""
        s = self.msg_sim_state()
        return mav.MAVLink_simstate_message(s.roll, s.pitch, s.yaw, s.xacc, s.yacc, s.zacc, s.xgyro, s.ygyro, s.zgyro,
                                            s.lat_int, s.lon_int)

