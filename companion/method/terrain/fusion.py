"""Evidence-grid fusion of converged points (seed 000, section II.E; docs/terrain.md, "Fusion").

The seed only says that a converged point raises or lowers the height of its grid location.
Here each cell holds a Gaussian estimate of the height of its TOP surface (value, variance) and an
evidence count. For obstacle avoidance the top is what matters, and a 1 m cell that holds a wall
receives points from the whole wall (0..9 m on the default building): averaging them maps the
building at its middle. So, as in ETH's elevation_mapping (a measurement outside the Mahalanobis
gate: a higher one replaces the cell, a lower one is ignored), a cell fuses only the
measurements that agree with it, and treats the others by side:

* agreeing (within the gate): a one-dimensional Kalman update, up or down;
* far above: a higher surface. It replaces the cell once a second measurement confirms it (one
  wild point never builds an obstacle);
* far below: a lower surface of the same cell (the face of a wall), ignored for the height; but
  counted, and ``reset_evidence`` of them with nothing agreeing in between bring the cell down to
  them (a wrong high value, or terrain that changed, is corrected).

The steps, in the order the grid applies them to a batch of N points:

1. :func:`valid_points` rejects non-finite or non-PSD input (counted, never fused);
   :func:`precise_points` rejects points too imprecise horizontally to belong to any cell.
2. :func:`horizontal_spread` turns each point into (point, cell, weight) pairs: the point's
   horizontal covariance says which cells it may fall in; weight = its share of the point.
3. :func:`measurement_variance`: a pair is a measurement of the cell's height with variance
   ``sigma_z^2 / w`` (a point that is only partly in a cell says less about it).
4. :func:`gate_side`: against cells that already hold evidence, a pair further than ``g``
   innovation sigmas is above (+1) or below (-1) the cell; within, it agrees (0).
5. :func:`disagreement_update`: evidence from below accumulates per cell while nothing agrees;
   past ``reset_evidence`` the cell takes the lower heights.
6. :func:`confirm_raise`: the pairs above a cell, and the pending higher height the cell keeps
   from earlier batches, decide whether the cell is raised and to what.
7. :func:`fuse_information`: prior (plus process noise) and the agreeing pairs combine in
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
        ok = _row_max(np.abs(positions)) <= max_abs_m
        f = covariances.reshape(n, 9)
        scale = _row_max(np.abs(f))
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


def _row_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=1)`` of a (N, K) array with few columns, NaN propagating alike: K - 1
    element-wise maxima of whole columns, ~7 times faster than the reduction along short rows."""
    out = a[:, 0].copy()
    for j in range(1, a.shape[1]):
        np.maximum(out, a[:, j], out=out)
    return out


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
        # q = (A + B) + C, A = qa dn^2, B = qb dn de, C = qc de^2, in two buffers fewer (the same bits)
        q = (pick(qb)[:, None] * dn)[:, :, None] * de[:, None, :]
        q += (pick(qa)[:, None] * dn * dn)[:, :, None]
        q += (pick(qc)[:, None] * de * de)[:, None, :]
        width = 2 * r + 1
        # Cells within n_sigma; a point reaching none of them goes to its nearest centre(s): the
        # limit is max(min q (1 + 1e-9), g2), which is g2 wherever the own cell is within it.
        q2 = q.reshape(len(q), -1)
        limit = np.full(len(q), g2)
        far = np.flatnonzero(q[:, r, r] * (1.0 + 1e-9) > g2)
        if len(far):
            limit[far] = np.maximum(q2[far].min(axis=1) * (1.0 + 1e-9), g2)
        flat = np.flatnonzero((q2 <= limit[:, None]).reshape(-1))
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


def gate_side(
    h: np.ndarray, r: np.ndarray, h_cell: np.ndarray, v_cell: np.ndarray, n_cell: np.ndarray, n_sigma: float, min_count: int,
    below_sigma: float | None = None,
) -> np.ndarray:
    """(M,) int8: +1 the pair is above its cell, -1 below, 0 it agrees.

    Above means ``h - h_cell > g sqrt(v_cell + r)``, below ``h_cell - h > g_b sqrt(v_cell + r)``
    (``g_b`` = ``below_sigma``, default ``g``), where the cell holds at least ``min_count`` points;
    a cell with less evidence agrees with everything (nothing to gate against).
    h, r: (M,) pair heights and variances; h_cell, v_cell, n_cell: (M,) the cell of each pair."""
    g_b = n_sigma if below_sigma is None else below_sigma
    with np.errstate(invalid="ignore"):
        nu = h - h_cell
        s2 = v_cell + r
        outside = (n_cell >= min_count) & (nu * nu > min(n_sigma, g_b) ** 2 * s2)
        if not outside.any():
            return np.zeros(len(h), dtype=np.int8)
        up = outside & (nu > 0) & (nu * nu > n_sigma * n_sigma * s2)
        down = outside & (nu < 0) & (nu * nu > g_b * g_b * s2)
    return up.astype(np.int8) - down.astype(np.int8)


