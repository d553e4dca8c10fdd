"""Independent per-feature EKF update, batched over the matched features (seed 000, eqs. 6-9).

Each feature ``j`` is updated on its own with ``P_j = blockdiag(P_x, P_yj)`` (eq. 6). Only the
feature is corrected (the vehicle state belongs to the autopilot's filter), so the vehicle part of
the Jacobian enters the innovation covariance only: ``K = P_y C_y^T S^-1`` (eq. 7; the seed's
``P_y C^T`` can only mean the feature block ``C_y``, for the dimensions to agree). For the feature
the navigation error acts as extra measurement noise ``R_eff = C_x P_x C_x^T + R_img``, and the
covariance is updated in Joseph form (equal to eq. 9 for this gain, but symmetric positive
semi-definite by construction)::

    P+ = (I - K C_y) P (I - K C_y)^T + K R_eff K^T

An edge feature (docs/mapper.md, "Edgels") is measured across its edge only: the scalar
``n^T (z - g)`` with ``n`` the edge's unit normal, Jacobians ``n^T C`` and noise ``n^T R n``
(:func:`ekf_update_across`, the same equations with 1 x D rows).
"""

from __future__ import annotations

import numpy as np

from companion.method.mapper.matching import inverse_2x2, navigation_term_vanishes


_IDENTITY = {k: np.eye(k) for k in range(1, 7)}


def _identity(dim: int) -> np.ndarray:
    """``np.eye(dim)``, built once for the state sizes of the models."""
    eye = _IDENTITY.get(dim)
    return np.eye(dim) if eye is None else eye


def ekf_update(
    y: np.ndarray,
    P_y: np.ndarray,
    innovation: np.ndarray,
    C_x: np.ndarray,
    C_y: np.ndarray,
    P_x: np.ndarray,
    R_img: np.ndarray,
    S_inverse: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 7-9 (Joseph form) for N features at once.

    y (N, D), P_y (N, D, D), innovation ``z - g`` (N, 2), C_x (N, 2, 6), C_y (N, 2, D), P_x (6, 6),
    R_img (2, 2) -> updated y (N, D), P_y (N, D, D) and ``ok`` (N,). A feature whose ``S`` is not
    positive definite, or whose result is not finite, keeps its prior state (``ok = False``).

    ``S_inverse``: ``S^-1`` (N, 2, 2) and its flags (N,) when the matching computed them for the
    same ``S`` (with a vanishing navigation term, :func:`~companion.mapper.matching.navigation_term_vanishes`,
    the matching's ``S`` of these features is this ``S``); they are then not computed again.
    """
    y = np.asarray(y, dtype=float)
    P_y = np.asarray(P_y, dtype=float)
    n, dim = y.shape
    if n == 0:
        return y.copy(), P_y.copy(), np.zeros(0, dtype=bool)
    C_yT = C_y.transpose(0, 2, 1)
    if navigation_term_vanishes(P_x, C_x):
        R_eff = R_img  # (2, 2): C_x P_x C_x^T is zero
    else:
        R_eff = C_x @ P_x @ C_x.transpose(0, 2, 1) + R_img  # (N, 2, 2)
    if S_inverse is None:
        S = C_y @ P_y @ C_yT + R_eff
        S_inv, ok = inverse_2x2(S)  # uses the symmetric part (S_01 + S_10) / 2
    else:
        S_inv, ok = S_inverse[0], S_inverse[1].copy()

    K = P_y @ C_yT @ S_inv  # (N, D, 2), eq. 7
    y_new = y + np.einsum("nij,nj->ni", K, innovation)  # eq. 8
    I_KC = _identity(dim) - K @ C_y
    P_new = I_KC @ P_y @ I_KC.transpose(0, 2, 1) + K @ R_eff @ K.transpose(0, 2, 1)  # eq. 9, Joseph
    P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))

    ok &= (P_new.diagonal(axis1=1, axis2=2) >= 0).all(axis=1)
    if not np.isfinite(y_new.sum() + P_new.sum()):  # (a finite sum: all finite, the usual case)
        ok &= np.isfinite(y_new).all(axis=1) & np.isfinite(P_new).all(axis=(1, 2))
    if np.count_nonzero(ok) < n:
        y_new[~ok] = y[~ok]
        P_new[~ok] = P_y[~ok]
    return y_new, P_new, ok


def ekf_update_across(
    y: np.ndarray,
    P_y: np.ndarray,
    innovation: np.ndarray,
    H_y: np.ndarray,
    r: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 7-9 (Joseph form) for N scalar measurements at once: the distance across an edge.

    y (N, D), P_y (N, D, D), innovation ``n^T (z - g)`` (N,), ``H_y = n^T C_y`` (N, D) and
    ``r = n^T (C_x P_x C_x^T + R_img) n`` (N,) -> updated y, P_y and ``ok`` (N,) as
    :func:`ekf_update`. With ``s = H P H^T + r`` and ``K = P H^T / s``::

        y+ = y + K nu,   P+ = (I - K H) P (I - K H)^T + r K K^T

    which is :func:`ekf_update` in the limit of an infinite noise along the edge
    (tests/test_edgels.py)."""
    y = np.asarray(y, dtype=float)
    P_y = np.asarray(P_y, dtype=float)
    n, dim = y.shape
    if n == 0:
        return y.copy(), P_y.copy(), np.zeros(0, dtype=bool)
    PH = np.einsum("nij,nj->ni", P_y, H_y)  # (N, D)
    s = np.einsum("ni,ni->n", H_y, PH) + r
    ok = np.isfinite(s) & (s > 0)
    K = PH / np.where(ok, s, 1.0)[:, None]
    y_new = y + K * np.where(ok, innovation, 0.0)[:, None]
    I_KH = _identity(dim) - K[:, :, None] * H_y[:, None, :]
    P_new = I_KH @ P_y @ I_KH.transpose(0, 2, 1) + r[:, None, None] * (K[:, :, None] * K[:, None, :])
    P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
    ok &= (P_new.diagonal(axis1=1, axis2=2) >= 0).all(axis=1)
    if not np.isfinite(y_new.sum() + P_new.sum()):
        ok &= np.isfinite(y_new).all(axis=1) & np.isfinite(P_new).all(axis=(1, 2))
    if np.count_nonzero(ok) < n:
        y_new[~ok] = y[~ok]
        P_new[~ok] = P_y[~ok]
    return y_new, P_new, ok
