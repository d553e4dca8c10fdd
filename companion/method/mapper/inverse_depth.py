"""Inverse-depth feature parameterisation (seed 000, section II.A and II.D; Civera et al., ref. [2]).

Feature state (eq. 1): ``y = [x_a, y_a, z_a, psi, theta, rho]``: the anchor ``a`` (NED camera
centre at initialisation), azimuth ``psi`` and elevation ``theta`` of the ray from the anchor, and
the inverse distance ``rho`` along it. The point is ``a + m / rho``; ``rho = 0`` is a point at
infinity, which the model handles without special cases.

Direction (eq. 3): ``m = R_ref m(psi, theta)`` with ``m(psi, theta) = [sin theta, cos theta sin psi,
cos theta cos psi]``. The paper measures the angles in the inertial frame, which makes
``theta = +-90 deg`` (rays along +-north, horizontal) singular. Here each feature carries a constant
reference rotation ``R_ref`` (not estimated) chosen at initialisation so that the reference z axis
is the optical axis of the camera at that moment; the singular directions are then 90 deg off the
optical axis, outside any field of view narrower than 180 deg (docs/mapper.md).

Every function is batched over N features; shapes are in the docstrings.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from companion.method.geometry import PAPER_TO_OPENCV, PinholeCamera, skew
from companion.method.mapper.projection import CameraPose, camera_ray_from_pixel, pixel_from_camera_vector, pixel_jacobian

STATE_DIM = 6
ANCHOR = slice(0, 3)
PSI, THETA, RHO = 3, 4, 5

# Reference axes (x, y, z) = camera axes (y right, z down, x optical) at initialisation, so that the
# paper's (psi, theta) = (0, 0) lies on the optical axis: h_ref = CAMERA_TO_REFERENCE @ h_c.
CAMERA_TO_REFERENCE = PAPER_TO_OPENCV
_I3 = np.eye(3)


def reference_rotation(R_nc: np.ndarray) -> np.ndarray:
    """Constant per-feature frame for the angles: reference -> NED, ``R_ref = R_nc M^T`` (..., 3, 3)."""
    return np.asarray(R_nc, dtype=float) @ CAMERA_TO_REFERENCE.T


def direction_vector(psi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``m(psi, theta)`` of eq. 3 in the reference frame: (N,), (N,) -> unit vectors (N, 3)."""
    return _direction_terms(psi, theta)[1]


