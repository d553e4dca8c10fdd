"""The reference the batched mapper is measured against: the same equations written the
straightforward way, one feature at a time in a Python loop, on that feature's own small NumPy
arrays (state ``(6,)``, covariance ``(6, 6)``, Jacobians ``(2, 6)``).

Equations (seed 000; docs/mapper.md), for one inverse-depth feature
``y = [a (3), psi, theta, rho]`` with its constant reference rotation ``R_ref``:

- direction (eq. 3): ``m = R_ref [sin theta, cos theta sin psi, cos theta cos psi]``;
- camera vector (eq. 3): ``h = R_nc^T (rho (a - p_c) + m)``;
- pixel (eq. 4): ``u = c_u + f_u h_y / h_x``, ``v = c_v + f_v h_z / h_x``;
- Jacobian (eq. 5) by the chain rule through ``h``, over the feature and over the vehicle error
  ``x = [p, dtheta]`` (``R_nb_true = Exp(dtheta) R_nb``, lever arm rotating with the body);
- innovation covariance (eq. 10): ``S = C_x P_x C_x^T + C_y P_y C_y^T + R``;
- Mahalanobis distance (eqs. 11-12): ``Z_ij = e^T S_j^-1 e``, ``e = z_i - g_j``; gate ``Z < Z_lim``
  and mutual nearest neighbours; the pairs near enough to matter (inside a gate or an exclusion
  distance), which the batched mapper finds without the ``N x M`` matrix and the loop finds by
  computing each feature's whole row;
- EKF update (eqs. 7-9), feature only, Joseph form with ``R_eff = C_x P_x C_x^T + R``.

Each ``*_one`` function is one feature. The functions without the suffix loop over features and
take and return the batched code's arrays (same signatures as ``companion.method.mapper.inverse_depth``,
``companion.method.mapper.matching`` and ``companion.method.mapper.update``), so the benchmark can run the
mapper with either. Inside the loop over features the distances of one feature to all ``M``
measurements are one small vector expression (``(M,)``): a double Python loop over features and
measurements would be slower still, and nobody would write it; the comparison is therefore with the
strongest straightforward version. ``tests/test_benchmarks_reference.py`` proves both give the same
numbers.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from companion.method.mapper import inverse_depth

ANCHOR = slice(0, 3)
PSI, THETA, RHO = 3, 4, 5


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _inverse_2x2(S: np.ndarray) -> tuple[np.ndarray, bool]:
    """Inverse of one symmetric 2x2 and whether it is positive definite (same test as the mapper:
    ``S_00 > 0`` and ``det > 1e-12 S_00 S_11``)."""
    a, b, d = S[0, 0], 0.5 * (S[0, 1] + S[1, 0]), S[1, 1]
    det = a * d - b * b
    ok = bool(math.isfinite(det) and a > 0 and det > 1e-12 * max(a * d, 1e-300))
    if not ok:
        return np.zeros((2, 2)), False
    return np.array([[d, -b], [-b, a]]) / det, True


# ------------------------------------------------------------------------------------------------
# One feature
# ------------------------------------------------------------------------------------------------


def direction_one(psi: float, theta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m(psi, theta)`` (3,) and its derivatives ``dm/dpsi``, ``dm/dtheta`` (3,) in the reference frame."""
    st, ct, sp, cp = math.sin(theta), math.cos(theta), math.sin(psi), math.cos(psi)
    m = np.array([st, ct * sp, ct * cp])
    dm_dpsi = np.array([0.0, ct * cp, -ct * sp])
    dm_dtheta = np.array([ct, -st * sp, -st * cp])
    return m, dm_dpsi, dm_dtheta


