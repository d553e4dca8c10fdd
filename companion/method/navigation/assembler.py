"""NavState assembly from what the autopilot actually sends.

Pure: messages go in as decoded objects (pymavlink messages: ``msg.get_type()`` and attributes)
or plain dicts (``{"mavpackettype": "LOCAL_POSITION_NED", "x": ...}``, as ``msg.to_dict()`` gives), with the companion time
at which they arrived; :class:`NavState` comes out. No sockets here (``drivers/autopilot/``
owns the link), so every model can be tested from numbers alone.

State
    ``LOCAL_POSITION_NED`` (position, velocity) and ``ATTITUDE_QUATERNION`` (attitude, body rates),
    or ``ODOMETRY`` (all of it). A state is emitted at the time of every position or attitude
    message; the other half is carried to that time (position by its velocity, attitude by its
    body rates), and only if it is at most ``nav.max_skew_s`` away.

Covariance (9x9 over [position m, velocity m/s, attitude error rad]): each message's evidence is
validated and converted here on arrival, and the models of :mod:`~companion.method.navigation.covariance`
choose per block from the best evidence that is valid and younger than ``nav.covariance_max_age_s``;
:attr:`NavState.covariance_source` names the messages used.

Bad inputs are rejected and counted per reason (:class:`RejectionCounter`): non-finite positions,
quaternions off unit norm by more than 1e-3 (slightly off: normalised), negative or non-finite
variances, covariances that are not positive semi-definite (the covariance is dropped and the
next model is used; the state itself is kept).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import NavConfig
from companion.method.geometry import quat_to_matrix
from companion.method.messages import NavState
from companion.method.navigation.covariance import (
    EVIDENCE_KINDS,
    Evidence,
    covariance_block,
    covariance_from_evidence,
    covariance_problem,
    euler_covariance_to_rotvec,
    euler_rate_jacobian_ned,
    quat_to_euler,
    reported_covariance,
    source_string,
)

# --------------------------------------------------------------------------------------------
# MAVLink constants used here (values from common.xml / ardupilotmega.xml)
# --------------------------------------------------------------------------------------------

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_VISION_NED = 16
MAV_FRAME_ESTIM_NED = 18
MAV_FRAME_LOCAL_FRD = 20
LOCAL_POSE_FRAMES = frozenset({MAV_FRAME_LOCAL_NED, MAV_FRAME_VISION_NED, MAV_FRAME_ESTIM_NED, MAV_FRAME_LOCAL_FRD})
LOCAL_VELOCITY_FRAMES = LOCAL_POSE_FRAMES | {MAV_FRAME_BODY_NED}

# SIM_STATE arriving this soon (companion seconds) after an attitude message was sent right after it
# in the same simulator step (both simulators here, and ArduPilot SITL at equal stream rates): it
# takes that attitude's time. Messages of one step arrive back to back, in the same read as a rule.
TRUTH_PAIR_WINDOW_S = 0.01

# EKF_STATUS_FLAGS (ArduPilot) and ESTIMATOR_STATUS_FLAGS (common) share the low bits.
EKF_ATTITUDE = 1
EKF_VELOCITY_HORIZ = 2
EKF_VELOCITY_VERT = 4
EKF_POS_HORIZ_REL = 8
EKF_POS_VERT_ABS = 32
EKF_CONST_POS_MODE = 128
EKF_UNINITIALIZED = 1024  # ArduPilot
EKF_GPS_GLITCHING = 32768  # ArduPilot
ESTIMATOR_GPS_GLITCH = 1024  # common (PX4)
ESTIMATOR_ACCEL_ERROR = 2048  # common (PX4)
REQUIRED_FLAGS = {
    EKF_ATTITUDE: "ATTITUDE",
    EKF_VELOCITY_HORIZ: "VELOCITY_HORIZ",
    EKF_VELOCITY_VERT: "VELOCITY_VERT",
    EKF_POS_HORIZ_REL: "POS_HORIZ_REL",
    EKF_POS_VERT_ABS: "POS_VERT_ABS",
}
BAD_FLAGS_ARDUPILOT = {EKF_CONST_POS_MODE: "CONST_POS_MODE", EKF_UNINITIALIZED: "UNINITIALIZED", EKF_GPS_GLITCHING: "GPS_GLITCHING"}
BAD_FLAGS_ESTIMATOR = {EKF_CONST_POS_MODE: "CONST_POS_MODE", ESTIMATOR_GPS_GLITCH: "GPS_GLITCH", ESTIMATOR_ACCEL_ERROR: "ACCEL_ERROR"}

GPS_FIX_TYPE_3D = 3
UNIX_EPOCH_THRESHOLD_US = 10**15  # time_usec above this (year 2001) is UNIX time, below it is boot time
QUATERNION_NORM_TOLERANCE = 1e-3
POSITION_LIMIT_M = 1e7  # a local NED coordinate beyond this is corrupt, not a flight
# A synchronised stamp this far after the message's arrival is corrupt: a message cannot come from
# the future, and the time mapping is good to half the best round trips (ms on a wire; tens of ms of
# clock time in a simulation sped up 10x on a loaded machine). This also bounds how long one corrupt
# stamp that passes the CRC can hold up the (time-ordered) buffer.
MAX_FUTURE_S = 0.25
BASIS_SYNCHRONISED = "autopilot clock (synchronised)"
BASIS_ARRIVAL = "arrival time (not synchronised)"
ARDUPILOT_EARTH_RADIUS_M = 6378100.0  # ArduPilot's LOCATION_SCALING_FACTOR = R * pi / 180 * 1e-7

# The messages this module reads (the link requests them).
STATE_MESSAGES = ("LOCAL_POSITION_NED", "ATTITUDE_QUATERNION", "ODOMETRY")
COVARIANCE_MESSAGES = ("LOCAL_POSITION_NED_COV", "ATTITUDE_QUATERNION_COV", "ESTIMATOR_STATUS", "EKF_STATUS_REPORT", "GPS_RAW_INT")
CONTEXT_MESSAGES = ("SYSTEM_TIME", "GPS_GLOBAL_ORIGIN", "HOME_POSITION", "SIM_STATE")
HANDLED_MESSAGES = frozenset(STATE_MESSAGES + COVARIANCE_MESSAGES + CONTEXT_MESSAGES)


def geodetic_to_ned(lat_deg: float, lon_deg: float, alt_m: float, origin: "GeoOrigin") -> np.ndarray:
    """Local NED (3,) of a WGS84 point relative to ``origin``, ArduPilot's flat-earth convention.

    ArduPilot's ``Location::get_distance_NE``: north = dlat * R * pi/180, east = dlon * R * pi/180 *
    cos(mean latitude), with R = 6378100 m; down = origin altitude - altitude (both AMSL). Using the
    autopilot's own convention keeps a truth pose in the same local frame as LOCAL_POSITION_NED.
    """
    k = ARDUPILOT_EARTH_RADIUS_M * math.pi / 180.0
    dlon = (lon_deg - origin.lon_deg + 180.0) % 360.0 - 180.0
    north = (lat_deg - origin.lat_deg) * k
    east = dlon * k * math.cos(math.radians(0.5 * (lat_deg + origin.lat_deg)))
    return np.array([north, east, origin.alt_m - alt_m])


# --------------------------------------------------------------------------------------------
# Small records
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class GeoOrigin:
    """WGS84 origin of the local NED frame (deg, deg, m AMSL) and where it came from."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    source: str  # "GPS_GLOBAL_ORIGIN" or "HOME_POSITION"