def direction_derivatives(psi: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dm/dpsi`` and ``dm/dtheta`` (N, 3) each."""
    _, _, dm_dpsi, dm_dtheta = _direction_terms(psi, theta)
    return dm_dpsi, dm_dtheta


def _direction_terms(psi: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``cos theta`` (N,), ``m = [sin theta, cos theta sin psi, cos theta cos psi]``, ``dm/dpsi``
    and ``dm/dtheta`` (N, 3) each, from one ``sin`` and one ``cos`` of each angle."""
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(psi), np.cos(psi)
    d = np.empty((3,) + np.shape(psi) + (3,))  # m, dm/dpsi, dm/dtheta in one allocation
    m, dm_dpsi, dm_dtheta = d[0], d[1], d[2]
    m[..., 0] = st
    m[..., 1] = ct * sp
    m[..., 2] = ct * cp
    dm_dpsi[..., 0] = 0.0
    dm_dpsi[..., 1] = ct * cp
    dm_dpsi[..., 2] = -ct * sp
    dm_dtheta[..., 0] = ct
    dm_dtheta[..., 1] = -st * sp
    dm_dtheta[..., 2] = -st * cp
    return ct, m, dm_dpsi, dm_dtheta


def angles_from_vector(h_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 14-15 in the reference frame: vectors (N, 3) of any length -> ``psi``, ``theta`` (N,).

    ``theta = atan2(h_x, sqrt(h_y^2 + h_z^2))``, ``psi = atan2(h_y, h_z)``.
    """
    h_ref = np.asarray(h_ref, dtype=float)
    theta = np.arctan2(h_ref[:, 0], np.hypot(h_ref[:, 1], h_ref[:, 2]))
    psi = np.arctan2(h_ref[:, 1], h_ref[:, 2])
    return psi, theta


def angle_jacobian(psi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``d(psi, theta)/dm`` at the unit vector ``m(psi, theta)``: (N, 2, 3).

    Rows ``[0, cos psi, -sin psi] / cos theta`` and ``[cos theta, -sin theta sin psi,
    -sin theta cos psi]``; both are orthogonal to ``m`` (the angles ignore the vector's length).
    The ``1 / cos theta`` is the parameterisation's singularity.
    """
    dm_dpsi, dm_dtheta = direction_derivatives(psi, theta)
    return _angle_jacobian(dm_dpsi, dm_dtheta, np.cos(theta))


def _angle_jacobian(dm_dpsi: np.ndarray, dm_dtheta: np.ndarray, ct: np.ndarray) -> np.ndarray:
    """:func:`angle_jacobian` from ``dm/dpsi``, ``dm/dtheta`` (N, 3) and ``cos theta`` (N,)."""
    A = np.empty((len(ct), 2, 3))
    np.divide(dm_dpsi, (ct * ct)[:, None], out=A[:, 0])
    A[:, 1] = dm_dtheta
    return A


class RayDirections(NamedTuple):
    """The direction terms of eq. 3 for N stored features, computed once per step.

    The drift Jacobian, the prediction (eqs. 3-4) and the measurement Jacobian (eq. 5) all need
    ``sin`` and ``cos`` of the angles and ``m_world = R_ref m(psi, theta)``; each used to compute
    them again. Every term is what :func:`direction_vector`, :func:`direction_derivatives` and
    :func:`world_direction` return for the same state (the same operations, so the same bits).

    cos_theta (N,); m_world (N, 3); dm_dpsi, dm_dtheta (N, 3) in the reference frame.
    """

    cos_theta: np.ndarray
    m_world: np.ndarray
    dm_dpsi: np.ndarray
    dm_dtheta: np.ndarray

    def take(self, index: np.ndarray) -> "RayDirections":
        """The terms of the features at ``index`` (k,)."""
        return RayDirections(self.cos_theta[index], self.m_world[index], self.dm_dpsi[index], self.dm_dtheta[index])


def ray_directions(y: np.ndarray, R_ref: np.ndarray) -> RayDirections:
    """Eq. 3's direction terms of states (N, 6) with rotations (N, 3, 3): four ``sin``/``cos``
    calls for the step instead of one set per function."""
    y = np.asarray(y, dtype=float)
    ct, m, dm_dpsi, dm_dtheta = _direction_terms(y[:, PSI], y[:, THETA])
    return RayDirections(ct, np.einsum("nij,nj->ni", R_ref, m), dm_dpsi, dm_dtheta)


def world_direction(y: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """``m_world = R_ref m(psi, theta)``: states (N, 6), rotations (N, 3, 3) -> (N, 3)."""
    m_ref = direction_vector(y[:, PSI], y[:, THETA])
    return np.einsum("nij,nj->ni", R_ref, m_ref)


def camera_vector(y: np.ndarray, R_ref: np.ndarray, pose: CameraPose, directions: RayDirections | None = None) -> np.ndarray:
    """Eq. 3 with the camera offset: ``h^c = R_nc^T [rho (a - p_c) + m_world]`` -> (N, 3).

    ``h^c`` is the ray to the feature scaled by ``rho`` (so it stays finite at ``rho = 0``).
    ``directions``: :func:`ray_directions` of ``y`` if already computed.
    """
    y = np.asarray(y, dtype=float)
    m_w = world_direction(y, R_ref) if directions is None else directions.m_world
    w = y[:, RHO, None] * (y[:, ANCHOR] - pose.p_c) + m_w
    return w @ pose.R_nc


def measurement_model(
    y: np.ndarray, R_ref: np.ndarray, pose: CameraPose, camera: PinholeCamera, directions: RayDirections | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 3-4: predicted ideal pixels (N, 2) (NaN behind the camera) and ``h^c`` (N, 3)."""
    h_c = camera_vector(y, R_ref, pose, directions)
    return pixel_from_camera_vector(h_c, camera), h_c


def measurement_jacobian(
    y: np.ndarray,
    R_ref: np.ndarray,
    pose: CameraPose,
    camera: PinholeCamera,
    h_c: np.ndarray | None = None,
    directions: RayDirections | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5: ``C_x = dz/dx`` (N, 2, 6) over ``[p, dtheta]`` and ``C_y = dz/dy`` (N, 2, 6).

    With ``w = rho (a - p) + m_world - rho R_nb t_bc`` and ``h = R_nc^T w``:
    ``dh/da = rho R_nc^T``, ``dh/dpsi = R_nc^T R_ref dm/dpsi``, ``dh/dtheta = R_nc^T R_ref dm/dtheta``,
    ``dh/drho = R_nc^T (a - p_c)``, ``dh/dp = -rho R_nc^T`` and, because ``R_nc`` and the lever arm
    rotate together under ``Exp(dtheta)``, ``dh/d(dtheta) = R_nc^T [rho (a - p) + m_world]x``.
    All are chained with ``dg/dh`` (:func:`pixel_jacobian`). Features with ``h_x <= 0`` must be
    removed before calling. ``h_c``, ``directions``: :func:`camera_vector` and :func:`ray_directions`
    of ``y`` if already computed.
    """
    y = np.asarray(y, dtype=float)
    n = len(y)
    if directions is None:
        directions = ray_directions(y, R_ref)
    if h_c is None:
        h_c = camera_vector(y, R_ref, pose, directions)
    G = pixel_jacobian(h_c, camera)  # (N, 2, 3)
    RT = pose.R_nc.T
    rho = y[:, RHO]
    dm_dpsi, dm_dtheta, m_w = directions.dm_dpsi, directions.dm_dtheta, directions.m_world

    dh_dy = np.empty((n, 3, STATE_DIM))
    dh_dy[:, :, ANCHOR] = rho[:, None, None] * RT
    dh_dy[:, :, PSI] = np.einsum("nij,nj->ni", R_ref, dm_dpsi) @ pose.R_nc
    dh_dy[:, :, THETA] = np.einsum("nij,nj->ni", R_ref, dm_dtheta) @ pose.R_nc
    dh_dy[:, :, RHO] = (y[:, ANCHOR] - pose.p_c) @ pose.R_nc

    dh_dx = np.empty((n, 3, 6))
    dh_dx[:, :, 0:3] = -rho[:, None, None] * RT
    v = rho[:, None] * (y[:, ANCHOR] - pose.p) + m_w
    dh_dx[:, :, 3:6] = RT @ skew(v)
    return G @ dh_dx, G @ dh_dy


def initialise_features(
    uv: np.ndarray,
    ranges: np.ndarray,
    pose: CameraPose,
    camera: PinholeCamera,
    R_img: np.ndarray,
    sigma_rho: float,
    P_x: np.ndarray,
    R_ref: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 13-17: new features from ideal pixels (N, 2) and prior ranges (N,) along their rays.

    Anchor ``a = p_c`` (eq. 13, the camera centre rather than the body origin); angles from the
    ray expressed in the reference frame (eqs. 14-15); ``rho = 1 / range`` (eq. 16, generalised to
    any depth prior). Covariance (eq. 17)::

        P_y = J_z R_img J_z^T + e_rho sigma_rho^2 e_rho^T + J_x P_x J_x^T

    ``J_z``: only the angles depend on the pixel, ``d(psi, theta)/dz = A R_ref^T R_nc (dh/dz) / |h|``
    with ``A`` = :func:`angle_jacobian`. ``J_x``: ``da/dp = I``, ``da/d(dtheta) = -[R_nb t_bc]x``,
    ``d(psi, theta)/d(dtheta) = -A R_ref^T [m_world]x``. The prior range is treated as independent
    of the navigation error (it is a belief about the terrain, with its own spread ``sigma_rho``).

    ``R_ref`` (N, 3, 3) defaults to :func:`reference_rotation` of the current camera (tests pass it
    to evaluate the same chart at perturbed inputs). Returns ``y`` (N, 6), ``P_y`` (N, 6, 6),
    ``R_ref`` (N, 3, 3).
    """
    h, dh_dz = camera_ray_from_pixel(uv, camera)
    n = len(h)
    if R_ref is None:
        R_ref = np.broadcast_to(reference_rotation(pose.R_nc), (n, 3, 3)).copy()
    norm = np.sqrt((h * h).sum(axis=1))  # np.linalg.norm(h, axis=1), without its wrapper
    m_w = (h / norm[:, None]) @ pose.R_nc.T
    m_ref = np.einsum("nji,nj->ni", R_ref, m_w)
    psi, theta = angles_from_vector(m_ref)
    ranges = np.asarray(ranges, dtype=float).reshape(n)

    y = np.empty((n, STATE_DIM))
    y[:, ANCHOR] = pose.p_c
    y[:, PSI] = psi
    y[:, THETA] = theta
    y[:, RHO] = 1.0 / ranges

    A = angle_jacobian(psi, theta)  # (N, 2, 3)
    A_ref = A @ R_ref.transpose(0, 2, 1)  # d(psi, theta)/d(m_world), (N, 2, 3)

    J_z = np.zeros((n, STATE_DIM, 2))
    J_z[:, PSI:THETA + 1, :] = (A_ref @ pose.R_nc @ dh_dz) / norm[:, None, None]

    P = J_z @ R_img @ J_z.transpose(0, 2, 1)
    # A zero P_x (the correlated navigation model's: its error is in the features' covariance)
    # adds nothing, J_x being finite (|theta| <= pi/2 keeps A finite): then J_x is not built.
    if P_x.any():
        J_x = np.zeros((n, STATE_DIM, 6))
        J_x[:, ANCHOR, 0:3] = _I3
        J_x[:, ANCHOR, 3:6] = -skew(pose.p_c - pose.p)  # lever arm R_nb t_bc rotates with the body
        J_x[:, PSI:THETA + 1, 3:6] = -A_ref @ skew(m_w)
        P = P + J_x @ P_x @ J_x.transpose(0, 2, 1)
    P[:, RHO, RHO] += sigma_rho**2
    return y, 0.5 * (P + P.transpose(0, 2, 1)), R_ref


def navigation_frame_jacobian(
    y: np.ndarray, R_ref: np.ndarray, p: np.ndarray, directions: RayDirections | None = None
) -> np.ndarray:
    """How a stored feature moves when the navigation frame moves: ``dy/dx`` (N, 6, 6).

    The features live in the autopilot's estimated frame (docs/mapper.md, "Correlated navigation
    error"). If the estimate moves by ``x = [dp, dtheta]`` (position, and ``R_nb -> Exp(dtheta) R_nb``)
    while the world stays put, every point seen from it moves rigidly about the body origin ``p``
    (3,): the anchor by ``da = dp - [a - p]x dtheta``, the direction by ``m -> Exp(dtheta) m``, so
    ``d(psi, theta) = -A R_ref^T [m]x dtheta``, and ``rho`` (a distance) not at all. The same form as
    the initialisation's ``J_x`` (eq. 17) with the lever arm ``a - p``. ``directions``:
    :func:`ray_directions` of ``y`` if already computed.
    """
    y = np.asarray(y, dtype=float)
    n = len(y)
    if directions is None:
        directions = ray_directions(y, R_ref)
    m_w = directions.m_world
    A_ref = _angle_jacobian(directions.dm_dpsi, directions.dm_dtheta, directions.cos_theta) @ R_ref.transpose(0, 2, 1)
    J = np.zeros((n, STATE_DIM, 6))
    J[:, ANCHOR, 0:3] = _I3
    J[:, ANCHOR, 3:6] = -skew(y[:, ANCHOR] - np.asarray(p, dtype=float))
    J[:, PSI:THETA + 1, 3:6] = -A_ref @ skew(m_w)
    return J


def point_from_state(y: np.ndarray, R_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Feature position ``X = a + m_world / rho`` (N, 3) and ``J = dX/dy`` (N, 3, 6).

    ``dX/da = I``, ``dX/dpsi = R_ref dm/dpsi / rho``, ``dX/dtheta = R_ref dm/dtheta / rho``,
    ``dX/drho = -m_world / rho^2``. NaN where ``rho <= 0`` (no finite point).
    """
    y = np.asarray(y, dtype=float)
    rho = y[:, RHO]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(rho > 0, 1.0 / rho, np.nan)
    m_w = world_direction(y, R_ref)
    dm_dpsi, dm_dtheta = direction_derivatives(y[:, PSI], y[:, THETA])
    X = y[:, ANCHOR] + m_w * inv[:, None]
    J = np.zeros((len(y), 3, STATE_DIM))
    J[:, :, ANCHOR] = _I3
    J[:, :, PSI] = np.einsum("nij,nj->ni", R_ref, dm_dpsi) * inv[:, None]
    J[:, :, THETA] = np.einsum("nij,nj->ni", R_ref, dm_dtheta) * inv[:, None]
    J[:, :, RHO] = -m_w * (inv * inv)[:, None]
    return X, J


def point(y: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """Feature position ``X = a + m_world / rho`` (N, 3), as :func:`point_from_state` without its
    Jacobian. NaN where ``rho <= 0``."""
    y = np.asarray(y, dtype=float)
    rho = y[:, RHO]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(rho > 0, 1.0 / rho, np.nan)
    return y[:, ANCHOR] + world_direction(y, R_ref) * inv[:, None]


def depth_from_origin(y: np.ndarray, R_ref: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Depth (N,) from the anchor, ``1 / rho`` (``inf`` where ``rho <= 0``); ``origin`` unused."""
    rho = np.asarray(y, dtype=float)[:, RHO]
    return np.divide(1.0, np.maximum(rho, 1e-300), out=np.full(len(rho), np.inf), where=rho > 0)


def relative_depth_sigma(y: np.ndarray, P: np.ndarray, R_ref: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """First-order ``sigma_d / d = sigma_rho / rho`` (N,) (``d = 1/rho``); ``inf`` where ``rho <= 0``.

    ``R_ref`` and ``origin`` are unused (same signature as the Cartesian baseline).
    """
    rho = np.asarray(y, dtype=float)[:, RHO]
    sigma = np.sqrt(np.maximum(P[:, RHO, RHO], 0.0))
    return np.divide(sigma, rho, out=np.full(len(rho), np.inf), where=rho > 0)


def point_at_sigma(y: np.ndarray, P: np.ndarray, R_ref: np.ndarray, origin: np.ndarray, k: float) -> np.ndarray:
    """The point of each feature's line of sight ``k`` sigma nearer than its estimate (``k < 0``:
    farther; docs/mapper.md, "Bounds of an unconverged feature"): the anchor ray at inverse depth
    ``rho + k sigma_rho``, ``a + m_world / (rho + k sigma_rho)`` (N, 3). Inverse depth is Gaussian
    in ``rho``, so the bound is the model's own however wide: a new feature (``sigma_rho`` the
    prior's) is only known to lie beyond a few metres, a converged one hardly nearer or farther
    than its estimate. NaN where ``rho + k sigma_rho <= 0`` (the far bound at infinity).
    ``origin`` is unused (the Cartesian baseline's signature)."""
    y = np.asarray(y, dtype=float)
    rho_k = y[:, RHO] + k * np.sqrt(np.maximum(P[:, RHO, RHO], 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(rho_k > 0, 1.0 / rho_k, np.nan)
    return y[:, ANCHOR] + world_direction(y, R_ref) * inv[:, None]


def normalise_state(y: np.ndarray) -> np.ndarray:
    """Wrap ``psi`` into (-pi, pi] (a shift by 2 pi: the covariance is unchanged). (N, 6) -> (N, 6)."""
    y = np.array(y, dtype=float)
    y[:, PSI] = np.pi - np.mod(np.pi - y[:, PSI], 2.0 * np.pi)
    return y
