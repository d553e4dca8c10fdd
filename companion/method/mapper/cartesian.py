"""Cartesian feature parameterisation: the baseline the paper compares against (figs. 2 vs 3).

Feature state ``y = X = [x, y, z]`` (NED, m). Same measurement model (eqs. 3-4 with ``rho = 1``
and no anchor), same update, matching and database as the inverse-depth mapper; only the state,
its Jacobians and its initialisation differ. A new feature is placed at the prior range along
its ray with a depth spread ``sigma_depth_rel * range`` along the ray, which is the Gaussian the
Cartesian filter has to assume for an unknown depth (the reason it converges slower).

Every function is batched over N features and has the signature of its
:mod:`companion.mapper.inverse_depth` counterpart; ``R_ref`` is carried but unused by the model.
"""

from __future__ import annotations

import numpy as np

from companion.method.geometry import PinholeCamera, skew
from companion.method.mapper.inverse_depth import reference_rotation
from companion.method.mapper.projection import CameraPose, camera_ray_from_pixel, pixel_jacobian

STATE_DIM = 3

__all__ = [
    "STATE_DIM",
    "reference_rotation",
    "camera_vector",
    "ray_directions",
    "measurement_model",
    "measurement_jacobian",
    "initialise_features",
    "navigation_frame_jacobian",
    "point_from_state",
    "relative_depth_sigma",
    "depth_from_origin",
    "normalise_state",
]


def ray_directions(y: np.ndarray, R_ref: np.ndarray) -> None:
    """No direction terms to share (a Cartesian point has no angles): ``None``."""
    return None


def camera_vector(y: np.ndarray, R_ref: np.ndarray, pose: CameraPose, directions: None = None) -> np.ndarray:
    """``h^c = R_nc^T (X - p_c)`` (N, 3)."""
    return (np.asarray(y, dtype=float) - pose.p_c) @ pose.R_nc