@dataclass(frozen=True, slots=True)
class TruthPose:
    """Simulator truth (SIM_STATE) in the autopilot's local NED frame.

    t_s: companion time of the truth. SIM_STATE carries no timestamp of its own; a simulator sends
    it right after the attitude of the same step, so when the attitude arrived just before it
    (within ``TRUTH_PAIR_WINDOW_S``) ``t_s`` is that attitude's sample time (``time_source`` names
    the message), else the arrival time (``time_source`` "arrival").
    position_ned_m, velocity_ned_mps: (3,); quaternion_wxyz: (4,) body->NED.
    """

    t_s: float
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray
    quaternion_wxyz: np.ndarray
    origin_source: str
    time_source: str = "arrival"


@dataclass(slots=True)
class RejectionCounter:
    """Counts of rejected inputs per reason (a bounded set of keys), with the last detail of each.

    ``listener(reason, detail)``, if set, hears every rejection (the link logs them, rate-limited).
    """

    counts: dict[str, int] = field(default_factory=dict)
    details: dict[str, str] = field(default_factory=dict)
    listener: Callable[[str, str], None] | None = None

    def add(self, reason: str, detail: str = "") -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1
        if detail:
            self.details[reason] = detail
        if self.listener is not None:
            self.listener(reason, detail)

    def total(self) -> int:
        return sum(self.counts.values())

    def snapshot(self) -> dict[str, int]:
        return dict(self.counts)


