"""The navigation covariance models: what the autopilot reports, converted to the mapper's 9x9, and
the choice per block from the evidence the assembler keeps (:mod:`~companion.method.navigation.assembler`).

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
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.method.geometry import quat_to_matrix

# The messages whose covariance evidence the models read.
EVIDENCE_KINDS = ("ODOMETRY", "LOCAL_POSITION_NED_COV", "ATTITUDE_QUATERNION_COV", "ESTIMATOR_STATUS",
                  "EKF_STATUS_REPORT", "GPS_RAW_INT")


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


@dataclass(slots=True)
class Evidence:
    """Covariance evidence from one message, validated and converted on arrival."""

    t_rx: float
    pos: np.ndarray | None = None  # (3, 3) m^2
    vel: np.ndarray | None = None  # (3, 3) (m/s)^2, NED
    att: np.ndarray | None = None  # (3, 3) rad^2, NED rotation vector
    pos_vel: np.ndarray | None = None  # (3, 3) cross
    pos_att: np.ndarray | None = None  # (3, 3) cross
    values: dict[str, float] = field(default_factory=dict)  # ratios, accuracies, flags


# --------------------------------------------------------------------------------------------
# The model: one covariance from the evidence
# --------------------------------------------------------------------------------------------


def covariance_from_evidence(fresh: Mapping[str, Evidence | None], floors: np.ndarray,
                             ratio_good: float) -> tuple[np.ndarray, dict[str, str]]:
    """The 9x9 covariance from the freshest evidence of each message kind, chosen per block as the
    module docstring's table says, and the source of each block (``position``, ``velocity``,
    ``attitude`` -> the messages used, ``+floors`` where the floors scale or stand in).

    fresh: message kind -> its evidence, or None when there is none young enough; floors (9,): the
    marginal sigmas' lower bounds; ratio_good: the innovation test ratio below which a filter is
    taken at its word.
    """
    odo = fresh.get("ODOMETRY")
    lpc = fresh.get("LOCAL_POSITION_NED_COV")
    aqc = fresh.get("ATTITUDE_QUATERNION_COV")
    est = fresh.get("ESTIMATOR_STATUS")
    ekf = fresh.get("EKF_STATUS_REPORT")
    gps = fresh.get("GPS_RAW_INT")
    good = ratio_good
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
    return P, blocks


def source_string(blocks: dict[str, str]) -> str:
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


__all__ = [
    "EVIDENCE_KINDS",
    "Evidence",
    "apply_floors",
    "covariance_block",
    "covariance_from_evidence",
    "covariance_problem",
    "euler_covariance_to_rotvec",
    "euler_rate_jacobian_ned",
    "quat_to_euler",
    "ratio_scale",
    "reported_covariance",
    "rotvec_covariance_to_euler",
    "source_string",
    "upper_triangle_to_matrix",
]
