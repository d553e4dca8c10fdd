"""Point matching by Mahalanobis distance (seed 000, section II.C, eqs. 10-12).

Every database point ``j`` has a predicted pixel ``g_j`` and a search region ``S_j``; every
measurement ``z_i`` gets a distance ``Z_ij`` to every point. A pair is accepted when it is inside
the gate and *mutually* nearest: ``i`` is ``j``'s nearest measurement and ``j`` is ``i``'s nearest
point ("if database point j is not closer to any other measurement", made symmetric so that two
points can never claim one measurement). A measurement inside some point's gate that is not
matched is *ambiguous*: it is neither used nor initialised as a new feature (it would duplicate
a feature already in the database).
"""

from __future__ import annotations

import numpy as np


def innovation_covariance(
    C_x: np.ndarray, C_y: np.ndarray, P_x: np.ndarray, P_y: np.ndarray, R_img: np.ndarray
) -> np.ndarray:
    """Eq. 10 with eq. 6's block-diagonal ``P_j``: ``S_j = C_x P_x C_x^T + C_y P_yj C_y^T + R_img``.

    C_x (N, 2, 6), C_y (N, 2, D), P_x (6, 6), P_y (N, D, D), R_img (2, 2) -> S (N, 2, 2), symmetric.
    """
    S = C_x @ P_x @ np.swapaxes(C_x, 1, 2) + C_y @ P_y @ np.swapaxes(C_y, 1, 2) + R_img
    return 0.5 * (S + np.swapaxes(S, 1, 2))


def inverse_2x2(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 2x2 matrices (N, 2, 2) and a mask (N,) of those positive definite.

    Closed form (no per-matrix factorisation); rows that are not positive definite or not finite
    get a zero inverse and ``ok = False``.
    """
    a, b, d = S[:, 0, 0], 0.5 * (S[:, 0, 1] + S[:, 1, 0]), S[:, 1, 1]
    det = a * d - b * b
    ok = np.isfinite(det) & (a > 0) & (det > 1e-12 * np.maximum(a * d, 1e-300))
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    S_inv = np.empty_like(S)
    S_inv[:, 0, 0] = d * inv_det
    S_inv[:, 1, 1] = a * inv_det
    S_inv[:, 0, 1] = S_inv[:, 1, 0] = -b * inv_det
    S_inv[~ok] = 0.0
    return S_inv, ok


def mahalanobis_distances(z: np.ndarray, g: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Eqs. 11-12: ``Z_ij = e_ij^T S_j^-1 e_ij`` with ``e_ij = z_i - g_j``.

    z (M, 2) measurements, g (N, 2) predictions, S (N, 2, 2) -> Z (N, M) indexed [point j,
    measurement i]; ``inf`` for a point whose ``S_j`` is not positive definite.
    """
    S_inv, ok = inverse_2x2(S)
    e = z[None, :, :] - g[:, None, :]  # (N, M, 2)
    Z = np.einsum("nmi,nij,nmj->nm", e, S_inv, e)
    Z[~ok, :] = np.inf
    return Z


def gate_and_match(Z: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gate ``Z < gate`` and mutual nearest neighbours.

    Z (N points, M measurements) -> ``point_idx`` (K,), ``meas_idx`` (K,) of the accepted pairs, and
    ``ambiguous`` (M,) bool: measurements inside some point's gate that were not matched.
    Ties go to the lower index.
    """
    n, m = Z.shape
    if n == 0 or m == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(m, dtype=bool)
    inside = Z < gate
    best_meas = np.argmin(Z, axis=1)  # (N,) nearest measurement of each point
    best_point = np.argmin(Z, axis=0)  # (M,) nearest point of each measurement
    points = np.arange(n)
    mutual = (best_point[best_meas] == points) & inside[points, best_meas]
    point_idx = points[mutual]
    meas_idx = best_meas[mutual]
    matched = np.zeros(m, dtype=bool)
    matched[meas_idx] = True
    ambiguous = inside.any(axis=0) & ~matched
    return point_idx, meas_idx, ambiguous


def near_stored_features(
    Z: np.ndarray, z: np.ndarray, g: np.ndarray, exclusion_chi2: float, exclusion_px: float
) -> np.ndarray:
    """Measurements that must not start a new feature because a stored one is (probably) the same point.

    Z (N, M) distances of eq. 12, z (M, 2) measurements, g (N, 2) predictions -> (M,) bool:
    ``Z_ij < exclusion_chi2`` or ``|z_i - g_j| < exclusion_px`` for some ``j``.
    """
    if len(g) == 0 or len(z) == 0:
        return np.zeros(len(z), dtype=bool)
    d2 = np.sum((z[None, :, :] - g[:, None, :]) ** 2, axis=2)
    return ((Z < exclusion_chi2) | (d2 < exclusion_px**2)).any(axis=0)