@dataclass(slots=True)
class _Position:
    t: float  # companion time of validity
    p: np.ndarray
    v: np.ndarray


@dataclass(slots=True)
class _Attitude:
    t: float
    q: np.ndarray
    omega_b: np.ndarray  # body rates (rad/s), FRD
    t_rx: float = -math.inf  # arrival (companion clock)
    kind: str = ""


# --------------------------------------------------------------------------------------------
# Message access
# --------------------------------------------------------------------------------------------


def message_type(msg: Any) -> str:
    if isinstance(msg, dict):
        return str(msg.get("mavpackettype", ""))
    return msg.get_type()


def _get(msg: Any, name: str, default: Any = None) -> Any:
    # isinstance(dict) rather than Mapping: the ABC check costs more than the rest of a field read
    if isinstance(msg, dict):
        return msg.get(name, default)
    return getattr(msg, name, default)


_MISSING = object()


def _floats(msg: Any, *names: str) -> np.ndarray:
    """Named float fields; a missing field is a malformed message (ValueError), not a NaN."""
    values = []
    for n in names:
        v = _get(msg, n, _MISSING)
        if v is _MISSING:
            raise ValueError(f"field {n!r} missing")
        values.append(float(v))
    return np.array(values)


# --------------------------------------------------------------------------------------------
# The assembler
# --------------------------------------------------------------------------------------------