def measurement_model_one(y: np.ndarray, R_ref: np.ndarray, pose, camera) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 3-4 for one feature: ideal pixel (2,) (NaN behind the camera) and ``h^c`` (3,)."""
    m, _, _ = direction_one(y[PSI], y[THETA])
    w = y[RHO] * (y[ANCHOR] - pose.p_c) + R_ref @ m
    h = pose.R_nc.T @ w
    if h[0] <= 0:
        return np.array([np.nan, np.nan]), h
    return np.array([camera.cx + camera.fx * h[1] / h[0], camera.cy + camera.fy * h[2] / h[0]]), h


def measurement_jacobian_one(y: np.ndarray, R_ref: np.ndarray, pose, camera) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5 for one feature in front of the camera: ``C_x`` (2, 6) over ``[p, dtheta]`` and ``C_y`` (2, 6)."""
    m, dm_dpsi, dm_dtheta = direction_one(y[PSI], y[THETA])
    m_w = R_ref @ m
    RT = pose.R_nc.T
    rho = y[RHO]
    h = RT @ (rho * (y[ANCHOR] - pose.p_c) + m_w)
    G = np.array([[-camera.fx * h[1] / h[0] ** 2, camera.fx / h[0], 0.0],
                  [-camera.fy * h[2] / h[0] ** 2, 0.0, camera.fy / h[0]]])
    dh_dy = np.empty((3, 6))
    dh_dy[:, ANCHOR] = rho * RT
    dh_dy[:, PSI] = RT @ (R_ref @ dm_dpsi)
    dh_dy[:, THETA] = RT @ (R_ref @ dm_dtheta)
    dh_dy[:, RHO] = RT @ (y[ANCHOR] - pose.p_c)
    dh_dx = np.empty((3, 6))
    dh_dx[:, 0:3] = -rho * RT
    # The camera centre and axes both turn with the body error: h depends on dtheta through
    # R_nc^T Exp(-dtheta) [rho (a - p) + m_w] (p = body origin, the lever arm turns too).
    dh_dx[:, 3:6] = RT @ _skew(rho * (y[ANCHOR] - pose.p) + m_w)
    return G @ dh_dx, G @ dh_dy


def innovation_covariance_one(C_x, C_y, P_x, P_y, R_img) -> np.ndarray:
    """Eq. 10 for one feature: (2, 2), symmetrised."""
    S = C_x @ P_x @ C_x.T + C_y @ P_y @ C_y.T + R_img
    return 0.5 * (S + S.T)