def disagreement_update(d: np.ndarray, agree_w: np.ndarray, below_w: np.ndarray) -> np.ndarray:
    """Per touched cell (K,): evidence from below still uncontradicted after this batch.

    d: the cell's disagreement before (points); agree_w, below_w: this batch's weight agreeing
    with the cell and far below it. Any agreement clears it; otherwise the evidence below adds up.
    A wall's cell receives many points from the wall's face below its top (more than from the top,
    in the same batches too), and from time to time one from the top, which clears it; a cell that
    is wrongly high receives only points below."""
    return np.where(agree_w > 0, 0.0, d + below_w)


def highest_two(cell: np.ndarray, h: np.ndarray, r: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    """Per cell (K,): the highest and second highest of the pairs given (cell index, height and
    variance, each (M,)): (h1, r1, h2, r2), NaN / inf where a cell has fewer."""
    h1, h2 = np.full(k, np.nan), np.full(k, np.nan)
    r1, r2 = np.full(k, np.inf), np.full(k, np.inf)
    if len(cell):
        order = np.lexsort((-h, cell))  # by cell, then highest first
        c, hs, rs = cell[order], h[order], r[order]
        first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        h1[c[first]], r1[c[first]] = hs[first], rs[first]
        second = first[(first + 1 < len(c)) & (np.r_[c, -1][first + 1] == c[first])] + 1
        h2[c[second]], r2[c[second]] = hs[second], rs[second]
    return h1, r1, h2, r2


def confirm_raise(
    h1: np.ndarray, r1: np.ndarray, h2: np.ndarray, r2: np.ndarray, pending: np.ndarray, n_sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whether each cell is raised by the evidence above it, to what, and what stays pending.

    Per touched cell (K,): ``h1, r1`` and ``h2, r2`` = the highest and second highest of this
    batch's pairs above the cell (NaN / inf: none); ``pending`` = the highest height earlier batches
    saw above the cell, unconfirmed (NaN: none). Two observations above a cell show that its top is
    at least as high as the LOWER of them, so when there are two or more the cell rises to the
    second highest (to their mean, with half the variance, if the highest agrees with it:
    ``(hi - second)^2 <= g^2 2 r``), and the highest, if apart, stays pending. One wild point far
    above never raises a cell, and with a second observation it raises it only to that
    observation; over a wall's points the cell climbs to the second highest, i.e. to the wall's top.
    With a single observation it becomes the pending height (the higher of it and the old one).

    A pending height keeps no variance: where it is the second highest, the variance of this
    batch's highest stands in for it. Returns (raised (K,) bool, height, variance, pending after);
    height and variance are meaningful where raised (a raised cell counts two points).
    """
    has_p = np.isfinite(pending)
    hi = np.fmax(pending, h1)
    # Second highest of {pending, h1, h2}, and the variance that goes with it.
    p_second = has_p & (pending < h1) & ~(pending < h2)
    second = np.where(has_p & (pending >= h1), h1, np.where(p_second, pending, h2))
    v_second = np.where(has_p & (pending >= h1), r1, np.where(p_second, r1, r2))
    raised = np.isfinite(second)
    d = hi - second
    with np.errstate(invalid="ignore"):
        agree = raised & (d * d <= n_sigma * n_sigma * 2.0 * v_second)
    height = np.where(agree, 0.5 * (hi + second), second)
    variance = np.where(agree, 0.5 * v_second, v_second)
    pending_after = np.where(agree, np.nan, hi)
    return raised, height, variance, pending_after


def highest_two_per_cell(cell: np.ndarray, height: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The highest and second highest of ``height`` (N,) per cell of ``cell`` (N,) in 0..k-1, each
    (k,), -inf where a cell has fewer rows (:func:`highest_two` without variances)."""
    h1, _, h2, _ = highest_two(cell, height, np.zeros(len(height)), k)
    return np.where(np.isnan(h1), -np.inf, h1), np.where(np.isnan(h2), -np.inf, h2)


def confirm_floor(h1: np.ndarray, h2: np.ndarray, pending: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The floor each cell may take, and the bound that stays pending (docs/terrain.md, "Floors").

    Per cell (K,): ``h1``, ``h2`` the highest and second highest bounds of this batch (-inf none),
    ``pending`` the highest earlier bound not yet confirmed (-inf none). As for the points above a
    cell (:func:`confirm_raise`), one bound alone lifts nothing: two bounds, of one frame or of two,
    show that the terrain reaches at least the LOWER of them, so the floor is the second highest of
    the three, and the highest stays pending. A feature whose bound holds over two frames confirms
    itself; a wild one (a mismatched track a frame old, 5 m above flat ground) does not. (The grid
    also takes a neighbouring cell's bound as the second: :meth:`TerrainGrid.raise_floors`.)
    Returns (floor, pending), each (K,)."""
    hi = np.fmax(pending, h1)
    second = np.where(pending >= h1, h1, np.fmax(pending, h2))
    return second, hi


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