def measurement_model(
    y: np.ndarray, R_ref: np.ndarray, pose: CameraPose, camera: PinholeCamera, directions: None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted ideal pixels (N, 2) (NaN behind the camera) and ``h^c`` (N, 3)."""
    h_c = camera_vector(y, R_ref, pose)
    return camera.project(h_c), h_c


def measurement_jacobian(
    y: np.ndarray,
    R_ref: np.ndarray,
    pose: CameraPose,
    camera: PinholeCamera,
    h_c: np.ndarray | None = None,
    directions: None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``C_x`` (N, 2, 6) and ``C_y`` (N, 2, 3): ``dh/dX = R_nc^T``, ``dh/dp = -R_nc^T``,
    ``dh/d(dtheta) = R_nc^T [X - p]x``, chained with ``dg/dh``."""
    y = np.asarray(y, dtype=float)
    if h_c is None:
        h_c = camera_vector(y, R_ref, pose)
    G = pixel_jacobian(h_c, camera)
    RT = pose.R_nc.T
    dh_dx = np.empty((len(y), 3, 6))
    dh_dx[:, :, 0:3] = -RT
    dh_dx[:, :, 3:6] = RT @ skew(y - pose.p)
    return G @ dh_dx, G @ RT


def initialise_features(
    uv: np.ndarray,
    ranges: np.ndarray,
    pose: CameraPose,
    camera: PinholeCamera,
    R_img: np.ndarray,
    sigma_depth_rel: float,
    P_x: np.ndarray,
    R_ref: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``X = p_c + r m_world`` with ``m_world = R_nc h / |h|``; the covariance in the form of eq. 17::

        P = J_z R_img J_z^T + (sigma_depth_rel r)^2 m m^T + J_x P_x J_x^T

    ``J_z = r R_nc (I - h_u h_u^T) (dh/dz) / |h|``, ``J_x = [I, -[X - p]x]``.
    Returns ``y`` (N, 3), ``P`` (N, 3, 3), ``R_ref`` (N, 3, 3) (stored, unused).
    """
    h, dh_dz = camera_ray_from_pixel(uv, camera)
    n = len(h)
    if R_ref is None:
        R_ref = np.broadcast_to(reference_rotation(pose.R_nc), (n, 3, 3)).copy()
    r = np.asarray(ranges, dtype=float).reshape(n)
    norm = np.linalg.norm(h, axis=1)
    h_u = h / norm[:, None]
    m_w = h_u @ pose.R_nc.T
    X = pose.p_c + r[:, None] * m_w

    proj = (np.eye(3) - h_u[:, :, None] * h_u[:, None, :]) / norm[:, None, None]
    J_z = r[:, None, None] * (pose.R_nc @ proj @ dh_dz)  # (N, 3, 2)
    J_x = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -skew(X - pose.p)], axis=2)
    sigma_d = sigma_depth_rel * r
    P = (
        J_z @ R_img @ np.swapaxes(J_z, 1, 2)
        + (sigma_d**2)[:, None, None] * (m_w[:, :, None] * m_w[:, None, :])
        + J_x @ P_x @ np.swapaxes(J_x, 1, 2)
    )
    return X, 0.5 * (P + np.swapaxes(P, 1, 2)), R_ref


def navigation_frame_jacobian(y: np.ndarray, R_ref: np.ndarray, p: np.ndarray, directions: None = None) -> np.ndarray:
    """``dX/dx`` (N, 3, 6) of a stored point when the navigation frame moves by ``x = [dp, dtheta]``
    (rigidly about the body origin ``p`` (3,)): ``[I, -[X - p]x]`` (see the inverse-depth version)."""
    y = np.asarray(y, dtype=float)
    return np.concatenate([np.broadcast_to(np.eye(3), (len(y), 3, 3)), -skew(y - np.asarray(p, dtype=float))], axis=2)


def point_from_state(y: np.ndarray, R_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The state is the point: ``X`` (N, 3), ``J = I`` (N, 3, 3)."""
    y = np.asarray(y, dtype=float)
    return y.copy(), np.broadcast_to(np.eye(3), (len(y), 3, 3)).copy()


def point(y: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """The state is the point: ``X`` (N, 3)."""
    return np.array(y, dtype=float)


def depth_from_origin(y: np.ndarray, R_ref: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Distance (N,) from the camera centre at initialisation ``origin`` (N, 3) to the point."""
    return np.linalg.norm(np.asarray(y, dtype=float) - origin, axis=1)


def relative_depth_sigma(y: np.ndarray, P: np.ndarray, R_ref: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Sigma along the ray from ``origin`` (N, 3; camera centre at initialisation) over the range (N,).

    Measured from the initial camera, like the inverse-depth ``sigma_rho / rho`` (depth from the
    anchor), so the two parameterisations are held to the same convergence test.
    """
    d = np.asarray(y, dtype=float) - origin
    r = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = d / r[:, None]
        var = np.einsum("ni,nij,nj->n", u, P, u)
        return np.where(r > 0, np.sqrt(np.maximum(var, 0.0)) / r, np.inf)


def point_at_sigma(y: np.ndarray, P: np.ndarray, R_ref: np.ndarray, origin: np.ndarray, k: float) -> np.ndarray:
    """The point ``k`` sigma nearer than the estimate (``k < 0``: farther) along the ray from
    ``origin`` (N, 3; camera centre at initialisation): ``X - k sigma_u u`` with ``u`` that ray's
    unit direction and ``sigma_u^2 = u^T P u`` (N, 3) (first order: the Cartesian model's Gaussian
    is in ``X``). NaN where a near bound reaches the origin."""
    X = np.asarray(y, dtype=float)
    d = X - origin
    r = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = d / r[:, None]
        sigma = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", u, P, u), 0.0))
        at = r - k * sigma
        return np.where((at > 0)[:, None], origin + u * at[:, None], np.nan)


def normalise_state(y: np.ndarray) -> np.ndarray:
    """Nothing to wrap in a Cartesian state. (N, 3) -> (N, 3)."""
    return np.array(y, dtype=float)
