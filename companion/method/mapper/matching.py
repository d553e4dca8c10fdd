"""Point matching by Mahalanobis distance (seed 000, section II.C, eqs. 10-12).

Every database point ``j`` has a predicted pixel ``g_j`` and a search region ``S_j``; every
measurement ``z_i`` gets a distance ``Z_ij`` to every point. A pair is accepted when it is inside
the gate and *mutually* nearest: ``i`` is ``j``'s nearest measurement and ``j`` is ``i``'s nearest
point ("if database point j is not closer to any other measurement", made symmetric so that two
points can never claim one measurement). A measurement inside some point's gate that is not
matched is *ambiguous*: it is neither used nor initialised as a new feature (it would duplicate
a feature already in the database).

Two forms of the same equations: dense ``(N, M)`` matrices (:func:`mahalanobis_distances`,
:func:`gate_and_match`, :func:`near_stored_features`; the straightforward form, used by tests and
small problems) and sparse candidate pairs (:func:`candidate_pairs`, :func:`gate_and_match_pairs`,
:func:`near_stored_pairs`; what the mapper runs). A point's gate is a small ellipse, so of the
``N x M`` pairs only a few percent can pass any test (measured: 5,000 of 143,000 at 300 features);
the sparse form finds those through the measurements sorted by ``u`` and decides exactly as the
dense form (tests/test_mapper_fast_paths.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def navigation_term_vanishes(P_x: np.ndarray, C_x: np.ndarray) -> bool:
    """Whether ``C_x P_x C_x^T`` is exactly zero, so that adding it changes nothing (but the sign
    of a zero): ``P_x`` (6, 6) all zero and ``C_x`` (N, 2, 6) finite (``inf * 0`` would be NaN).
    With the correlated navigation model (docs/mapper.md) the measurement's ``P_x`` is zero every
    step: the navigation error is already in the features' covariance."""
    return not P_x.any() and math.isfinite(C_x.sum())


def innovation_covariance(
    C_x: np.ndarray, C_y: np.ndarray, P_x: np.ndarray, P_y: np.ndarray, R_img: np.ndarray
) -> np.ndarray:
    """Eq. 10 with eq. 6's block-diagonal ``P_j``: ``S_j = C_x P_x C_x^T + C_y P_yj C_y^T + R_img``.

    C_x (N, 2, 6), C_y (N, 2, D), P_x (6, 6), P_y (N, D, D), R_img (2, 2) -> S (N, 2, 2), symmetric.
    """
    if navigation_term_vanishes(P_x, C_x):
        S = C_y @ P_y @ C_y.transpose(0, 2, 1) + R_img
    else:
        S = C_x @ P_x @ C_x.transpose(0, 2, 1) + C_y @ P_y @ C_y.transpose(0, 2, 1) + R_img
    return 0.5 * (S + S.transpose(0, 2, 1))


