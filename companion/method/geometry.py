"""Frames, rotations and the camera model.

Conventions (docs/conventions.md):

* World: the autopilot's local NED frame (x north, y east, z down); altitude ``h = -z``.
* Body: FRD (x forward, y right, z down).
* Attitude: quaternion body->NED, Hamilton, scalar first ``(w, x, y, z)`` as MAVLink sends it.
  ``R_nb = quat_to_matrix(q)`` maps body vectors to NED: ``v_n = R_nb @ v_b``.
* Camera: the paper's frame (seed 000, eq. 4): x along the optical axis, y right, z down in the
  image. Pixel ``u = c_u + f_u h_y / h_x``, ``v = c_v + f_v h_z / h_x``. OpenCV's camera frame
  (x right, y down, z forward) is ``[h_y, h_z, h_x]``.
* Mount: ``R_bc`` maps camera vectors to body, from ZYX Euler angles of the camera axes relative
  to the body (a camera with all angles 0 looks along the nose; pitch -45 deg looks 45 deg down);
  ``t_bc`` is the camera centre in the body frame.
* Attitude error: a rotation vector ``dtheta`` in the NED frame, ``R_true = Exp(dtheta) R_est``.

Every function is batched over leading dimensions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

# Paper camera frame (x optical, y right, z down) -> OpenCV camera frame (x right, y down, z optical).
PAPER_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` with ``[v]x w = v x w``; ``v`` (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix of a Hamilton quaternion (w, x, y, z); normalises first. (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) with w >= 0 of a rotation matrix. (..., 3, 3) -> (..., 4)."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):  # small batches only (conversions at the edges)
        t = np.trace(m)
        if t > 0:
            s = 2.0 * np.sqrt(1.0 + t)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        out[i] = q if q[0] >= 0 else -q
    return out.reshape(R.shape[:-2] + (4,))


def euler_to_matrix(roll: np.ndarray | float, pitch: np.ndarray | float, yaw: np.ndarray | float) -> np.ndarray:
    """ZYX (yaw, pitch, roll) aerospace Euler angles in radians -> rotation matrix ``R = Rz Ry Rx``."""
    roll, pitch, yaw = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float), np.asarray(yaw, float))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    out = np.empty(roll.shape + (3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def euler_to_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ZYX Euler angles (rad) -> quaternion (w, x, y, z)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def matrix_to_euler(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation matrix -> ZYX (roll, pitch, yaw) in radians."""
    R = np.asarray(R, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return roll, pitch, yaw


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (..., 3) -> rotation matrix (..., 3, 3)."""
    rotvec = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    K = skew(rotvec)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


@dataclass(frozen=True, slots=True)
class CameraMount:
    """Rigid mount of the camera on the body: ``R_bc`` (camera->body) and ``t_bc`` (m, body FRD)."""

    R_bc: np.ndarray
    t_bc: np.ndarray

    @classmethod
    def from_euler_deg(cls, roll_deg: float, pitch_deg: float, yaw_deg: float, offset_m=(0.0, 0.0, 0.0)) -> "CameraMount":
        R = euler_to_matrix(np.radians(roll_deg), np.radians(pitch_deg), np.radians(yaw_deg))
        return cls(R_bc=R, t_bc=np.asarray(offset_m, dtype=float).reshape(3))

    def camera_pose(self, position_ned: np.ndarray, R_nb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre in NED and ``R_nc`` (camera->NED) from the body pose. Batched over (..., 3)."""
        p_c = np.asarray(position_ned, float) + R_nb @ self.t_bc
        return p_c, R_nb @ self.R_bc


@dataclass(frozen=True, slots=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels with OpenCV distortion coefficients (seed 000, eq. 4).

    ``project`` and ``ray`` work on ideal (undistorted) pixels; ``undistort`` maps raw detected
    pixel coordinates to ideal ones (the paper undistorts points, not the whole image).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.asarray(self.distortion) != 0.0))

    def project(self, h_c: np.ndarray) -> np.ndarray:
        """Paper eq. 4: ``(..., 3)`` camera-frame vectors -> ``(..., 2)`` ideal pixels. Points behind
        the camera (``h_x <= 0``) give NaN."""
        h_c = np.asarray(h_c, dtype=float)
        hx = h_c[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(hx > 0, 1.0 / hx, np.nan)
        return np.stack([self.cx + self.fx * h_c[..., 1] * inv, self.cy + self.fy * h_c[..., 2] * inv], axis=-1)

    def ray(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pixels ``(..., 2)`` -> unit direction in the paper camera frame ``(..., 3)``."""
        uv = np.asarray(uv, dtype=float)
        d = np.stack(
            [np.ones(uv.shape[:-1]), (uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1
        )
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def undistort(self, uv_raw: np.ndarray) -> np.ndarray:
        """Raw (distorted) pixels ``(N, 2)`` -> ideal pixels ``(N, 2)`` with the same K."""
        uv_raw = np.asarray(uv_raw, dtype=float).reshape(-1, 2)
        if not self.has_distortion or len(uv_raw) == 0:
            return uv_raw.copy()
        pts = cv2.undistortPoints(uv_raw.reshape(-1, 1, 2), self.K, np.asarray(self.distortion, float), P=self.K)
        return pts.reshape(-1, 2)

    def distort(self, uv_ideal: np.ndarray) -> np.ndarray:
        """Ideal pixels ``(N, 2)`` -> raw pixels as the lens would image them (for simulation)."""
        uv_ideal = np.asarray(uv_ideal, dtype=float).reshape(-1, 2)
        if not self.has_distortion or len(uv_ideal) == 0:
            return uv_ideal.copy()
        rays = np.column_stack([(uv_ideal - [self.cx, self.cy]) / [self.fx, self.fy], np.ones(len(uv_ideal))])
        pts, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), self.K, np.asarray(self.distortion, float))
        return pts.reshape(-1, 2)

    def in_image(self, uv: np.ndarray, border_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image, ``border_px`` away from the edges (NaN -> False)."""
        uv = np.asarray(uv, dtype=float)
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return (
                (u >= border_px)
                & (u <= self.width - 1 - border_px)
                & (v >= border_px)
                & (v <= self.height - 1 - border_px)
            )

    @property
    def vertical_fov_deg(self) -> float:
        return float(np.degrees(2 * np.arctan2(self.height / 2, self.fy)))


def view_depression(camera: PinholeCamera, mount: CameraMount, R_nb: np.ndarray, top_px: float = 0.0) -> float:
    """Angle (rad) below the horizontal of the camera's line of sight through the middle of the
    image's top row (``top_px`` rows in: features nearer the edge are not used) with the body at
    attitude ``R_nb`` (3, 3): the highest line of sight the camera has ahead, so the highest
    terrain it can see at a distance d is ``d tan(angle)`` below it (docs/avoidance.md, "What the
    camera can see"). Negative when that line looks up. A multirotor flying forward pitches its
    nose, and a fixed camera with it, down: the attitude counts."""
    d_cam = camera.ray(np.array([camera.cx, float(top_px)]))
    d_ned = np.asarray(R_nb, dtype=float) @ (mount.R_bc @ d_cam)
    return float(np.arcsin(np.clip(d_ned[2] / np.linalg.norm(d_ned), -1.0, 1.0)))


def camera_from_config(cam) -> tuple[PinholeCamera, CameraMount]:
    """Build the camera model and mount from a :class:`companion.config.CameraConfig`."""
    model = PinholeCamera(
        fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=cam.width, height=cam.height,
        distortion=np.asarray(cam.distortion, dtype=float),
    )
    mount = CameraMount.from_euler_deg(cam.mount_roll_deg, cam.mount_pitch_deg, cam.mount_yaw_deg, cam.mount_offset_m)
    return model, mount
