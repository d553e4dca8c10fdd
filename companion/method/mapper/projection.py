"""Camera pose of the vehicle and the pinhole projection with its Jacobian (seed 000, eqs. 3-4).

The mapper's vehicle state is ``x = [p (3), dtheta (3)]``: the NED position of the body origin and
the attitude error as a NED rotation vector, ``R_nb_true = Exp(dtheta) R_nb_est``. Its covariance
``P_x`` (6x6) is ``NavState.pose_covariance``. Velocity and IMU biases do not enter eq. 3.

The camera centre and orientation follow from the mount (``CameraMount.camera_pose``):
``p_c = p + R_nb t_bc`` and ``R_nc = R_nb R_bc``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.method.geometry import CameraMount, PinholeCamera

VEHICLE_DIM = 6  # [p (3), dtheta (3)]


@dataclass(frozen=True, slots=True)
class CameraPose:
    """Vehicle and camera pose at one instant (estimated values).

    p: (3,) body origin, NED. R_nb: (3, 3) body->NED.
    p_c: (3,) camera centre, NED. R_nc: (3, 3) camera (paper frame) -> NED.
    """

    p: np.ndarray
    R_nb: np.ndarray
    p_c: np.ndarray
    R_nc: np.ndarray

    @classmethod
    def from_body(cls, p: np.ndarray, R_nb: np.ndarray, mount: CameraMount) -> "CameraPose":
        p = np.asarray(p, dtype=float).reshape(3)
        R_nb = np.asarray(R_nb, dtype=float).reshape(3, 3)
        p_c, R_nc = mount.camera_pose(p, R_nb)
        return cls(p=p, R_nb=R_nb, p_c=np.asarray(p_c, float), R_nc=np.asarray(R_nc, float))

    @classmethod
    def from_nav(cls, position_ned_m: np.ndarray, quaternion_wxyz: np.ndarray, mount: CameraMount) -> "CameraPose":
        """:meth:`from_body` with ``R_nb`` from the attitude quaternion (``NavState.R_nb``)."""
        return cls.from_body(position_ned_m, rotation_from_quaternion(quaternion_wxyz), mount)


def rotation_from_quaternion(q_wxyz: np.ndarray) -> np.ndarray:
    """Body->NED rotation (3, 3) of one Hamilton quaternion (w, x, y, z), normalised first.

    The same arithmetic as :func:`companion.geometry.quat_to_matrix` (bit-identical results) on
    Python floats: on a single quaternion NumPy's cost per operation is most of the time.
    """
    w, x, y, z = np.asarray(q_wxyz, dtype=float).reshape(4).tolist()
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def pixel_from_camera_vector(h_c: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """Eq. 4: camera-frame vectors ``h_c`` (N, 3) -> ideal pixels (N, 2); NaN where ``h_x <= 0``.

    ``u = c_u + f_u h_y / h_x``, ``v = c_v + f_v h_z / h_x``: ``PinholeCamera.project``'s arithmetic
    (bit-identical) for (N, 3), without its error-state context (a few microseconds a call)."""
    hx = h_c[:, 0]
    front = hx > 0
    inv = np.divide(1.0, hx, out=np.full(len(hx), np.nan), where=front)
    uv = np.empty((len(hx), 2))
    uv[:, 0] = camera.cx + camera.fx * h_c[:, 1] * inv
    uv[:, 1] = camera.cy + camera.fy * h_c[:, 2] * inv
    return uv


def pixel_jacobian(h_c: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """``dg/dh`` of eq. 4 at ``h_c`` (N, 3) -> (N, 2, 3).

    ``[[-f_u h_y/h_x^2, f_u/h_x, 0], [-f_v h_z/h_x^2, 0, f_v/h_x]]``. Callers remove points with
    ``h_x <= 0`` first (they are behind the camera and have no pixel).
    """
    h_c = np.asarray(h_c, dtype=float)
    hx, hy, hz = h_c[:, 0], h_c[:, 1], h_c[:, 2]
    inv = 1.0 / hx
    J = np.zeros((len(h_c), 2, 3))
    J[:, 0, 0] = -camera.fx * hy * inv * inv
    J[:, 0, 1] = camera.fx * inv
    J[:, 1, 0] = -camera.fy * hz * inv * inv
    J[:, 1, 2] = camera.fy * inv
    return J


def camera_ray_from_pixel(uv: np.ndarray, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of eq. 4 up to scale.

    Ideal pixels ``uv`` (N, 2) -> ``h = [1, (u - c_u)/f_u, (v - c_v)/f_v]`` (N, 3; camera frame,
    not normalised) and ``dh/dz`` (3, 2), which is the same for every pixel.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    h = np.empty((len(uv), 3))
    h[:, 0] = 1.0
    h[:, 1] = (uv[:, 0] - camera.cx) / camera.fx
    h[:, 2] = (uv[:, 1] - camera.cy) / camera.fy
    dh_dz = np.array([[0.0, 0.0], [1.0 / camera.fx, 0.0], [0.0, 1.0 / camera.fy]])
    return h, dh_dz