class NavAssembler:
    """Keeps the latest of each navigation message and produces NavState.

    cfg: the ``nav`` section (floors, ages, ratio threshold).
    time_map: autopilot boot time (s) -> companion time (s), or None when not synchronised
        (e.g. :meth:`companion.method.navigation.timesync.TimeSync.to_companion`); without a mapping the arrival time
        is used and :attr:`time_basis` says so.

    Time bases are never mixed: when the basis changes (arrival time -> synchronised, or back after
    the time mapping was reset) the stored halves are dropped and :attr:`time_basis_changes` counts
    it, so the link can clear its buffer too. A state stamped more than ``MAX_FUTURE_S`` after its
    arrival is rejected (a corrupt stamp would otherwise sit at the head of the buffer and make every
    genuine state after it look out of order).
    """

    def __init__(self, cfg: NavConfig | None = None, time_map: Callable[[float], float | None] | None = None) -> None:
        self.cfg = cfg or NavConfig()
        self.time_map = time_map
        self.rejections = RejectionCounter()
        self.reset()

    def reset(self) -> None:
        """Forget everything received (autopilot reboot, new link). Counters are kept."""
        self._pos: _Position | None = None
        self._att: _Attitude | None = None
        self._evidence: dict[str, Evidence] = {}
        self._evidence_version = 0
        self._covariance_cache: tuple[tuple, np.ndarray, str] | None = None
        self._unix_minus_boot_s: float | None = None
        self._last_emitted_t = -math.inf
        self._odometry_reset_counter: int | None = None
        self.estimator_resets = 0
        self.origin: GeoOrigin | None = None
        self._home: tuple[float, float, float, np.ndarray] | None = None
        self._truth: TruthPose | None = None
        self.truth_paired = 0    # SIM_STATE stamped with the attitude it followed
        self.truth_unpaired = 0  # ... with its arrival time (no attitude just before it)
        self.time_basis = "none"
        self.time_basis_changes = 0
        self.last_covariance_blocks: dict[str, str] = {}
        self.superseded = 0

    # ------------------------------------------------------------------------------------------
    # Floors
    # ------------------------------------------------------------------------------------------

    @property
    def floor_sigmas(self) -> np.ndarray:
        """(9,) lower bounds on the marginal sigmas [pos x3 m, vel x3 m/s, att x3 rad]."""
        c = self.cfg
        return np.r_[
            np.full(3, c.position_sigma_floor_m),
            np.full(3, c.velocity_sigma_floor_mps),
            math.radians(c.attitude_sigma_floor_deg),
            math.radians(c.attitude_sigma_floor_deg),
            math.radians(max(c.attitude_sigma_floor_deg, c.yaw_sigma_floor_deg)),  # heading: its own floor
        ]

    def _set_evidence(self, kind: str, ev: Evidence) -> None:
        self._evidence[kind] = ev
        self._evidence_version += 1

    def _drop_evidence(self, kind: str) -> None:
        if self._evidence.pop(kind, None) is not None:
            self._evidence_version += 1

    # ------------------------------------------------------------------------------------------
    # Time
    # ------------------------------------------------------------------------------------------

    def _companion_time(self, kind: str, t_remote_s: float | None, t_rx: float) -> float | None:
        """Companion time of an autopilot boot-clock time; the arrival time when that is impossible.

        None (rejected, counted) when the mapped time lies more than ``MAX_FUTURE_S`` after arrival.
        """
        t, basis = t_rx, BASIS_ARRIVAL
        if t_remote_s is not None and t_remote_s > 0 and self.time_map is not None:
            mapped = self.time_map(t_remote_s)
            if mapped is not None and math.isfinite(mapped):
                t, basis = float(mapped), BASIS_SYNCHRONISED
        if t > t_rx + MAX_FUTURE_S:
            self._reject(kind, "timestamp in the future", f"{t - t_rx:.3f} s after arrival")
            return None
        if basis != self.time_basis:
            if self.time_basis != "none":
                self.time_basis_changes += 1
            self.forget_state()
            self.time_basis = basis
        return t

    def forget_state(self) -> None:
        """Drop the stored position and attitude halves (their times belong to another time base)."""
        self._pos = None
        self._att = None
        self._last_emitted_t = -math.inf

    def _time_usec_to_boot_s(self, time_usec: Any) -> float | None:
        """``time_usec`` (boot or UNIX, MAVLink lets the magnitude decide) -> boot seconds, or None."""
        try:
            us = int(time_usec)
        except (TypeError, ValueError):
            return None
        if us <= 0:
            return None
        if us < UNIX_EPOCH_THRESHOLD_US:
            return us * 1e-6
        if self._unix_minus_boot_s is None:  # UNIX time before any SYSTEM_TIME: cannot map
            return None
        return us * 1e-6 - self._unix_minus_boot_s

    # ------------------------------------------------------------------------------------------
    # Input
    # ------------------------------------------------------------------------------------------

    def update(self, msg: Any, t_rx: float) -> NavState | None:
        """Take one message received at companion time ``t_rx``; return a NavState when one is produced."""
        kind = message_type(msg)
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is None:
            return None
        try:
            return handler(msg, t_rx)
        except (TypeError, ValueError, AttributeError, IndexError) as exc:  # malformed decoded object
            self.rejections.add(f"{kind}: malformed", str(exc))
            return None

    def _reject(self, kind: str, reason: str, detail: str = "") -> None:
        self.rejections.add(f"{kind}: {reason}", detail)

    def _valid_vector(self, kind: str, what: str, v: np.ndarray) -> bool:
        if not all(math.isfinite(x) for x in v):
            self._reject(kind, f"non-finite {what}", str(v))
            return False
        if max(abs(v[0]), abs(v[1]), abs(v[2])) > POSITION_LIMIT_M:
            self._reject(kind, f"{what} out of range", str(v))
            return False
        return True

    def _valid_quaternion(self, kind: str, q: np.ndarray) -> np.ndarray | None:
        if not np.all(np.isfinite(q)):
            self._reject(kind, "non-finite quaternion", str(q))
            return None
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            self._reject(kind, "non-unit quaternion", f"norm {norm:.6f}")
            return None
        return q / norm

    def _body_rates(self, kind: str, msg: Any) -> np.ndarray:
        w = _floats(msg, "rollspeed", "pitchspeed", "yawspeed")
        if not np.all(np.isfinite(w)):
            self._reject(kind, "non-finite body rates", str(w))  # state kept, rates not used
            return np.zeros(3)
        return w

    # --- state messages --------------------------------------------------------------------------

    def _on_local_position_ned(self, msg: Any, t_rx: float) -> NavState | None:
        kind = "LOCAL_POSITION_NED"
        p = _floats(msg, "x", "y", "z")
        v = _floats(msg, "vx", "vy", "vz")
        if not (self._valid_vector(kind, "position", p) and self._valid_vector(kind, "velocity", v)):
            return None
        t = self._companion_time(kind, _get(msg, "time_boot_ms", 0) * 1e-3, t_rx)
        if t is None:
            return None
        self._pos = _Position(t, p, v)
        return self._assemble(t, t_rx)

    def _on_attitude_quaternion(self, msg: Any, t_rx: float) -> NavState | None:
        kind = "ATTITUDE_QUATERNION"
        q = self._valid_quaternion(kind, _floats(msg, "q1", "q2", "q3", "q4"))
        if q is None:
            return None
        t = self._companion_time(kind, _get(msg, "time_boot_ms", 0) * 1e-3, t_rx)
        if t is None:
            return None
        self._att = _Attitude(t, q, self._body_rates(kind, msg), t_rx, kind)
        return self._assemble(t, t_rx)

    def _on_odometry(self, msg: Any, t_rx: float) -> NavState | None:
        kind = "ODOMETRY"
        frame, child = int(_get(msg, "frame_id", 0)), int(_get(msg, "child_frame_id", 0))
        if frame not in LOCAL_POSE_FRAMES:
            self._reject(kind, "unsupported frame_id", str(frame))
            return None
        p = _floats(msg, "x", "y", "z")
        v = _floats(msg, "vx", "vy", "vz")
        q = self._valid_quaternion(kind, np.asarray(_get(msg, "q"), dtype=float).reshape(4))
        if q is None or not (self._valid_vector(kind, "position", p) and self._valid_vector(kind, "velocity", v)):
            return None
        if child == MAV_FRAME_BODY_FRD:
            R = quat_to_matrix(q)  # velocity (and its covariance) given in the body frame
        elif child in LOCAL_VELOCITY_FRAMES:
            R = None
        else:
            self._reject(kind, "unsupported child_frame_id", str(child))
            return None
        if R is not None:
            v = R @ v
        t = self._companion_time(kind, self._time_usec_to_boot_s(_get(msg, "time_usec", 0)), t_rx)
        if t is None:  # a corrupt stamp: nothing of this message is used
            return None
        reset_counter = int(_get(msg, "reset_counter", 0))
        if self._odometry_reset_counter is not None and reset_counter != self._odometry_reset_counter:
            self.estimator_resets += 1
        self._odometry_reset_counter = reset_counter

        ev = Evidence(t_rx)
        pose, problem = reported_covariance(_get(msg, "pose_covariance"), 6)
        if problem:
            self._reject(kind, f"pose {problem}")
        elif pose is not None:
            pos_cov, p_problem = covariance_block(pose, slice(0, 3))
            rpy_cov, a_problem = covariance_block(pose, slice(3, 6))
            if pos_cov is not None and rpy_cov is not None:
                _, p_problem = covariance_block(pose, slice(0, 6))  # the joint matrix must be PSD too
                a_problem = p_problem
            if p_problem or a_problem:
                self._reject(kind, f"pose {p_problem or a_problem}")
            else:
                E = euler_rate_jacobian_ned(*quat_to_euler(q))
                ev.pos = pos_cov
                ev.att = None if rpy_cov is None else E @ rpy_cov @ E.T
                if pos_cov is not None and rpy_cov is not None:
                    ev.pos_att = pose[:3, 3:] @ E.T
        twist, problem = reported_covariance(_get(msg, "velocity_covariance"), 6)
        vel_cov = None
        if twist is not None:
            vel_cov, problem = covariance_block(twist, slice(0, 3))  # the angular-rate part is not used
        if problem:
            self._reject(kind, f"velocity {problem}")
        elif vel_cov is not None:
            ev.vel = vel_cov if R is None else R @ vel_cov @ R.T
        self._set_evidence(kind, ev)

        self._pos = _Position(t, p, v)
        self._att = _Attitude(t, q, self._body_rates(kind, msg), t_rx, kind)
        return self._assemble(t, t_rx)

    # --- covariance evidence ---------------------------------------------------------------------

    def _on_local_position_ned_cov(self, msg: Any, t_rx: float) -> None:
        kind = "LOCAL_POSITION_NED_COV"
        self._drop_evidence(kind)
        P, problem = reported_covariance(_get(msg, "covariance"), 9)
        if problem is None and P is not None:
            pos, problem = covariance_block(P, slice(0, 3))
            vel, problem2 = covariance_block(P, slice(3, 6))
            problem = problem or problem2
            if problem is None and pos is not None and vel is not None:
                _, problem = covariance_block(P, slice(0, 6))
            if problem is None and pos is not None and vel is not None:  # the model needs both blocks
                self._set_evidence(kind, Evidence(t_rx, pos=pos, vel=vel, pos_vel=P[:3, 3:6].copy()))
        if problem:
            self._reject(kind, problem)
        return None

    def _on_attitude_quaternion_cov(self, msg: Any, t_rx: float) -> None:
        kind = "ATTITUDE_QUATERNION_COV"
        q = self._valid_quaternion(kind, np.asarray(_get(msg, "q"), dtype=float).reshape(4))
        if q is None:
            return None
        values = np.asarray(_get(msg, "covariance"), dtype=float).reshape(-1)
        if values.size != 9 or math.isnan(values[0]):
            self._drop_evidence(kind)
            return None
        P = values.reshape(3, 3)
        P = np.where(np.isnan(P) & ~np.eye(3, dtype=bool), 0.0, P)
        problem = covariance_problem(0.5 * (P + P.T)) if np.allclose(P, P.T, rtol=1e-4, atol=1e-12) else "covariance not symmetric"
        if problem:
            self._reject(kind, problem)
            self._drop_evidence(kind)
            return None
        self._set_evidence(kind, Evidence(t_rx, att=euler_covariance_to_rotvec(0.5 * (P + P.T), q)))
        return None

    def _on_estimator_status(self, msg: Any, t_rx: float) -> None:
        kind = "ESTIMATOR_STATUS"
        ev = Evidence(t_rx)
        h, vert = float(_get(msg, "pos_horiz_accuracy", math.nan)), float(_get(msg, "pos_vert_accuracy", math.nan))
        if math.isfinite(h) and math.isfinite(vert) and h > 0 and vert > 0:
            # PX4 reports eph = sqrt(P_nn + P_ee): split equally between north and east.
            ev.pos = np.diag([h * h / 2, h * h / 2, vert * vert])
        elif (math.isfinite(h) and h < 0) or (math.isfinite(vert) and vert < 0):
            self._reject(kind, "negative accuracy", f"{h} {vert}")
        ev.values = {
            "vel_ratio": float(_get(msg, "vel_ratio", math.nan)),
            "mag_ratio": float(_get(msg, "mag_ratio", math.nan)),
            "flags": float(_get(msg, "flags", 0)),
        }
        self._set_evidence(kind, ev)
        return None

    def _on_ekf_status_report(self, msg: Any, t_rx: float) -> None:
        names = ("velocity_variance", "pos_horiz_variance", "pos_vert_variance", "compass_variance")
        values = {n: float(_get(msg, n, math.nan)) for n in names}
        if any(not math.isfinite(x) or x < 0 for x in values.values()):
            self._reject("EKF_STATUS_REPORT", "negative or non-finite test ratio", str(values))
            return None
        values["flags"] = float(_get(msg, "flags", 0))
        self._set_evidence("EKF_STATUS_REPORT", Evidence(t_rx, values=values))
        return None

    def _on_gps_raw_int(self, msg: Any, t_rx: float) -> None:
        fix = int(_get(msg, "fix_type", 0))
        # h_acc/v_acc (mm) and vel_acc (mm/s) are MAVLink 2 extensions: 0 means unknown.
        values = {
            "h_acc_m": int(_get(msg, "h_acc", 0)) * 1e-3,
            "v_acc_m": int(_get(msg, "v_acc", 0)) * 1e-3,
            "vel_acc_mps": int(_get(msg, "vel_acc", 0)) * 1e-3,
        }
        if fix < GPS_FIX_TYPE_3D:
            self._drop_evidence("GPS_RAW_INT")
            return None
        self._set_evidence("GPS_RAW_INT", Evidence(t_rx, values=values))
        return None

    # --- context ---------------------------------------------------------------------------------

    def _on_system_time(self, msg: Any, t_rx: float) -> None:
        unix_us, boot_ms = int(_get(msg, "time_unix_usec", 0)), int(_get(msg, "time_boot_ms", 0))
        if unix_us > UNIX_EPOCH_THRESHOLD_US and boot_ms > 0:
            self._unix_minus_boot_s = unix_us * 1e-6 - boot_ms * 1e-3
        return None

    def _on_gps_global_origin(self, msg: Any, t_rx: float) -> None:
        lat, lon = int(_get(msg, "latitude")) * 1e-7, int(_get(msg, "longitude")) * 1e-7
        alt = int(_get(msg, "altitude")) * 1e-3
        if abs(lat) > 90 or abs(lon) > 180:
            self._reject("GPS_GLOBAL_ORIGIN", "latitude/longitude out of range", f"{lat} {lon}")
            return None
        self.origin = GeoOrigin(lat, lon, alt, "GPS_GLOBAL_ORIGIN")
        return None

    def _on_home_position(self, msg: Any, t_rx: float) -> None:
        lat, lon = int(_get(msg, "latitude")) * 1e-7, int(_get(msg, "longitude")) * 1e-7
        alt = int(_get(msg, "altitude")) * 1e-3
        xyz = _floats(msg, "x", "y", "z")
        if abs(lat) > 90 or abs(lon) > 180 or not np.all(np.isfinite(xyz)):
            self._reject("HOME_POSITION", "position out of range", f"{lat} {lon} {xyz}")
            return None
        if self.origin is None or self.origin.source == "HOME_POSITION":
            # Home sits at local xyz: step back by xyz to the origin (flat earth, as in geodetic_to_ned).
            k = ARDUPILOT_EARTH_RADIUS_M * math.pi / 180.0
            o_lat = lat - xyz[0] / k
            o_lon = lon - xyz[1] / (k * math.cos(math.radians(0.5 * (lat + o_lat))))
            self.origin = GeoOrigin(o_lat, o_lon, alt + xyz[2], "HOME_POSITION")
        return None

    def _on_sim_state(self, msg: Any, t_rx: float) -> None:
        kind = "SIM_STATE"
        q = self._valid_quaternion(kind, _floats(msg, "q1", "q2", "q3", "q4"))
        if q is None:
            return None
        lat_i, lon_i = int(_get(msg, "lat_int", 0) or 0), int(_get(msg, "lon_int", 0) or 0)
        if lat_i != 0 or lon_i != 0:  # the degE7 extension is preferred (float degrees are ~1 m coarse)
            lat, lon = lat_i * 1e-7, lon_i * 1e-7
        else:
            lat, lon = float(_get(msg, "lat")), float(_get(msg, "lon"))
        alt = float(_get(msg, "alt"))
        v = _floats(msg, "vn", "ve", "vd")
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt) and np.all(np.isfinite(v))):
            self._reject(kind, "non-finite position", f"{lat} {lon} {alt}")
            return None
        if self.origin is None:
            self._truth = None
            return None
        p = geodetic_to_ned(lat, lon, alt, self.origin)
        att = self._att
        if att is not None and 0.0 <= t_rx - att.t_rx <= TRUTH_PAIR_WINDOW_S:
            # Sent right after the attitude of the same step: that step's time, on the autopilot's
            # clock like every navigation state. The arrival time is late by the link's and this
            # process's delays, which on a loaded machine reach tens of milliseconds: at the
            # rotation rates of a pitching multirotor a frame rendered at the truth would be paired
            # with navigation a degree away from the attitude it was rendered at.
            self._truth = TruthPose(att.t, p, v, q, self.origin.source, att.kind)
            self.truth_paired += 1
        else:
            self._truth = TruthPose(t_rx, p, v, q, self.origin.source)
            self.truth_unpaired += 1
        return None

    def truth_pose(self) -> TruthPose | None:
        """Latest SIM_STATE in the local NED frame, or None (no SIM_STATE yet or no origin known)."""
        return self._truth

    # ------------------------------------------------------------------------------------------
    # Assembly
    # ------------------------------------------------------------------------------------------

    def _assemble(self, t: float, t_rx: float) -> NavState | None:
        """State at ``t`` from the latest position and attitude, each carried to ``t``."""
        pos, att = self._pos, self._att
        if pos is None or att is None:
            return None
        skew = self.cfg.max_skew_s
        if abs(t - pos.t) > skew or abs(t - att.t) > skew:
            return None
        if t < self._last_emitted_t:  # an older half arrived after a newer one: nothing new to say
            self.superseded += 1
            return None
        p = pos.p + (t - pos.t) * pos.v
        q = att.q
        if t != att.t:
            dq = _quat_exp(att.omega_b * (t - att.t))  # body rates: right-multiply
            q = _quat_mul(att.q, dq)
            q = q / np.linalg.norm(q)
        P, source = self.covariance(t_rx)
        self._last_emitted_t = t
        return NavState(t, p, pos.v.copy(), q, P, source)

    def _fresh(self, kind: str, now: float) -> Evidence | None:
        ev = self._evidence.get(kind)
        if ev is None or now - ev.t_rx > self.cfg.covariance_max_age_s:
            return None
        return ev

    def covariance(self, now: float) -> tuple[np.ndarray, str]:
        """The 9x9 covariance and its source string from the evidence fresh at ``now`` (arrival clock).

        Cached until the evidence or its freshness changes (states arrive at 100 Hz, evidence at a
        few Hz); the returned array is read-only and shared by the states built from it.
        """
        max_age = self.cfg.covariance_max_age_s
        key = (self._evidence_version, tuple(k for k, ev in self._evidence.items() if now - ev.t_rx <= max_age))
        cached = self._covariance_cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        P, source = self._compute_covariance(now)
        P.flags.writeable = False
        self._covariance_cache = (key, P, source)
        return P, source

    def _compute_covariance(self, now: float) -> tuple[np.ndarray, str]:
        fresh = {kind: self._fresh(kind, now) for kind in EVIDENCE_KINDS}
        P, blocks = covariance_from_evidence(fresh, self.floor_sigmas, self.cfg.innovation_ratio_good)
        self.last_covariance_blocks = blocks
        return P, source_string(blocks)

    # ------------------------------------------------------------------------------------------
    # Health
    # ------------------------------------------------------------------------------------------

    def health(self, now: float) -> tuple[bool, str]:
        """Whether the estimator says its solution is usable, from EKF_STATUS_REPORT / ESTIMATOR_STATUS flags.

        ``(True, "...")`` when no estimator status is fresh: health unknown is not a refusal by
        itself (staleness of the state is checked by the link).
        """
        for kind, bad_names in (("EKF_STATUS_REPORT", BAD_FLAGS_ARDUPILOT), ("ESTIMATOR_STATUS", BAD_FLAGS_ESTIMATOR)):
            ev = self._fresh(kind, now)
            if ev is None:
                continue
            flags = int(ev.values.get("flags", 0))
            missing = [name for bit, name in REQUIRED_FLAGS.items() if not flags & bit]
            bad = [name for bit, name in bad_names.items() if flags & bit]
            if missing or bad:
                parts = ([f"missing {', '.join(missing)}"] if missing else []) + bad
                return False, f"{kind} flags 0x{flags:x}: {'; '.join(parts)}"
            return True, f"{kind} flags good"
        return True, "no estimator status (health unknown)"

    def status(self, now: float) -> dict[str, Any]:
        ok, reason = self.health(now)
        return {
            "covariance_blocks": dict(self.last_covariance_blocks),
            "estimator_healthy": ok,
            "estimator": reason,
            "time_basis": self.time_basis,
            "time_basis_changes": self.time_basis_changes,
            "estimator_resets": self.estimator_resets,
            "origin": None if self.origin is None else {"lat_deg": self.origin.lat_deg, "lon_deg": self.origin.lon_deg, "alt_m": self.origin.alt_m, "source": self.origin.source},
            "evidence_age_s": {k: round(now - ev.t_rx, 3) for k, ev in self._evidence.items()},
        }


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector (rad)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([1.0, *(0.5 * rotvec)])
    s = math.sin(0.5 * angle) / angle
    return np.array([math.cos(0.5 * angle), s * rotvec[0], s * rotvec[1], s * rotvec[2]])


__all__ = [
    "GeoOrigin",
    "HANDLED_MESSAGES",
    "NavAssembler",
    "RejectionCounter",
    "TruthPose",
    "geodetic_to_ned",
    "message_type",
]
