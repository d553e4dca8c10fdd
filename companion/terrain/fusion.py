"""Evidence-grid fusion of converged points (seed 000, section II.E; docs/terrain.md, "Fusion").

The seed only says that a converged point raises or lowers the height of its grid location.
Here each cell holds a Gaussian estimate of its height (value, variance) and an evidence count,
and a point updates it with a one-dimensional Kalman update, so the cell moves both up and down.
The steps, in the order the grid applies them to a batch of N points:

1. :func:`valid_points` rejects non-finite or non-PSD input (counted, never fused);
   :func:`precise_points` rejects points too imprecise horizontally to belong to any cell.
2. :func:`horizontal_spread` turns each point into (point, cell, weight) pairs: the point's
   horizontal covariance says which cells it may fall in; weight = its share of the point.
3. :func:`measurement_variance`: a pair is a measurement of the cell's height with variance
   ``sigma_z^2 / w`` (a point that is only partly in a cell says less about it).
4. :func:`gate`: against cells that already hold evidence, a pair further than ``g`` innovation
   sigmas is rejected (a single wild point cannot build a spike in a mapped cell).
5. :func:`disagreement_update`: rejected evidence accumulates per cell while nothing agrees with
   the cell; past ``reset_evidence`` the cell forgets its estimate and takes the new heights
   (the terrain changed, or the first estimate was wrong).
6. :func:`fuse_information`: prior (plus process noise) and the accepted pairs combine in
   information form, which is the sequential Kalman update done all at once.
"""

from __future__ import annotations

import numpy as np


def valid_points(positions: np.ndarray, covariances: np.ndarray, max_abs_m: float) -> np.ndarray:
    """(N,) bool: finite position within ``max_abs_m`` of the origin, finite symmetric PSD covariance.

    positions: (N, 3) NED (m); covariances: (N, 3, 3) (m^2). PSD is tested with every principal
    minor (three diagonals, three 2x2, the determinant) at a relative tolerance, which is exact for
    3x3 symmetric matrices and much cheaper than an eigen-decomposition. NaN fails every
    comparison, so it needs no separate test.
    """
    n = len(positions)
    with np.errstate(invalid="ignore", over="ignore"):
        ok = np.abs(positions).max(axis=1) <= max_abs_m
        f = covariances.reshape(n, 9)
        scale = np.abs(f).max(axis=1)
        ok &= scale < np.inf
        tol = 1e-9 * np.maximum(scale, 1e-300)
        a, b, c, d, e, g = f[:, 0], f[:, 1], f[:, 2], f[:, 4], f[:, 5], f[:, 8]
        ok &= (np.abs(b - f[:, 3]) <= tol) & (np.abs(c - f[:, 6]) <= tol) & (np.abs(e - f[:, 7]) <= tol)
        ok &= (a >= -tol) & (d >= -tol) & (g >= -tol)
        tol2 = tol * scale
        m_de = d * g - e * e
        ok &= (a * d - b * b >= -tol2) & (a * g - c * c >= -tol2) & (m_de >= -tol2)
        ok &= a * m_de - b * (b * g - e * c) + c * (b * e - d * c) >= -tol2 * scale
    return ok


def precise_points(covariances: np.ndarray, max_sigma_m: float) -> np.ndarray:
    """(N,) bool: the largest horizontal standard deviation (major axis of the 2x2 north-east block of
    ``covariances`` (N, 3, 3)) is at most ``max_sigma_m``. A point less precise than that says
    little about any one cell, and the spread (limited to ``max_spread_cells``) would put all of its
    weight into the few cells it reaches: a far feature with a 16 m sigma becomes a full point in
    cells it is probably not in. Closed-form eigenvalue of a symmetric 2x2."""
    a, b, d = covariances[:, 0, 0], covariances[:, 0, 1], covariances[:, 1, 1]
    major = 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)
    return major <= max_sigma_m * max_sigma_m


