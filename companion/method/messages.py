"""The messages that flow between the parts of the service (frozen, slotted dataclasses).

Times ``t_s`` are on the companion's monotonic clock (seconds) unless a name says otherwise.
Arrays are NumPy; shapes are given in each docstring.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.method.geometry import quat_to_matrix

# Index blocks of NavState.covariance (9x9): position, velocity, attitude error (rotation vector, NED).
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)


@dataclass(frozen=True, slots=True)
class NavState:
    """The autopilot's navigation solution at one instant.

    t_s: companion time of validity (s).
    position_ned_m: (3,) local NED position of the body origin.
    velocity_ned_mps: (3,) NED velocity.
    quaternion_wxyz: (4,) attitude body->NED (Hamilton, scalar first, as MAVLink sends it).
    covariance: (9, 9) over [position (m), velocity (m/s), attitude error (rad, NED rotation vector
        with R_true = Exp(dtheta) R_est)].
    covariance_source: where the covariance came from (e.g. "ODOMETRY", "EKF_STATUS_REPORT+floors",
        "floors"), reported in the status so an operator knows what the mapper trusts.
    """

    t_s: float
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray
    quaternion_wxyz: np.ndarray
    covariance: np.ndarray
    covariance_source: str = "floors"

    @property
    def R_nb(self) -> np.ndarray:
        """Rotation body->NED (3, 3)."""
        return quat_to_matrix(self.quaternion_wxyz)

    @property
    def altitude_m(self) -> float:
        return float(-self.position_ned_m[2])

    @property
    def pose_covariance(self) -> np.ndarray:
        """P_x of the mapper (6, 6): [position, attitude error] (seed 000, eq. 6)."""
        idx = np.r_[0:3, 6:9]
        return self.covariance[np.ix_(idx, idx)]

    def is_finite(self) -> bool:
        return bool(
            np.all(np.isfinite(self.position_ned_m))
            and np.all(np.isfinite(self.velocity_ned_mps))
            and np.all(np.isfinite(self.quaternion_wxyz))
            and np.all(np.isfinite(self.covariance))
        )


@dataclass(frozen=True, slots=True)
class Frame:
    """One camera image. image: (H, W) uint8 grayscale. t_s: capture time (companion clock)."""

    t_s: float
    image: np.ndarray
    sequence: int = 0
    source: str = ""


@dataclass(frozen=True, slots=True)
class TerrainPoints:
    """Converged feature positions handed from the mapper to the terrain map.

    positions_ned_m: (N, 3); covariances: (N, 3, 3) in m^2; feature_ids: (N,) int64.
    """

    t_s: float
    positions_ned_m: np.ndarray
    covariances: np.ndarray
    feature_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @classmethod
    def empty(cls, t_s: float = 0.0) -> "TerrainPoints":
        return cls(t_s, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.positions_ned_m)


@dataclass(frozen=True, slots=True)
class FreeSpaceRays:
    """Segments the camera saw through this frame, handed from the mapper to the terrain map
    (docs/terrain.md, "Free space"): from the camera centre ``origin_ned_m`` (3,) to each of
    ``ends_ned_m`` (K, 3), the nearest its feature can be (k sigma). Nothing of the terrain lies on
    a segment: a feature was seen at its end. ``feature_ids`` (K,), the feature of each segment
    (None: unknown, each frame's segments then count as one look), lets the map count the
    features that contradict a cell, not the frames (a feature tracked wrongly repeats its error
    every frame). ``angle_sigma_rad``: the sigma of the lines of sight's direction (the
    navigation's attitude, its largest axis; 0 = exact): at horizontal distance s from the camera a
    segment is known laterally to s x that."""

    t_s: float
    origin_ned_m: np.ndarray
    ends_ned_m: np.ndarray
    feature_ids: np.ndarray | None = None
    angle_sigma_rad: float = 0.0

    @classmethod
    def empty(cls, t_s: float = 0.0) -> "FreeSpaceRays":
        return cls(t_s, np.zeros(3), np.zeros((0, 3)))

    def __len__(self) -> int:
        return len(self.ends_ned_m)


@dataclass(frozen=True, slots=True)
class TerrainFloors:
    """Lower bounds on the terrain's height, handed from the mapper to the terrain map (docs/mapper.md,
    "Bounds of an unconverged feature"): the terrain in the cell of each ``positions_ned_m`` (K, 3)
    row's north and east reaches at least that row's height (``-down``); ``feature_ids`` (K,), the
    feature each row bounds, lets the map move a floor with its feature (docs/terrain.md, "Floors";
    a negative id: a bound no feature owns, a rise seen by dense flow);
    ``ended_ids`` (E,), the features that left the mapper this step (out of view, replaced, or
    corrupt), lets the map withdraw a floor no longer backed by anything (docs/terrain.md, "A floor
    whose feature ended")."""

    t_s: float
    positions_ned_m: np.ndarray
    feature_ids: np.ndarray | None = None
    ended_ids: np.ndarray | None = None

    @classmethod
    def empty(cls, t_s: float = 0.0) -> "TerrainFloors":
        return cls(t_s, np.zeros((0, 3)))

    def __len__(self) -> int:
        return len(self.positions_ned_m)

    @property
    def n_ended(self) -> int:
        """How many features ended this step (0 when not told)."""
        return 0 if self.ended_ids is None else len(self.ended_ids)
