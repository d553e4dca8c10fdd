"""NavState assembly from what the autopilot actually sends, and the covariance models.

Pure: messages go in as decoded objects (pymavlink messages: ``msg.get_type()`` and attributes)
or plain dicts (``{"mavpackettype": "LOCAL_POSITION_NED", "x": ...}``, as ``msg.to_dict()`` gives), with the companion time
at which they arrived; :class:`NavState` comes out. No sockets here (``drivers/autopilot/``
owns the link), so every model can be tested from numbers alone.

State
    ``LOCAL_POSITION_NED`` (position, velocity) and ``ATTITUDE_QUATERNION`` (attitude, body rates),
    or ``ODOMETRY`` (all of it). A state is emitted at the time of every position or attitude
    message; the other half is carried to that time (position by its velocity, attitude by its
    body rates), and only if it is at most ``nav.max_skew_s`` away.

Covariance (9x9 over [position m, velocity m/s, attitude error rad], the attitude error being a
NED rotation vector with ``R_true = Exp(dtheta) R_est``), chosen per block from the best evidence
that is valid and younger than ``nav.covariance_max_age_s``:

====================  ==========================================================================
position              ODOMETRY > LOCAL_POSITION_NED_COV > ESTIMATOR_STATUS (accuracies) >
                      EKF_STATUS_REPORT(+GPS_RAW_INT) heuristic > GPS_RAW_INT > floors
velocity              ODOMETRY > LOCAL_POSITION_NED_COV > ESTIMATOR_STATUS heuristic >
                      EKF_STATUS_REPORT(+GPS_RAW_INT) heuristic > GPS_RAW_INT > floors
attitude              ODOMETRY > ATTITUDE_QUATERNION_COV > ESTIMATOR_STATUS heuristic >
                      EKF_STATUS_REPORT heuristic > floors
====================  ==========================================================================

The configured floors (``nav.*_floor_*``) are always applied as lower bounds on the marginal
standard deviations (a non-negative diagonal is added, which keeps the matrix PSD and the
cross-covariances). :attr:`NavState.covariance_source` names the messages used, with ``+floors``
when any block is floor-based (a heuristic that scales the floors, or the floors alone):
``"ODOMETRY"``, ``"LOCAL_POSITION_NED_COV+ATTITUDE_QUATERNION_COV"``,
``"ESTIMATOR_STATUS+floors"``, ``"EKF_STATUS_REPORT+GPS_RAW_INT+floors"``, ``"floors"``.

The heuristic for innovation test ratios (ArduPilot EKF_STATUS_REPORT "variances", which are
``sqrt`` of the EKF's innovation test ratios, dimensionless, < 0.5 normal, >= 1 measurement
rejected; PX4 ESTIMATOR_STATUS ``*_ratio``): ``sigma = base * max(1, ratio / ratio_good)``. It says
"when the filter's innovations are larger than it expects, its own uncertainty is probably too
small by about that factor". It is a heuristic, not a covariance; the status says so by naming
the source. ``base`` is the GPS accuracy when GPS_RAW_INT reports one (h_acc, v_acc in mm,
vel_acc in mm/s), else the floor.

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


# --------------------------------------------------------------------------------------------
# Covariance conversions (pure maths, batched where it matters)
# --------------------------------------------------------------------------------------------


def upper_triangle_to_matrix(values: np.ndarray, n: int) -> np.ndarray:
    """Symmetric (n, n) matrix from its row-major upper triangle incl. the diagonal, n(n+1)/2 values.

    MAVLink's ``pose_covariance[21]`` (n=6), ``covariance[45]`` of LOCAL_POSITION_NED_COV (n=9).
    """
    values = np.asarray(values, dtype=float).reshape(-1)
    if values.size != n * (n + 1) // 2:
        raise ValueError(f"upper triangle of a {n}x{n} matrix needs {n * (n + 1) // 2} values, got {values.size}")
    out = np.zeros((n, n))
    rows, cols = np.triu_indices(n)  # row-major order, as MAVLink lays it out
    out[rows, cols] = values
    out[cols, rows] = values
    return out


def quat_to_euler(q_wxyz: np.ndarray) -> tuple[float, float, float]:
    """ZYX (roll, pitch, yaw) of a body->NED quaternion (rad)."""
    R = quat_to_matrix(q_wxyz)
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def euler_rate_jacobian_ned(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """E (3, 3) with ``dtheta_ned = E @ [droll, dpitch, dyaw]`` for R = Rz(yaw) Ry(pitch) Rx(roll).

    Derivation: dR R^T = [e_z]x dyaw + [Rz e_y]x dpitch + [Rz Ry e_x]x droll, so the columns of E
    are the roll axis after yaw and pitch, the pitch axis after yaw, and the down axis. ``roll``
    does not appear; E is singular at pitch = +-90 deg (gimbal lock), where the Euler covariance
    cannot carry full rank anyway.
    """
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, -sy, 0.0],
            [sy * cp, cy, 0.0],
            [-sp, 0.0, 1.0],
        ]
    )


def euler_covariance_to_rotvec(cov_rpy: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of (roll, pitch, yaw) at attitude q -> covariance of the NED rotation-vector error.

    First order: ``dtheta = E dEuler`` so ``P_theta = E P_rpy E^T`` (:func:`euler_rate_jacobian_ned`).
    This is how ODOMETRY.pose_covariance and ATTITUDE_QUATERNION_COV.covariance (both documented
    by MAVLink as roll/pitch/yaw covariances) become the mapper's attitude block.
    """
    E = euler_rate_jacobian_ned(*quat_to_euler(q_wxyz))
    return E @ np.asarray(cov_rpy, dtype=float) @ E.T