def horizontal_spread(
    north: np.ndarray, east: np.ndarray, cov_ne: np.ndarray, cell_m: float, n_sigma: float, max_radius: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Spread each point over the cells its horizontal uncertainty covers.

    north, east: (N,) point positions (m); cov_ne: (N, 2, 2) horizontal covariance (m^2).
    The effective covariance is ``S = cov_ne + c^2/12 I`` (the point's uncertainty convolved with
    the cell's own extent, moment-matched), so a point much smaller than a cell lands in its cell
    and one on a border is shared. Cells whose centre lies within ``n_sigma`` of the point under
    ``S`` (Mahalanobis) get weight proportional to the Gaussian density there (a sharp point near a
    corner reaches no centre within ``n_sigma``: it goes to the nearest centre(s), shared equally);
    weights are normalised per point to sum to 1 (one point = one unit of evidence). The search is limited to ``max_radius`` cells around the point's cell.

    Returns (point_index (M,), cell_ix (M,), cell_iy (M,), weight (M,)); cell index = floor(x/c).
    """
    n = len(north)
    if n == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e, e, np.zeros(0)
    ix0 = np.floor(north / cell_m).astype(np.int64)
    iy0 = np.floor(east / cell_m).astype(np.int64)
    own = cell_m * cell_m / 12.0
    s00, s11, s01 = cov_ne[:, 0, 0] + own, cov_ne[:, 1, 1] + own, cov_ne[:, 0, 1]
    det = s00 * s11 - s01 * s01
    # Mahalanobis^2 of an offset (dn, de): A dn^2 + B dn de + C de^2 with S^-1 = [[A, B/2], [B/2, C]].
    qa, qb, qc = s11 / det, -2.0 * s01 / det, s00 / det
    # Offset of the point's own cell centre from the point.
    fn = (ix0 + 0.5) * cell_m - north
    fe = (iy0 + 0.5) * cell_m - east
    radius = np.minimum(np.ceil(n_sigma * np.sqrt(np.maximum(s00, s11)) / cell_m), max_radius).astype(np.int64)
    g2 = n_sigma * n_sigma
    parts = []
    # One stencil per distinct radius (usually one or two): no per-point Python loop.
    for r in np.flatnonzero(np.bincount(radius)):
        sel = np.flatnonzero(radius == r)
        whole = len(sel) == n
        pick = (lambda x: x) if whole else (lambda x: x[sel])
        k = np.arange(-r, r + 1)
        # The stencil is separable: north offsets (n, 2r+1) x east offsets (n, 2r+1).
        dn = pick(fn)[:, None] + cell_m * k
        de = pick(fe)[:, None] + cell_m * k
        q = ((pick(qa)[:, None] * dn * dn)[:, :, None] + (pick(qb)[:, None] * dn)[:, :, None] * de[:, None, :]
             + (pick(qc)[:, None] * de * de)[:, None, :])
        width = 2 * r + 1
        # Cells within n_sigma; a point reaching none of them goes to its nearest centre(s).
        limit = np.maximum(q.reshape(len(q), -1).min(axis=1) * (1.0 + 1e-9), g2)
        flat = np.flatnonzero((q.reshape(len(q), -1) <= limit[:, None]).reshape(-1))
        rows, cell = np.divmod(flat, width * width)
        oi, oj = np.divmod(cell, width)
        pts = rows if whole else sel[rows]
        parts.append((pts, ix0[pts] + (oi - r), iy0[pts] + (oj - r), np.exp(-0.5 * q.reshape(-1)[flat])))
    p, ci, cj, w = (np.concatenate(x) for x in zip(*parts)) if len(parts) > 1 else parts[0]
    total = np.bincount(p, weights=w, minlength=n)
    return p, ci, cj, w / total[p]


def measurement_variance(var_z: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Variance of a pair as a measurement of its cell's height: ``sigma_z^2 / w`` (m^2)."""
    return var_z / weight


def gate(
    h: np.ndarray, r: np.ndarray, h_cell: np.ndarray, v_cell: np.ndarray, n_cell: np.ndarray, n_sigma: float, min_count: int
) -> np.ndarray:
    """(M,) bool, True = reject: ``(h - h_cell)^2 > g^2 (v_cell + r)`` where the cell holds at least
    ``min_count`` points; a cell with less evidence accepts everything (nothing to gate against)."""
    with np.errstate(invalid="ignore"):
        nu2 = (h - h_cell) ** 2
        return (n_cell >= min_count) & (nu2 > n_sigma * n_sigma * (v_cell + r))


def disagreement_update(d: np.ndarray, accepted_w: np.ndarray, rejected_w: np.ndarray) -> np.ndarray:
    """Per touched cell: rejected evidence still uncontradicted after this batch.

    Agreement at least as strong as the disagreement clears it; otherwise the excess accumulates.
    """
    return np.where(accepted_w >= rejected_w, 0.0, d + rejected_w - accepted_w)


def fuse_information(
    h0: np.ndarray, v0: np.ndarray, info: np.ndarray, info_h: np.ndarray, process_noise: float
) -> tuple[np.ndarray, np.ndarray]:
    """1D Kalman update of cells in information form.

    h0, v0: (K,) prior height and variance (v0 = inf: no prior); info = sum(1/r_k),
    info_h = sum(h_k/r_k) over the cell's accepted measurements. The prior variance first grows by
    ``process_noise``. Returns the posterior (height, variance), each (K,).
    """
    prior = np.isfinite(v0)
    vp = np.where(prior, v0 + process_noise, 1.0)
    info0 = np.where(prior, 1.0 / np.maximum(vp, 1e-30), 0.0)
    total = info0 + info
    h = (np.where(prior, h0, 0.0) * info0 + info_h) / total
    return h, 1.0 / total