def mahalanobis_row_one(z: np.ndarray, g: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Eqs. 11-12: distances (M,) of all measurements ``z`` (M, 2) to one prediction ``g`` (2,)."""
    S_inv, ok = _inverse_2x2(S)
    if not ok:
        return np.full(len(z), np.inf)
    e0 = z[:, 0] - g[0]
    e1 = z[:, 1] - g[1]
    return S_inv[0, 0] * e0 * e0 + (S_inv[0, 1] + S_inv[1, 0]) * e0 * e1 + S_inv[1, 1] * e1 * e1


def ekf_update_one(y, P_y, innovation, C_x, C_y, P_x, R_img) -> tuple[np.ndarray, np.ndarray, bool]:
    """Eqs. 7-9 for one feature (Joseph form); the prior comes back with ``False`` when ``S`` is not
    positive definite or the result is not finite."""
    R_eff = C_x @ P_x @ C_x.T + R_img
    S = C_y @ P_y @ C_y.T + R_eff
    S_inv, ok = _inverse_2x2(0.5 * (S + S.T))
    if not ok:
        return y.copy(), P_y.copy(), False
    K = P_y @ C_y.T @ S_inv
    y_new = y + K @ innovation
    I_KC = np.eye(len(y)) - K @ C_y
    P_new = I_KC @ P_y @ I_KC.T + K @ R_eff @ K.T
    P_new = 0.5 * (P_new + P_new.T)
    if not (np.isfinite(y_new).all() and np.isfinite(P_new).all() and (np.diag(P_new) >= 0).all()):
        return y.copy(), P_y.copy(), False
    return y_new, P_new, True


# ------------------------------------------------------------------------------------------------
# Loops over features with the batched code's signatures
# ------------------------------------------------------------------------------------------------


def measurement_model(y, R_ref, pose, camera, directions=None):
    """Loop of :func:`measurement_model_one`: (N, 6), (N, 3, 3) -> pixels (N, 2), ``h^c`` (N, 3).
    ``directions`` (the batched step's shared terms) is ignored: each feature computes its own."""
    n = len(y)
    uv, h = np.empty((n, 2)), np.empty((n, 3))
    for j in range(n):
        uv[j], h[j] = measurement_model_one(y[j], R_ref[j], pose, camera)
    return uv, h


def measurement_jacobian(y, R_ref, pose, camera, h_c=None, directions=None):
    """Loop of :func:`measurement_jacobian_one` -> ``C_x`` (N, 2, 6), ``C_y`` (N, 2, 6)."""
    n = len(y)
    C_x, C_y = np.empty((n, 2, 6)), np.empty((n, 2, 6))
    for j in range(n):
        C_x[j], C_y[j] = measurement_jacobian_one(y[j], R_ref[j], pose, camera)
    return C_x, C_y


def innovation_covariance(C_x, C_y, P_x, P_y, R_img):
    n = len(C_x)
    S = np.empty((n, 2, 2))
    for j in range(n):
        S[j] = innovation_covariance_one(C_x[j], C_y[j], P_x, P_y[j], R_img)
    return S


def mahalanobis_distances(z, g, S):
    """Loop over points of :func:`mahalanobis_row_one` -> Z (N points, M measurements)."""
    Z = np.empty((len(g), len(z)))
    for j in range(len(g)):
        Z[j] = mahalanobis_row_one(z, g[j], S[j])
    return Z


def gate_and_match(Z, gate):
    """Gate ``Z < gate`` and mutual nearest neighbours, written as loops (ties to the lower index).

    Returns ``point_idx`` (K,), ``meas_idx`` (K,) and ``ambiguous`` (M,) like the batched code."""
    n, m = Z.shape
    if n == 0 or m == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(m, dtype=bool)
    best_point = [0] * m  # nearest point of each measurement
    for i in range(m):
        col = Z[:, i]
        best = 0
        for j in range(1, n):
            if col[j] < col[best]:
                best = j
        best_point[i] = best
    points, meas = [], []
    matched = np.zeros(m, dtype=bool)
    inside_any = np.zeros(m, dtype=bool)
    for j in range(n):
        row = Z[j]
        best = 0
        for i in range(m):
            if row[i] < gate:
                inside_any[i] = True
            if row[i] < row[best]:
                best = i
        if best_point[best] == j and row[best] < gate:
            points.append(j)
            meas.append(best)
            matched[best] = True
    return np.array(points, dtype=np.intp), np.array(meas, dtype=np.intp), inside_any & ~matched


def near_stored_features(Z, z, g, exclusion_chi2, exclusion_px):
    """Measurements within ``exclusion_chi2`` (Mahalanobis) or ``exclusion_px`` of some prediction (M,)."""
    near = np.zeros(len(z), dtype=bool)
    for j in range(len(g)):
        d2 = (z[:, 0] - g[j, 0]) ** 2 + (z[:, 1] - g[j, 1]) ** 2
        near |= (Z[j] < exclusion_chi2) | (d2 < exclusion_px**2)
    return near


def candidate_pairs(z, g, S, chi2, px, S_inverse=None):
    """Pairs (point j, measurement i) with ``Z_ij < chi2`` or ``|z_i - g_j| < px``: each feature's
    whole row of distances (:func:`mahalanobis_row_one`), then the pairs that pass. Returns an object
    with ``point``, ``meas``, ``Z``, ``d2`` (P,), the fields of the batched ``CandidatePairs``."""
    point, meas, Zs, d2s = [], [], [], []
    for j in range(len(g)):
        Z = mahalanobis_row_one(z, g[j], S[j])
        d2 = (z[:, 0] - g[j, 0]) ** 2 + (z[:, 1] - g[j, 1]) ** 2
        for i in np.flatnonzero((Z < chi2) | (d2 < px**2)):
            point.append(j)
            meas.append(i)
            Zs.append(Z[i])
            d2s.append(d2[i])
    return SimpleNamespace(point=np.array(point, dtype=np.intp), meas=np.array(meas, dtype=np.intp),
                           Z=np.array(Zs, dtype=float), d2=np.array(d2s, dtype=float))


def gate_and_match_pairs(point, meas, Z, gate, n_meas):
    """Gate and mutual nearest neighbours over pairs, as loops: each point's nearest measurement and
    each measurement's nearest point among the pairs inside the gate (ties to the lower index)."""
    nearest_meas: dict = {}  # point -> (Z, measurement)
    nearest_point: dict = {}  # measurement -> (Z, point)
    inside_any = np.zeros(n_meas, dtype=bool)
    for j, i, d in zip(point.tolist(), meas.tolist(), Z.tolist()):
        if not d < gate:
            continue
        inside_any[i] = True
        if j not in nearest_meas or (d, i) < nearest_meas[j]:
            nearest_meas[j] = (d, i)
        if i not in nearest_point or (d, j) < nearest_point[i]:
            nearest_point[i] = (d, j)
    points, measurements = [], []
    for j in sorted(nearest_meas):
        i = nearest_meas[j][1]
        if nearest_point[i][1] == j:
            points.append(j)
            measurements.append(i)
            inside_any[i] = False  # matched, not ambiguous
    return np.array(points, dtype=np.intp), np.array(measurements, dtype=np.intp), inside_any


def near_stored_pairs(pairs, n_meas, exclusion_chi2, exclusion_px):
    """Measurements with a pair within ``exclusion_chi2`` (Mahalanobis) or ``exclusion_px`` (M,)."""
    near = np.zeros(n_meas, dtype=bool)
    for i, d, d2 in zip(pairs.meas.tolist(), pairs.Z.tolist(), pairs.d2.tolist()):
        if d < exclusion_chi2 or d2 < exclusion_px**2:
            near[i] = True
    return near


def ekf_update(y, P_y, innovation, C_x, C_y, P_x, R_img, S_inverse=None):
    """Loop of :func:`ekf_update_one` -> y (N, D), P (N, D, D), ok (N,). ``S_inverse`` (the batched
    code's shared inverses) is ignored: each feature computes its own."""
    y = np.asarray(y, dtype=float)
    P_y = np.asarray(P_y, dtype=float)
    n = len(y)
    y_new, P_new, ok = np.empty_like(y), np.empty_like(P_y), np.zeros(n, dtype=bool)
    for j in range(n):
        y_new[j], P_new[j], ok[j] = ekf_update_one(y[j], P_y[j], innovation[j], C_x[j], C_y[j], P_x, R_img)
    return y_new, P_new, ok


def loop_model() -> SimpleNamespace:
    """The inverse-depth model with the loop measurement model and Jacobian; everything else
    (initialisation, convergence test, state normalisation) is the mapper's own."""
    names = {k: getattr(inverse_depth, k) for k in dir(inverse_depth) if not k.startswith("__")}
    names.update(measurement_model=measurement_model, measurement_jacobian=measurement_jacobian)
    return SimpleNamespace(**names)


# Names the mapper module imports from companion.method.mapper.matching / update, replaced for the loop run.
MAPPER_FUNCTIONS = {
    "innovation_covariance": innovation_covariance,
    "candidate_pairs": candidate_pairs,
    "gate_and_match_pairs": gate_and_match_pairs,
    "near_stored_pairs": near_stored_pairs,
    "ekf_update": ekf_update,
}


class loop_reference:
    """Context manager: run the mapper on the loop equations. The matching and update functions the
    mapper module calls are swapped for the loops above; ``mapper`` (a
    :class:`companion.method.mapper.Mapper` with the inverse-depth parameterisation), if given, also gets
    :func:`loop_model` (loop measurement model and Jacobian). Everything is restored on exit.
    Detection, initialisation and bookkeeping stay the mapper's own. Mappers built inside the block
    need ``mapper.model = loop_model()`` (or pass them here).

    Raises RuntimeError if the mapper module no longer calls one of those functions by name (the
    comparison would silently be batched against batched)."""

    def __init__(self, mapper=None):
        import companion.method.mapper.mapper as mapper_module

        if mapper is not None and mapper.cfg.parameterisation != "inverse_depth":
            raise ValueError("the loop reference implements the inverse-depth parameterisation only")
        missing = [name for name in MAPPER_FUNCTIONS if not hasattr(mapper_module, name)]
        if missing:
            raise RuntimeError(f"companion.method.mapper.mapper no longer uses {', '.join(missing)}: "
                               "update benchmarks/reference_loop.py")
        self._module = mapper_module
        self._mapper = mapper
        self._saved: dict = {}
        self._saved_model = None

    def __enter__(self):
        self._saved = {name: getattr(self._module, name) for name in MAPPER_FUNCTIONS}
        for name, fn in MAPPER_FUNCTIONS.items():
            setattr(self._module, name, fn)
        if self._mapper is not None:
            self._saved_model = self._mapper.model
            self._mapper.model = loop_model()
        return self._mapper

    def __exit__(self, *exc):
        for name, fn in self._saved.items():
            setattr(self._module, name, fn)
        if self._mapper is not None:
            self._mapper.model = self._saved_model
        return False
