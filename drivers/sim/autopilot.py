"""The simulated autopilot: time, truth, navigation estimate, arming, behaviours, commands,
parameters and telemetry. No sockets: :mod:`drivers.sim.vehicle` feeds it parsed MAVLink messages
and sends what it puts in :attr:`SimAutopilot.outbox` and what :meth:`SimAutopilot.build` returns
for the streams each link asked for.

The two flavours (:mod:`drivers.sim.ardupilot`, :mod:`drivers.sim.px4`) subclass
:class:`SimAutopilot` and decide what differs between ArduPilot Copter and PX4: the HEARTBEAT
custom-mode encoding, which modes exist and what they do, arming and takeoff rules, how
SET_POSITION_TARGET_LOCAL_NED's type_mask is read, setpoint-loss failsafes, which messages can be
streamed, the parameter table and how refusals are acknowledged. docs/sim.md lists each behaviour
with the source it follows.

Conventions: the local NED frame is the scenario's frame (origin = home, on the ground at
altitude 0); simulated time ``t_s`` starts at 0 at boot and advances in fixed physics steps;
``time_boot_ms`` / ``time_usec`` in every message are that time. The controller flies on the
*estimate* (truth plus the injected navigation error), like a real autopilot, so a commanded
position is reached in the reported frame and missed in truth by the navigation error.
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import struct
import time
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.method.geometry import matrix_to_euler, matrix_to_quat
from drivers.sim.dynamics import GRAVITY_MPS2, MultirotorLimits, PointMassMultirotor, Setpoint, WindModel
from drivers.sim.mavlink_endpoint import StreamSchedule
from drivers.sim.navigation_error import GaussMarkovNavError, GpsReceiver, NavErrorSpec

log = logging.getLogger("companion.sim.autopilot")

NAN = float("nan")
EARTH_RADIUS_M = 6378137.0  # WGS-84 equatorial radius; flat-earth conversion about home
AUTOPILOT_COMPONENT = 1
GPS_RATE_HZ = 5.0

# SET_POSITION_TARGET_* type_mask bits (MAVLink POSITION_TARGET_TYPEMASK)
IGNORE_PX, IGNORE_PY, IGNORE_PZ = 1, 2, 4
IGNORE_VX, IGNORE_VY, IGNORE_VZ = 8, 16, 32
IGNORE_AX, IGNORE_AY, IGNORE_AZ = 64, 128, 256
FORCE_SET = 512
IGNORE_YAW, IGNORE_YAW_RATE = 1024, 2048

LOCAL_FRAMES = (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_LOCAL_OFFSET_NED, mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED)


def _finite(x: float) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@dataclass(frozen=True, slots=True)
class Home:
    """Where the vehicle boots: the local NED origin's geodetic position and the ground under it.

    lat_deg, lon_deg, alt_m: the origin (AMSL metres), on the ground at scenario altitude 0.
    start_down_m: NED z of the ground where the vehicle sits at boot (minus the terrain height).
    """

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0
    start_down_m: float = 0.0

    def __post_init__(self) -> None:
        if not (_finite(self.lat_deg) and -89.0 <= self.lat_deg <= 89.0):
            raise ValueError(f"home latitude must be within +-89 deg, got {self.lat_deg!r}")
        if not (_finite(self.lon_deg) and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(f"home longitude must be within +-180 deg, got {self.lon_deg!r}")
        if not (_finite(self.alt_m) and -500.0 <= self.alt_m <= 9000.0):
            raise ValueError(f"home altitude must be within -500..9000 m, got {self.alt_m!r}")
        if not (_finite(self.start_down_m) and abs(self.start_down_m) < 1000.0):
            raise ValueError(f"start ground height must be finite and within 1 km, got {self.start_down_m!r}")

    def ned_to_global(self, north: float, east: float, down: float) -> tuple[float, float, float]:
        """Local NED (m) -> (lat deg, lon deg, alt AMSL m), flat earth about the origin."""
        lat = self.lat_deg + math.degrees(north / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon, self.alt_m - down

    def global_to_ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        north = math.radians(lat_deg - self.lat_deg) * EARTH_RADIUS_M
        east = math.radians(lon_deg - self.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))
        return north, east, self.alt_m - alt_m


class Behaviour(enum.Enum):
    """What the vehicle is doing, whatever the flavour calls the mode."""

    HOLD = "hold"            # hold position (and on the ground: stay there)
    EXTERNAL = "external"    # fly the companion's setpoints (ArduPilot GUIDED, PX4 OFFBOARD)
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "rtl"


@dataclass(slots=True)
class PositionTarget:
    """A decoded SET_POSITION_TARGET_*: NED arrays with NaN where the type_mask ignores an axis."""

    position: list[float]
    velocity: list[float]
    accel: list[float]
    yaw: float
    yaw_rate: float
    type_mask: int
    frame: int


@dataclass(slots=True)
class Param:
    name: str
    value: float
    ptype: int  # MAV_PARAM_TYPE


@dataclass(slots=True)
class Peer:
    """A MAVLink node heard on a link (GCS, companion, mavsdk)."""

    last_heartbeat_s: float
    lost: bool = False


class SimAutopilot:
    """Base of the simulated autopilot; see the module docstring. Subclasses set the class constants."""

    FLAVOUR = "generic"
    AUTOPILOT = mav.MAV_AUTOPILOT_GENERIC
    VEHICLE_TYPE = mav.MAV_TYPE_QUADROTOR
    #: message ids a client may stream or request, mapped to the builder method name
    STREAMABLE: dict[int, str] = {}
    # What both flavours stream (each flavour's STREAMABLE starts from it): message id -> builder.
    COMMON_STREAMABLE: dict[int, str] = {
        mav.MAVLINK_MSG_ID_HEARTBEAT: "msg_heartbeat",
        mav.MAVLINK_MSG_ID_SYS_STATUS: "msg_sys_status",
        mav.MAVLINK_MSG_ID_SYSTEM_TIME: "msg_system_time",
        mav.MAVLINK_MSG_ID_GPS_RAW_INT: "msg_gps_raw_int",
        mav.MAVLINK_MSG_ID_ATTITUDE: "msg_attitude",
        mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: "msg_attitude_quaternion",
        mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "msg_local_position_ned",
        mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "msg_global_position_int",
        mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: "msg_gps_global_origin",
        mav.MAVLINK_MSG_ID_VFR_HUD: "msg_vfr_hud",
        mav.MAVLINK_MSG_ID_SIM_STATE: "msg_sim_state",
    }
    #: message ids this autopilot refuses to stream
    DENIED: frozenset[int] = frozenset()
    #: setpoints in EXTERNAL may lift the vehicle off the ground (PX4 offboard yes, ArduPilot no)
    EXTERNAL_CAN_TAKE_OFF = False

    def __init__(self, sim, home: Home | None = None, sysid: int = 1, seed: int | None = None):
        if not (isinstance(sysid, int) and 1 <= sysid <= 255):
            raise ValueError(f"system id must be an integer in 1..255, got {sysid!r}")
        self.sim = sim
        self.home = home or Home()
        self.sysid = sysid
        self.seed = sim.seed if seed is None else seed
        self.dt = 1.0 / sim.physics_rate_hz
        self.nav_every = max(1, round(sim.physics_rate_hz / sim.nav_rate_hz))
        self.nav_dt = self.nav_every * self.dt
        self.step_count = 0
        self.boot_unix_s = time.time()  # SYSTEM_TIME only; never feeds the physics
        streams = np.random.SeedSequence(self.seed).spawn(3)
        self.nav = GaussMarkovNavError(NavErrorSpec.from_config(sim), np.random.default_rng(streams[0]))
        self.gps = GpsReceiver(self.nav, sim.gps_noise_m, sim.gps_vel_noise_mps, np.random.default_rng(streams[1]))
        self.wind = WindModel(tuple(sim.wind_ned_mps), sim.gust_sigma_mps, sim.gust_tau_s, np.random.default_rng(streams[2]))
        self.vehicle = PointMassMultirotor(MultirotorLimits.from_config(sim), ground_down_m=self.home.start_down_m,
                                           p=[0.0, 0.0, self.home.start_down_m])
        self.vehicle.estimate_offset(self.nav.position_error_m, self.nav.velocity_error_mps)
        self.armed = False
        self.behaviour = Behaviour.HOLD
        self.hold_ned = list(self.vehicle.p)
        self.hold_yaw = 0.0
        self.goto_ned: list[float] | None = None  # a position to hold instead of stopping (reposition)
        self.takeoff_down_m = self.home.start_down_m
        self.takeoff_speed_mps = 1.5
        self.rtl_phase = "climb"
        self.has_flown = False
        self.landed_since_s = 0.0
        self.armed_since_s = 0.0
        self.origin_set = False
        self.external: Setpoint | None = None
        self.external_kind = ""
        self.external_t_s = -math.inf
        self.setpoint_times: collections.deque = collections.deque(maxlen=64)
        self.setpoints_received = 0
        self.setpoints_ignored = 0
        self.peers: dict[tuple[int, int], Peer] = {}
        self.outbox: list[tuple[str | None, object]] = []
        self.params: dict[str, Param] = {p.name: p for p in self.default_params()}
        self.unhandled: collections.Counter = collections.Counter()
        self.after_ack: list = []
        self._estimate_cache: tuple[int, dict] | None = None
        self.last_gps_s = -math.inf

    # ------------------------------------------------------------------------------------------
    # time and physics
    # ------------------------------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        """Simulated seconds since boot."""
        return self.step_count * self.dt

    @property
    def time_boot_ms(self) -> int:
        return int(self.t_s * 1000.0) & 0xFFFFFFFF

    @property
    def time_usec(self) -> int:
        return int(round(self.t_s * 1e6))

    def step(self) -> None:
        """One physics step; the slower processes (navigation error, wind, events) every ``nav_every``."""
        self.step_count += 1
        sp = self.current_setpoint()
        self.vehicle.step(self.dt, sp, self.wind.velocity_ned(), self.armed)
        if self.step_count % self.nav_every == 0:
            self.nav.step(self.nav_dt)
            self.wind.step(self.nav_dt)
            self.vehicle.estimate_offset(self.nav.position_error_m, self.nav.velocity_error_mps)
            if self.t_s - self.last_gps_s >= 1.0 / GPS_RATE_HZ - 1e-9:
                self.gps.sample()
                self.last_gps_s = self.t_s
            self.check_events()

    def run_for(self, seconds: float) -> None:
        """Advance ``seconds`` of simulated time (tests and tools; the process paces with a Clock)."""
        for _ in range(int(round(seconds / self.dt))):
            self.step()

    # ------------------------------------------------------------------------------------------
    # estimate (what is reported) vs truth
    # ------------------------------------------------------------------------------------------

    def truth(self) -> dict:
        """Truth: position/velocity NED (3,), R_nb (3, 3), quaternion (4,), yaw."""
        R = self.vehicle.rotation_body_to_ned()
        return {"p": np.array(self.vehicle.p), "v": np.array(self.vehicle.v), "R": R, "q": matrix_to_quat(R)}

    def estimate(self) -> dict:
        """The navigation estimate: truth plus the injected error (see navigation_error).

        Cached for the current physics step: several messages of one step share it (read-only).
        """
        cached = self._estimate_cache
        if cached is not None and cached[0] == self.step_count:
            return cached[1]
        R_true = self.vehicle.rotation_body_to_ned()
        R = self.nav.estimated_rotation(R_true)
        est = {
            "p": np.array(self.vehicle.p) + self.nav.position_error_m,
            "v": np.array(self.vehicle.v) + self.nav.velocity_error_mps,
            "R": R,
            "q": matrix_to_quat(R),
        }
        self._estimate_cache = (self.step_count, est)
        return est

    @property
    def position_valid(self) -> bool:
        """The EKF has an origin and uses GPS (``origin_delay_s`` after boot)."""
        return self.origin_set

    @property
    def landed(self) -> bool:
        return self.vehicle.landed

    # ------------------------------------------------------------------------------------------
    # behaviours
    # ------------------------------------------------------------------------------------------

    def enter(self, behaviour: Behaviour) -> None:
        """Start a behaviour from where the vehicle is (its estimate, as the controller sees it)."""
        est_p = [self.vehicle.p[i] + self.nav.position_error_m[i] for i in range(3)]
        self.hold_ned = est_p
        self.hold_yaw = self.vehicle.yaw
        self.goto_ned = None
        if behaviour is Behaviour.RTL:
            self.rtl_phase = "climb"
        if behaviour is not self.behaviour:
            log.info("t=%.2f behaviour %s -> %s", self.t_s, self.behaviour.value, behaviour.value)
        self.behaviour = behaviour

    def current_setpoint(self) -> Setpoint:
        b = self.behaviour
        # Holding is a zero-velocity target: the shaped reference brakes to a stop and the position
        # loop then holds where it stopped (ArduPilot's GUIDED stop, PX4's Hold braking point);
        # on the ground it means staying there however the estimate wanders.
        stop = Setpoint(velocity_ned_mps=(0.0, 0.0, 0.0), yaw_rad=self.hold_yaw)
        if self.landed and (b is Behaviour.HOLD or (b is Behaviour.EXTERNAL and not self.EXTERNAL_CAN_TAKE_OFF)):
            return stop
        if b is Behaviour.EXTERNAL:
            sp = self.external_setpoint()
            if sp is not None and (self.EXTERNAL_CAN_TAKE_OFF or not self.landed):
                return sp
            return stop
        if b is Behaviour.TAKEOFF:
            return Setpoint(position_ned_m=(self.hold_ned[0], self.hold_ned[1], self.takeoff_down_m),
                            yaw_rad=self.hold_yaw, climb_mps=self.takeoff_speed_mps)
        if b is Behaviour.LAND:
            return Setpoint(position_ned_m=(self.hold_ned[0], self.hold_ned[1], NAN),
                            velocity_ned_mps=(NAN, NAN, self.land_speed_mps()), yaw_rad=self.hold_yaw)
        if b is Behaviour.RTL:
            return self.rtl_setpoint()
        if self.goto_ned is not None:
            return Setpoint.hold(self.goto_ned, self.hold_yaw)
        return stop

    def external_setpoint(self) -> Setpoint | None:
        """The companion's last setpoint as the flavour applies it (timeouts differ)."""
        return self.external

    def rtl_setpoint(self) -> Setpoint:
        """Climb to the return altitude, fly home, descend: the common shape of both RTLs."""
        rtl_down = min(self.home.start_down_m - self.rtl_altitude_m(), self.hold_ned[2])
        p = self.vehicle.p
        if self.rtl_phase == "climb":
            if p[2] <= rtl_down + 0.5:
                self.rtl_phase = "return"
            return Setpoint(position_ned_m=(self.hold_ned[0], self.hold_ned[1], rtl_down))
        if self.rtl_phase == "return":
            if math.hypot(p[0], p[1]) < 1.0:
                self.rtl_phase = "land"
            return Setpoint(position_ned_m=(0.0, 0.0, rtl_down), yaw_follows_velocity=True)
        return Setpoint(position_ned_m=(0.0, 0.0, NAN), velocity_ned_mps=(NAN, NAN, self.land_speed_mps()))

    # flavour parameters of the behaviours
    def land_speed_mps(self) -> float:
        return 0.5

    def rtl_altitude_m(self) -> float:
        return 15.0

    def takeoff(self, altitude_above_home_m: float, speed_mps: float) -> None:
        """Climb vertically to ``altitude_above_home_m`` over the current position."""
        self.enter(Behaviour.TAKEOFF)
        self.takeoff_down_m = self.home.start_down_m - altitude_above_home_m
        self.takeoff_speed_mps = speed_mps

    # ------------------------------------------------------------------------------------------
    # events (checked at the navigation rate)
    # ------------------------------------------------------------------------------------------

    def check_events(self) -> None:
        t = self.t_s
        if not self.origin_set and t >= self.sim.origin_delay_s:
            self.origin_set = True
            self.on_origin_set()
        if self.landed:
            if self.landed_since_s < 0:
                self.landed_since_s = t
        else:
            self.landed_since_s = -1.0
            if self.armed:
                self.has_flown = True
        if self.behaviour is Behaviour.TAKEOFF and not self.landed and abs(self.vehicle.p[2] + self.nav.position_error_m[2] - self.takeoff_down_m) < 0.1:
            self.on_takeoff_complete()
        self.check_auto_disarm()
        self.check_setpoint_failsafe()
        self.check_links()

    def on_origin_set(self) -> None:
        """The EKF origin exists: announce it (flavour-specific)."""

    def on_takeoff_complete(self) -> None:
        self.enter(Behaviour.HOLD)

    def check_auto_disarm(self) -> None:
        """Disarm on the ground after the flavour's delays."""

    def check_setpoint_failsafe(self) -> None:
        """Setpoint stream lost (flavour-specific)."""

    def link_timeout_s(self) -> float:
        return 5.0

    def check_links(self) -> None:
        """Report a peer whose heartbeat stopped (and when it comes back); keep flying either way."""
        timeout = self.link_timeout_s()
        for (sysid, compid), peer in self.peers.items():
            silent = self.t_s - peer.last_heartbeat_s
            if not peer.lost and silent > timeout:
                peer.lost = True
                self.statustext(mav.MAV_SEVERITY_WARNING, f"Link lost: no heartbeat from {sysid}/{compid} for {silent:.0f} s")

    def set_armed(self, armed: bool, reason: str = "") -> None:
        if armed == self.armed:
            return
        self.armed = armed
        self.armed_since_s = self.t_s
        if armed:
            self.has_flown = False
        log.info("t=%.2f %s %s", self.t_s, "armed" if armed else "disarmed", reason)

    # ------------------------------------------------------------------------------------------
    # outgoing helpers
    # ------------------------------------------------------------------------------------------

    def send(self, link_name: str | None, msg) -> None:
        """Queue ``msg`` for one link (None = every link)."""
        self.outbox.append((link_name, msg))

    def statustext(self, severity: int, text: str) -> None:
        log.info("t=%.2f STATUSTEXT %s", self.t_s, text)
        self.send(None, mav.MAVLink_statustext_message(severity, text[:50].encode(), 0, 0))

    # ------------------------------------------------------------------------------------------
    # incoming messages
    # ------------------------------------------------------------------------------------------

    def handle(self, msg, link) -> None:
        """React to one received message. ``link`` has ``name`` and ``schedule`` (StreamSchedule)."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.sysid, AUTOPILOT_COMPONENT):
            return  # our own echo (e.g. a loopback router)
        ts = getattr(msg, "target_system", 0)
        if ts not in (0, self.sysid):
            return
        tc = getattr(msg, "target_component", 0)
        if tc not in (0, AUTOPILOT_COMPONENT):
            return
        name = msg.get_type()
        handler = getattr(self, "on_" + name.lower(), None)
        if handler is None:
            self.unhandled[name] += 1
            return
        try:
            handler(msg, link)
        except Exception as exc:  # noqa: BLE001 - one bad input must not stop the vehicle
            # a malformed message (or a value this simulator cannot take) is counted and dropped
            self.unhandled["BAD_" + name] += 1
            log.warning("t=%.2f could not handle %s from %s: %s: %s", self.t_s, name, src, type(exc).__name__, exc)

    def on_heartbeat(self, msg, link) -> None:
        if msg.type == mav.MAV_TYPE_GCS or msg.autopilot == mav.MAV_AUTOPILOT_INVALID:
            key = (msg.get_srcSystem(), msg.get_srcComponent())
            peer = self.peers.get(key)
            if peer is None:
                self.peers[key] = Peer(self.t_s)
            else:
                if peer.lost:
                    self.statustext(mav.MAV_SEVERITY_INFO, f"Link regained: heartbeat from {key[0]}/{key[1]}")
                peer.last_heartbeat_s = self.t_s
                peer.lost = False

    def on_statustext(self, msg, link) -> None:
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode(errors="replace")
        log.info("t=%.2f [%d/%d] %s", self.t_s, msg.get_srcSystem(), msg.get_srcComponent(), text.rstrip("\x00"))

    def on_timesync(self, msg, link) -> None:
        # A request (tc1 == 0) is answered with our clock in ns (MAVLink TIMESYNC protocol).
        if msg.tc1 == 0:
            self.send(link.name, mav.MAVLink_timesync_message(int(round(self.t_s * 1e9)), msg.ts1))

    def on_command_long(self, msg, link) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        self._command(msg, link, msg.command, params, frame=None)

    def on_command_int(self, msg, link) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        self._command(msg, link, msg.command, params, frame=msg.frame)

    def _command(self, msg, link, command: int, params: list[float], frame) -> None:
        handler = getattr(self, "cmd_" + mav.enums["MAV_CMD"][command].name[8:].lower(), None) \
            if command in mav.enums["MAV_CMD"] else None
        self.after_ack = []
        if handler is None:
            result = mav.MAV_RESULT_UNSUPPORTED
        else:
            result = handler(params, link, frame)
        self.send(link.name, mav.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        # messages a command asked for follow its ACK (ArduPilot defers them to the next send slot)
        for m in self.after_ack:
            self.send(link.name, m)
        self.after_ack = []

    # ---- stream control -----------------------------------------------------------------------

    def can_stream(self, msg_id: int) -> bool:
        return msg_id in self.STREAMABLE

    def refuse_stream(self, msg_id: int) -> int:
        """MAV_RESULT for a SET_MESSAGE_INTERVAL naming a message this autopilot cannot send."""
        return mav.MAV_RESULT_DENIED

    def default_interval_s(self, msg_id: int) -> float | None:
        """The interval a link starts with (and SET_MESSAGE_INTERVAL with 0 restores)."""
        return 1.0 if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT else None

    def initial_schedule(self) -> StreamSchedule:
        schedule = StreamSchedule()
        for msg_id in self.STREAMABLE:
            iv = self.default_interval_s(msg_id)
            if iv:
                schedule.set_interval(msg_id, iv, self.t_s)
        return schedule

    def cmd_set_message_interval(self, params, link, frame) -> int:
        msg_id, interval_us = int(params[0]), params[1]
        if not _finite(interval_us):
            return mav.MAV_RESULT_DENIED
        if not self.can_stream(msg_id):
            return self.refuse_stream(msg_id)
        if interval_us < 0:
            link.schedule.set_interval(msg_id, None, self.t_s)
        elif interval_us == 0:
            link.schedule.set_interval(msg_id, self.default_interval_s(msg_id), self.t_s)
        else:
            link.schedule.set_interval(msg_id, interval_us * 1e-6, self.t_s)
        return mav.MAV_RESULT_ACCEPTED

    def cmd_get_message_interval(self, params, link, frame) -> int:
        msg_id = int(params[0])
        if not self.can_stream(msg_id):
            interval_us = 0
        else:
            iv = link.schedule.interval(msg_id)
            interval_us = -1 if iv is None else int(round(iv * 1e6))
        self.send(link.name, mav.MAVLink_message_interval_message(msg_id, interval_us))
        return mav.MAV_RESULT_ACCEPTED

    def cmd_request_message(self, params, link, frame) -> int:
        msg_id = int(params[0])
        if not self.can_stream(msg_id):
            return self.refuse_request(msg_id)
        msg = self.build(msg_id)
        if msg is None:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED  # exists, but not yet (e.g. no home before origin)
        self.after_ack.append(msg)
        return mav.MAV_RESULT_ACCEPTED

    def refuse_request(self, msg_id: int) -> int:
        return mav.MAV_RESULT_FAILED

    def cmd_request_autopilot_capabilities(self, params, link, frame) -> int:
        self.after_ack.append(self.msg_autopilot_version())
        return mav.MAV_RESULT_ACCEPTED

    # ---- setpoints ----------------------------------------------------------------------------

    def decode_position_target(self, msg, local_position=None) -> PositionTarget:
        """SET_POSITION_TARGET_LOCAL_NED -> NED target (frames and type_mask applied per axis).

        ``local_position``: (n, e, d) replacing msg.x/y/z, for a SET_POSITION_TARGET_GLOBAL_INT
        already converted to the local frame (its frame is then taken as LOCAL_NED).
        """
        m = msg.type_mask
        x, y, z = local_position if local_position is not None else (msg.x, msg.y, msg.z)
        pos = [NAN if m & IGNORE_PX else x, NAN if m & IGNORE_PY else y, NAN if m & IGNORE_PZ else z]
        vel = [NAN if m & IGNORE_VX else msg.vx, NAN if m & IGNORE_VY else msg.vy, NAN if m & IGNORE_VZ else msg.vz]
        acc = [NAN if m & IGNORE_AX else msg.afx, NAN if m & IGNORE_AY else msg.afy, NAN if m & IGNORE_AZ else msg.afz]
        yaw = NAN if m & IGNORE_YAW else msg.yaw
        yaw_rate = NAN if m & IGNORE_YAW_RATE else msg.yaw_rate
        frame = mav.MAV_FRAME_LOCAL_NED if local_position is not None else msg.coordinate_frame
        est = self.estimate()
        if frame in (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED):
            # body frames: x forward / y right in the horizontal plane, rotated by heading
            c, s = math.cos(self.vehicle.yaw), math.sin(self.vehicle.yaw)
            for vec in (pos, vel, acc):
                x, y = vec[0], vec[1]
                vec[0], vec[1] = c * x - s * y, s * x + c * y
            if _finite(yaw):
                yaw = self.vehicle.yaw + yaw
        if frame in (mav.MAV_FRAME_LOCAL_OFFSET_NED, mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED):
            pos = [pos[i] + est["p"][i] for i in range(3)]
        return PositionTarget(pos, vel, acc, yaw, yaw_rate, m, frame)

    def accept_external(self, sp: Setpoint, kind: str) -> None:
        self.external = sp
        self.external_kind = kind
        self.external_t_s = self.t_s

    def note_setpoint(self) -> None:
        self.setpoints_received += 1
        self.setpoint_times.append(self.t_s)

    # ---- parameters ---------------------------------------------------------------------------

    def default_params(self) -> list[Param]:
        return []

    def param(self, name: str) -> float:
        return self.params[name].value

    def encode_param(self, p: Param) -> float:
        """The float on the wire (ArduPilot: C cast; PX4 overrides with bytewise integers)."""
        return float(p.value)

    def decode_param(self, value: float, ptype: int) -> float:
        if ptype in (mav.MAV_PARAM_TYPE_REAL32, mav.MAV_PARAM_TYPE_REAL64):
            return float(value)
        return float(int(round(value)))

    def _param_value_msg(self, index: int, p: Param):
        return mav.MAVLink_param_value_message(p.name.encode(), self.encode_param(p), p.ptype, len(self.params), index)

    def on_param_request_list(self, msg, link) -> None:
        for i, p in enumerate(self.params.values()):
            self.send(link.name, self._param_value_msg(i, p))

    def on_param_request_read(self, msg, link) -> None:
        names = list(self.params)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self.send(link.name, self._param_value_msg(msg.param_index, self.params[names[msg.param_index]]))
            return
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
        if name in self.params:
            self.send(link.name, self._param_value_msg(names.index(name), self.params[name]))

    def on_param_set(self, msg, link) -> None:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
        p = self.params.get(name)
        if p is None:
            self.unhandled["PARAM_SET_UNKNOWN"] += 1
            return
        value = self.decode_param(msg.param_value, p.ptype)
        if not _finite(value):
            self.unhandled["PARAM_SET_BAD"] += 1
            return
        p.value = value
        self.send(None, self._param_value_msg(list(self.params).index(name), p))

    # ---- missions (none: the simulator flies setpoints) ----------------------------------------

    def on_mission_request_list(self, msg, link) -> None:
        self.send(link.name, mav.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                                                getattr(msg, "mission_type", 0), 0))

    # ------------------------------------------------------------------------------------------
    # telemetry builders (None = not available now)
    # ------------------------------------------------------------------------------------------

    def build(self, msg_id: int):
        name = self.STREAMABLE.get(msg_id)
        return getattr(self, name)() if name else None

    def heartbeat_base_mode(self) -> int:
        return mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)

    def custom_mode(self) -> int:
        return 0

    def msg_heartbeat(self):
        status = mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(self.VEHICLE_TYPE, self.AUTOPILOT, self.heartbeat_base_mode(),
                                             self.custom_mode(), status, 3)

    def sensors(self) -> tuple[int, int, int]:
        """SYS_STATUS (present, enabled, health) bitmasks."""
        present = (mav.MAV_SYS_STATUS_SENSOR_3D_GYRO | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
                   | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | mav.MAV_SYS_STATUS_SENSOR_GPS
                   | mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mav.MAV_SYS_STATUS_AHRS | mav.MAV_SYS_STATUS_PREARM_CHECK)
        health = present
        if not self.position_valid:
            health &= ~(mav.MAV_SYS_STATUS_SENSOR_GPS | mav.MAV_SYS_STATUS_PREARM_CHECK)
        return present, present, health

    def msg_sys_status(self):
        present, enabled, health = self.sensors()
        return mav.MAVLink_sys_status_message(present, enabled, health, 250, 12600, 1500 if self.armed else 0,
                                              95, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def msg_system_time(self):
        return mav.MAVLink_system_time_message(int((self.boot_unix_s + self.t_s) * 1e6), self.time_boot_ms)

    def _body_rates(self) -> np.ndarray:
        return self.vehicle.angular_velocity_body()

    def msg_attitude(self):
        est = self.estimate()
        roll, pitch, yaw = (float(a) for a in matrix_to_euler(est["R"]))
        w = self._body_rates()
        return mav.MAVLink_attitude_message(self.time_boot_ms, roll, pitch, yaw, float(w[0]), float(w[1]), float(w[2]))

    def msg_attitude_quaternion(self):
        q = self.estimate()["q"]
        w = self._body_rates()
        return mav.MAVLink_attitude_quaternion_message(self.time_boot_ms, *(float(x) for x in q),
                                                       float(w[0]), float(w[1]), float(w[2]), [0.0, 0.0, 0.0, 0.0])

    def msg_local_position_ned(self):
        if not self.position_valid:
            return None
        est = self.estimate()
        p, v = est["p"], est["v"]
        return mav.MAVLink_local_position_ned_message(self.time_boot_ms, *(float(x) for x in p), *(float(x) for x in v))

    def _heading_cdeg(self, R: np.ndarray) -> int:
        yaw = float(matrix_to_euler(R)[2])
        return int(round(math.degrees(yaw) % 360.0 * 100)) % 36000

    def msg_global_position_int(self):
        if not self.position_valid:
            return mav.MAVLink_global_position_int_message(self.time_boot_ms, 0, 0, 0, 0, 0, 0, 0, 65535)
        est = self.estimate()
        p, v = est["p"], est["v"]
        lat, lon, alt = self.home.ned_to_global(*p)
        rel = self.home.start_down_m - p[2]
        return mav.MAVLink_global_position_int_message(
            self.time_boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), int(round(rel * 1000)),
            int(round(v[0] * 100)), int(round(v[1] * 100)), int(round(v[2] * 100)), self._heading_cdeg(est["R"]))

    def msg_gps_raw_int(self):
        fix = self.gps.fix
        if not self.position_valid:
            return mav.MAVLink_gps_raw_int_message(self.time_usec, mav.GPS_FIX_TYPE_NO_FIX, 0, 0, 0, 65535, 65535, 0,
                                                   65535, 3, 0, 0, 0, 0, 0, 0)
        p = np.array(self.vehicle.p) + fix.position_error_m
        v = np.array(self.vehicle.v) + fix.velocity_error_mps
        lat, lon, alt = self.home.ned_to_global(*p)
        speed = math.hypot(v[0], v[1])
        cog = int(round(math.degrees(math.atan2(v[1], v[0])) % 360.0 * 100)) % 36000 if speed > 0.2 else 65535
        return mav.MAVLink_gps_raw_int_message(
            self.time_usec, mav.GPS_FIX_TYPE_3D_FIX, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            min(65534, int(round(fix.h_acc_m * 100))), min(65534, int(round(fix.v_acc_m * 100))),
            int(round(speed * 100)), cog, 14, int(round(alt * 1000)),
            int(round(fix.h_acc_m * 1000)), int(round(fix.v_acc_m * 1000)), int(round(fix.vel_acc_mps * 1000)), 0, 0)

    def msg_gps_global_origin(self):
        if not self.position_valid:
            return None
        return mav.MAVLink_gps_global_origin_message(int(round(self.home.lat_deg * 1e7)), int(round(self.home.lon_deg * 1e7)),
                                                     int(round(self.home.alt_m * 1000)), self.time_usec)

    def msg_home_position(self):
        if not self.position_valid:
            return None
        lat, lon, alt = self.home.ned_to_global(0.0, 0.0, self.home.start_down_m)
        return mav.MAVLink_home_position_message(int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                                                 0.0, 0.0, self.home.start_down_m, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.time_usec)

    def landed_state(self) -> int:
        if self.landed:
            return mav.MAV_LANDED_STATE_ON_GROUND
        if self.behaviour is Behaviour.TAKEOFF:
            return mav.MAV_LANDED_STATE_TAKEOFF
        if self.behaviour is Behaviour.LAND or (self.behaviour is Behaviour.RTL and self.rtl_phase == "land"):
            return mav.MAV_LANDED_STATE_LANDING
        return mav.MAV_LANDED_STATE_IN_AIR

    def msg_extended_sys_state(self):
        return mav.MAVLink_extended_sys_state_message(mav.MAV_VTOL_STATE_UNDEFINED, self.landed_state())

    def msg_vfr_hud(self):
        est = self.estimate()
        v = est["v"]
        w = self.wind.velocity_ned()
        air = math.hypot(v[0] - w[0], v[1] - w[1])
        thrust = math.sqrt(sum(x * x for x in self.vehicle.thrust)) / (2.0 * GRAVITY_MPS2)
        alt = self.home.alt_m - est["p"][2]
        return mav.MAVLink_vfr_hud_message(air, math.hypot(v[0], v[1]), self._heading_cdeg(est["R"]) // 100,
                                           int(round(100 * thrust)) if self.armed else 0, alt, -v[2])

    def msg_sim_state(self):
        """SIM_STATE (108): the simulator's truth (ArduPilot SITL streams it on request)."""
        tr = self.truth()
        roll, pitch, yaw = (float(a) for a in matrix_to_euler(tr["R"]))
        lat, lon, alt = self.home.ned_to_global(*tr["p"])
        f = self.vehicle.specific_force_body()
        w = self._body_rates()
        q = tr["q"]
        return mav.MAVLink_sim_state_message(
            float(q[0]), float(q[1]), float(q[2]), float(q[3]), roll, pitch, yaw,
            float(f[0]), float(f[1]), float(f[2]), float(w[0]), float(w[1]), float(w[2]),
            float(lat), float(lon), float(alt), 0.0, 0.0,
            float(tr["v"][0]), float(tr["v"][1]), float(tr["v"][2]),
            int(round(lat * 1e7)), int(round(lon * 1e7)))

    def firmware_version(self) -> tuple[int, int, int]:
        return (0, 0, 0)

    def capabilities(self) -> int:
        return (mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT | mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2)

    def msg_autopilot_version(self):
        major, minor, patch = self.firmware_version()
        sw = (major << 24) | (minor << 16) | (patch << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL
        uid2 = list(struct.pack("<I", self.seed & 0xFFFFFFFF)) + [0] * 14
        return mav.MAVLink_autopilot_version_message(self.capabilities(), sw, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
                                                     0, 0, 0x5EED0000 + self.sysid, uid2)