def inverse_2x2(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 2x2 matrices (N, 2, 2) and a mask (N,) of those positive definite.

    Closed form (no per-matrix factorisation); rows that are not positive definite or not finite
    get a zero inverse and ``ok = False``.
    """
    a, b, d = S[:, 0, 0], 0.5 * (S[:, 0, 1] + S[:, 1, 0]), S[:, 1, 1]
    ad = a * d
    det = ad - b * b
    ok = np.isfinite(det) & (a > 0) & (det > 1e-12 * np.maximum(ad, 1e-300))
    all_ok = np.count_nonzero(ok) == len(ok)  # (ok.all() at a third of its cost)
    # the usual case: every det positive and finite, a plain division (the same values)
    if all_ok:
        inv_det = 1.0 / det
    else:  # zero the refused rows first: their a, b or d may be inf or NaN (inf * 0 warns)
        inv_det = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        a, b, d = np.where(ok, a, 0.0), np.where(ok, b, 0.0), np.where(ok, d, 0.0)
    S_inv = np.empty_like(S)
    S_inv[:, 0, 0] = d * inv_det
    S_inv[:, 1, 1] = a * inv_det
    S_inv[:, 0, 1] = S_inv[:, 1, 0] = -b * inv_det
    return S_inv, ok


def mahalanobis_distances(z: np.ndarray, g: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Eqs. 11-12: ``Z_ij = e_ij^T S_j^-1 e_ij`` with ``e_ij = z_i - g_j``.

    z (M, 2) measurements, g (N, 2) predictions, S (N, 2, 2) -> Z (N, M) indexed [point j,
    measurement i]; ``inf`` for a point whose ``S_j`` is not positive definite.
    """
    S_inv, ok = inverse_2x2(S)
    e0 = z[None, :, 0] - g[:, 0, None]  # (N, M) per axis: no (N, M, 2) temporaries
    e1 = z[None, :, 1] - g[:, 1, None]
    Z = _quadratic_form(S_inv[:, 0, 0, None], S_inv[:, 0, 1, None], S_inv[:, 1, 1, None], e0, e1)
    Z[~ok, :] = np.inf
    return Z


def _quadratic_form(a, b, c, e0, e1):
    """``e^T [[a, b], [b, c]] e = a e0^2 + 2 b e0 e1 + c e1^2``, the one evaluation order that the
    dense and the pair forms share (so that both give bit-identical distances)."""
    return a * (e0 * e0) + (2.0 * b) * (e0 * e1) + c * (e1 * e1)


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


# ------------------------------------------------------------------------------------------------
# The same tests on candidate pairs (what the mapper runs)
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CandidatePairs:
    """Pairs (point ``j``, measurement ``i``) that pass ``Z_ij < chi2`` or ``|z_i - g_j| < px``, and
    no others, in no particular order: ``point`` (P,) and ``meas`` (P,) intp, ``Z`` (P,) the
    distance of eqs. 11-12 (``inf`` for a point whose ``S_j`` is not positive definite), ``d2`` (P,)
    the squared pixel distance."""

    point: np.ndarray
    meas: np.ndarray
    Z: np.ndarray
    d2: np.ndarray

    def __len__(self) -> int:
        return len(self.point)


def candidate_pairs(
    z: np.ndarray,
    g: np.ndarray,
    S: np.ndarray,
    chi2: float,
    px: float,
    S_inverse: tuple[np.ndarray, np.ndarray] | None = None,
) -> CandidatePairs:
    """Every pair with ``Z_ij < chi2`` (eqs. 11-12) or ``|z_i - g_j| < px``, without the ``N x M`` matrix.

    z (M, 2) measurements, g (N, 2) predictions, S (N, 2, 2). A pair inside point ``j``'s ellipse
    ``e^T S_j^-1 e < chi2`` has ``|e_u| < sqrt(chi2 S_j,uu)`` (the ellipse's half-width in ``u``: the
    least ``e^T S^-1 e`` at a given ``e_u`` is ``e_u^2 / S_uu``), and one within ``px`` has
    ``|e_u| < px``. With the measurements sorted by ``u`` each point's partners in that strip are
    one contiguous run, found by ``searchsorted``; only those runs are evaluated, then tested
    exactly with the arithmetic of :func:`mahalanobis_distances` (same values to the bit).
    ``S_inverse``: :func:`inverse_2x2` of ``S`` if already computed.
    """
    z = np.asarray(z, dtype=float).reshape(-1, 2)
    g = np.asarray(g, dtype=float).reshape(-1, 2)
    n, m = len(g), len(z)
    if n == 0 or m == 0:
        empty = np.zeros(0, dtype=np.intp)
        return CandidatePairs(empty, empty.copy(), np.zeros(0), np.zeros(0))
    S_inv, ok = inverse_2x2(S) if S_inverse is None else S_inverse
    all_ok = np.count_nonzero(ok) == n
    half_u = np.sqrt(chi2 * S[:, 0, 0] if all_ok else np.where(ok, chi2 * S[:, 0, 0], 0.0))  # S_uu > 0 where ok
    # widened by a relative 1e-9 so that rounding can never drop a pair the exact test keeps
    half_u = np.maximum(half_u, px) * (1.0 + 1e-9) + 1e-12
    order = np.argsort(z[:, 0], kind="stable")
    zu = z[order, 0]
    start = np.searchsorted(zu, g[:, 0] - half_u, side="left")
    count = np.searchsorted(zu, g[:, 0] + half_u, side="right") - start
    point = np.repeat(np.arange(n), count)
    first = np.cumsum(count) - count  # where each point's run starts among the pairs
    meas = order[np.arange(point.size) - np.repeat(first - start, count)]
    e0 = z[meas, 0] - g[point, 0]
    e1 = z[meas, 1] - g[point, 1]
    Z = _quadratic_form(S_inv[point, 0, 0], S_inv[point, 0, 1], S_inv[point, 1, 1], e0, e1)
    if not all_ok:
        Z[~ok[point]] = np.inf
    d2 = e0 * e0 + e1 * e1
    keep = ((Z < chi2) | (d2 < px * px)).nonzero()[0]  # then gathers (faster than 4 boolean indexes)
    return CandidatePairs(point[keep], meas[keep], Z[keep], d2[keep])


def gate_and_match_pairs(
    point: np.ndarray, meas: np.ndarray, Z: np.ndarray, gate: float, n_meas: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`gate_and_match` on pairs: the same decisions as on the dense matrix whose other entries
    are at least ``gate``.

    point (P,), meas (P,), Z (P,) (any pairs, at most one per (point, measurement)), n_meas = M ->
    ``point_idx`` (K,) ascending, ``meas_idx`` (K,), ``ambiguous`` (M,) bool. Only pairs inside the
    gate can be a point's or a measurement's nearest when that nearest is inside the gate, so the
    mutual test needs no others. Ties go to the lower index, as in the dense form.
    """
    inside = (Z < gate).nonzero()[0]
    p, i, d = point[inside], meas[inside], Z[inside]
    k = len(p)
    ambiguous = np.zeros(n_meas, dtype=bool)
    if k == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty.copy(), ambiguous
    nearest_of_point = _first_of_groups(np.lexsort((i, d, p)), p)  # nearest measurement of each point
    nearest_of_meas = _first_of_groups(np.lexsort((p, d, i)), i)  # nearest point of each measurement
    mutual = np.flatnonzero(nearest_of_point & nearest_of_meas)
    mutual = mutual[np.argsort(p[mutual], kind="stable")]
    ambiguous[i] = True
    ambiguous[i[mutual]] = False
    return p[mutual].astype(np.intp), i[mutual].astype(np.intp), ambiguous


def _first_of_groups(order: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Mask (P,) of the first element of each run of equal ``key`` along ``order``."""
    sorted_key = key[order]
    first = np.empty(len(order), dtype=bool)
    first[:1] = True
    np.not_equal(sorted_key[1:], sorted_key[:-1], out=first[1:])
    out = np.zeros(len(order), dtype=bool)
    out[order[first]] = True
    return out


def near_stored_pairs(pairs: CandidatePairs, n_meas: int, exclusion_chi2: float, exclusion_px: float) -> np.ndarray:
    """:func:`near_stored_features` on candidate pairs (built with ``chi2 >= exclusion_chi2`` and
    ``px >= exclusion_px``) -> (M,) bool."""
    near = np.zeros(n_meas, dtype=bool)
    near[pairs.meas[(pairs.Z < exclusion_chi2) | (pairs.d2 < exclusion_px * exclusion_px)]] = True
    return near