def rotvec_covariance_to_euler(cov_rotvec: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_covariance_to_rotvec` (for simulators that report roll/pitch/yaw covariance)."""
    E_inv = np.linalg.inv(euler_rate_jacobian_ned(*quat_to_euler(q_wxyz)))
    return E_inv @ np.asarray(cov_rotvec, dtype=float) @ E_inv.T


def covariance_problem(P: np.ndarray, rel_tol: float = 1e-5) -> str | None:
    """Why a symmetric covariance is unusable (non-finite, negative variance, not PSD), or None."""
    if not np.all(np.isfinite(P)):
        return "non-finite covariance"
    d = np.diag(P)
    if np.any(d < 0):
        return "negative variance"
    # Judge the correlation matrix D^-1/2 P D^-1/2, not P: a tolerance scaled by the largest variance would let
    # a huge variance on one axis hide a correlation above 1 between two others.
    P = 0.5 * (P + P.T)
    s = np.sqrt(d)
    known = s > 0
    if np.any(P[~known] != 0.0):  # an axis with zero variance cannot covary with anything
        return "covariance not positive semi-definite"
    C = P[np.ix_(known, known)] / np.outer(s[known], s[known])
    if C.size and float(np.linalg.eigvalsh(C).min()) < -rel_tol:
        return "covariance not positive semi-definite"
    return None


def reported_covariance(values: Any, n: int) -> tuple[np.ndarray | None, str | None]:
    """A MAVLink upper-triangle covariance -> (matrix, problem).

    ``(None, None)`` when unknown (NaN first element, MAVLink's convention). A NaN variance marks
    that state unknown (it stays NaN on the diagonal; :func:`covariance_block` then declines blocks
    that contain it) and a NaN off-diagonal is an unknown correlation, read as 0: PX4's ODOMETRY
    stream sets only the variances it has (position, orientation; vx, vy, vz but not the angular
    rates) and leaves everything else NaN (PX4 src/modules/mavlink/streams/ODOMETRY.hpp). An infinite
    element or a negative variance is a problem.
    """
    if values is None:
        return None, None
    values = np.asarray(values, dtype=float).reshape(-1)
    if values.size == 0 or math.isnan(values[0]):
        return None, None
    try:
        P = upper_triangle_to_matrix(values, n)
    except ValueError:
        return None, "covariance has the wrong length"
    if np.any(np.isinf(P)):
        return None, "non-finite covariance"
    d = np.diag(P).copy()
    if np.any(d < 0):
        return None, "negative variance"
    P[np.isnan(P)] = 0.0
    P[np.diag_indices(n)] = d  # unknown variances stay NaN
    return P, None


def covariance_block(P: np.ndarray, states: slice) -> tuple[np.ndarray | None, str | None]:
    """The sub-covariance over ``states`` of a :func:`reported_covariance` matrix.

    ``(None, None)`` when one of its variances is unknown, ``(None, problem)`` when it is not PSD.
    """
    B = P[states, states]
    if np.any(np.isnan(np.diag(B))):
        return None, None
    problem = covariance_problem(B)
    return (None, problem) if problem else (B.copy(), None)


def apply_floors(P: np.ndarray, floor_sigmas: np.ndarray) -> np.ndarray:
    """Raise marginal standard deviations to at least ``floor_sigmas`` (n,) by adding a non-negative diagonal."""
    add = np.maximum(0.0, np.asarray(floor_sigmas, dtype=float) ** 2 - np.diag(P))
    return P + np.diag(add)


def ratio_scale(ratio: float | None, ratio_good: float) -> float:
    """Heuristic inflation ``max(1, ratio / ratio_good)`` of a sigma from an innovation test ratio."""
    if ratio is None or not math.isfinite(ratio) or ratio <= 0.0:
        return 1.0
    return max(1.0, ratio / ratio_good)


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

    t_s: companion time of arrival (SIM_STATE carries no timestamp).
    position_ned_m, velocity_ned_mps: (3,); quaternion_wxyz: (4,) body->NED.
    """

    t_s: float
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray
    quaternion_wxyz: np.ndarray
    origin_source: str


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


@dataclass(slots=True)
class _Evidence:
    """Covariance evidence from one message, validated and converted on arrival."""

    t_rx: float
    pos: np.ndarray | None = None  # (3, 3) m^2
    vel: np.ndarray | None = None  # (3, 3) (m/s)^2, NED
    att: np.ndarray | None = None  # (3, 3) rad^2, NED rotation vector
    pos_vel: np.ndarray | None = None  # (3, 3) cross
    pos_att: np.ndarray | None = None  # (3, 3) cross
    values: dict[str, float] = field(default_factory=dict)  # ratios, accuracies, flags


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
        self._evidence: dict[str, _Evidence] = {}
        self._evidence_version = 0
        self._covariance_cache: tuple[tuple, np.ndarray, str] | None = None
        self._unix_minus_boot_s: float | None = None
        self._last_emitted_t = -math.inf
        self._odometry_reset_counter: int | None = None
        self.estimator_resets = 0
        self.origin: GeoOrigin | None = None
        self._home: tuple[float, float, float, np.ndarray] | None = None
        self._truth: TruthPose | None = None
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

    def _set_evidence(self, kind: str, ev: _Evidence) -> None:
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
        self._att = _Attitude(t, q, self._body_rates(kind, msg))
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

        ev = _Evidence(t_rx)
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
        self._att = _Attitude(t, q, self._body_rates(kind, msg))
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
                self._set_evidence(kind, _Evidence(t_rx, pos=pos, vel=vel, pos_vel=P[:3, 3:6].copy()))
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
        self._set_evidence(kind, _Evidence(t_rx, att=euler_covariance_to_rotvec(0.5 * (P + P.T), q)))
        return None

    def _on_estimator_status(self, msg: Any, t_rx: float) -> None:
        kind = "ESTIMATOR_STATUS"
        ev = _Evidence(t_rx)
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
        self._set_evidence("EKF_STATUS_REPORT", _Evidence(t_rx, values=values))
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
        self._set_evidence("GPS_RAW_INT", _Evidence(t_rx, values=values))
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
        self._truth = TruthPose(t_rx, p, v, q, self.origin.source)
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

    def _fresh(self, kind: str, now: float) -> _Evidence | None:
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
        odo = self._fresh("ODOMETRY", now)
        lpc = self._fresh("LOCAL_POSITION_NED_COV", now)
        aqc = self._fresh("ATTITUDE_QUATERNION_COV", now)
        est = self._fresh("ESTIMATOR_STATUS", now)
        ekf = self._fresh("EKF_STATUS_REPORT", now)
        gps = self._fresh("GPS_RAW_INT", now)
        floors = self.floor_sigmas
        good = self.cfg.innovation_ratio_good
        P = np.zeros((9, 9))
        blocks: dict[str, str] = {}

        # GPS accuracies (m, m/s) as the base of the heuristic models; floors when unknown.
        gh = gv = gvel = 0.0
        if gps is not None:
            gh, gv, gvel = gps.values["h_acc_m"], gps.values["v_acc_m"], gps.values["vel_acc_mps"]
        gps_tag = "+GPS_RAW_INT" if gps is not None and (gh > 0 or gv > 0 or gvel > 0) else ""
        base_pos = np.array([max(floors[0], gh / math.sqrt(2)), max(floors[1], gh / math.sqrt(2)), max(floors[2], gv)])
        base_vel = np.full(3, max(floors[3], gvel))

        # Position (and the cross terms its source provides).
        if odo is not None and odo.pos is not None:
            P[0:3, 0:3] = odo.pos
            blocks["position"] = "ODOMETRY"
        elif lpc is not None:
            P[0:3, 0:3] = lpc.pos
            blocks["position"] = "LOCAL_POSITION_NED_COV"
        elif est is not None and est.pos is not None:
            P[0:3, 0:3] = est.pos
            blocks["position"] = "ESTIMATOR_STATUS"
        elif ekf is not None:
            s = np.array([ratio_scale(ekf.values["pos_horiz_variance"], good)] * 2 + [ratio_scale(ekf.values["pos_vert_variance"], good)])
            P[0:3, 0:3] = np.diag((base_pos * s) ** 2)
            blocks["position"] = "EKF_STATUS_REPORT" + gps_tag + "+floors"
        elif gps_tag:
            P[0:3, 0:3] = np.diag(base_pos**2)
            blocks["position"] = "GPS_RAW_INT+floors"
        else:
            blocks["position"] = "floors"

        # Velocity.
        if odo is not None and odo.vel is not None:
            P[3:6, 3:6] = odo.vel
            blocks["velocity"] = "ODOMETRY"
        elif lpc is not None:
            P[3:6, 3:6] = lpc.vel
            if blocks["position"] == "LOCAL_POSITION_NED_COV":
                P[0:3, 3:6] = lpc.pos_vel
                P[3:6, 0:3] = lpc.pos_vel.T
            blocks["velocity"] = "LOCAL_POSITION_NED_COV"
        elif est is not None:
            P[3:6, 3:6] = np.diag((base_vel * ratio_scale(est.values["vel_ratio"], good)) ** 2)
            blocks["velocity"] = "ESTIMATOR_STATUS" + gps_tag + "+floors"
        elif ekf is not None:
            P[3:6, 3:6] = np.diag((base_vel * ratio_scale(ekf.values["velocity_variance"], good)) ** 2)
            blocks["velocity"] = "EKF_STATUS_REPORT" + gps_tag + "+floors"
        elif gps_tag:
            P[3:6, 3:6] = np.diag(base_vel**2)
            blocks["velocity"] = "GPS_RAW_INT+floors"
        else:
            blocks["velocity"] = "floors"

        # Attitude (NED rotation vector: components 0, 1 are tilt, 2 is heading).
        if odo is not None and odo.att is not None:
            P[6:9, 6:9] = odo.att
            if blocks["position"] == "ODOMETRY":
                P[0:3, 6:9] = odo.pos_att
                P[6:9, 0:3] = odo.pos_att.T
            blocks["attitude"] = "ODOMETRY"
        elif aqc is not None:
            P[6:9, 6:9] = aqc.att
            blocks["attitude"] = "ATTITUDE_QUATERNION_COV"
        elif est is not None or ekf is not None:
            # PX4 mag_ratio is one test ratio; ArduPilot's compass_variance is the length of a 3-vector
            # of per-axis ratios (AP_NavEKF3 getVariances), so divide by sqrt(3) for a per-axis figure.
            mag = est.values["mag_ratio"] if est is not None else ekf.values["compass_variance"] / math.sqrt(3)
            sig = floors[6:9] * np.array([1.0, 1.0, ratio_scale(mag, good)])
            P[6:9, 6:9] = np.diag(sig**2)
            blocks["attitude"] = ("ESTIMATOR_STATUS" if est is not None else "EKF_STATUS_REPORT") + "+floors"
        else:
            blocks["attitude"] = "floors"

        P = apply_floors(P, floors)
        self.last_covariance_blocks = blocks
        return P, _source_string(blocks)

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


def _source_string(blocks: dict[str, str]) -> str:
    """Ordered union of the messages named by the blocks, with '+floors' last when any block uses floors."""
    names: list[str] = []
    floors = False
    for source in blocks.values():
        for part in source.split("+"):
            if part == "floors":
                floors = True
            elif part not in names:
                names.append(part)
    if floors:
        names.append("floors")
    return "+".join(names)


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
    "apply_floors",
    "covariance_block",
    "covariance_problem",
    "euler_covariance_to_rotvec",
    "euler_rate_jacobian_ned",
    "geodetic_to_ned",
    "message_type",
    "quat_to_euler",
    "ratio_scale",
    "reported_covariance",
    "rotvec_covariance_to_euler",
    "upper_triangle_to_matrix",
]
