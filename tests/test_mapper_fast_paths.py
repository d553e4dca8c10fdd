"""The mapper's fast paths compute exactly what the straightforward formulas compute.

Each fast path is checked against the plain version on random inputs: candidate pairs against the
dense N x M distance matrix (same pairs, bit-identical distances, same gating, matching and
exclusion decisions, ties included), the grid search for close points against all K^2 pairs, the
threshold-first local maxima against OpenCV's dilation, the adaptive first batch of the detector
against any other batch size, the one-gather patches against the clipped gather, the scalar
quaternion rotation against geometry.quat_to_matrix, the navigation check's diagonal shortcut
against the eigenvalues; and the daemon's windowed status figures. Nothing here is timed.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import MapperConfig
from companion.method.geometry import quat_to_matrix
from companion.method.mapper import appearance, matching
from companion.method.mapper.features import HarrisDetector, _close_pairs, suppress_within
from companion.method.mapper.mapper import _checked_pose_covariance, check_nav
from companion.method.mapper.projection import rotation_from_quaternion
from companion.method.messages import NavState
from companion.service.daemon import Percentiles

SEEDS = st.integers(0, 2**32 - 1)


def random_spd(rng, n, scale):
    A = rng.normal(0.0, scale, (n, 2, 2))
    return A @ np.swapaxes(A, 1, 2) + np.eye(2) * 0.05 * scale**2


def matching_case(rng, n, m):
    """Predictions, measurements (some near predictions, some duplicated: ties), S with a few
    indefinite, NaN and elongated (epipolar strip) rows."""
    g = rng.uniform(0, 300, (n, 2))
    near = min(n, m // 2)
    z = np.vstack([g[:near] + rng.normal(0.0, 3.0, (near, 2)), rng.uniform(0, 300, (m - near, 2))])
    if m >= 3:
        z[rng.integers(1, m)] = z[0]  # two identical measurements: ties between measurements
    S = random_spd(rng, n, rng.uniform(0.5, 6.0))
    if n >= 4:
        S[1] = [[1.0, 2.0], [2.0, 1.0]]  # indefinite: no distance
        S[2, 0, 0] = np.nan
        S[3] = [[400.0, 0.0], [0.0, 1.0]]  # a long strip along u
    if n >= 6:
        g[5] = g[4]  # two identical predictions with the same S: ties between points
        S[5] = S[4]
    return z, g, S


def dense_einsum(z, g, S):
    """Eqs. 11-12 as first written: e^T S^-1 e by einsum over (N, M, 2)."""
    S_inv, ok = matching.inverse_2x2(S)
    e = z[None, :, :] - g[:, None, :]
    Z = np.einsum("nmi,nij,nmj->nm", e, S_inv, e)
    Z[~ok] = np.inf
    return Z


@settings(max_examples=60, deadline=None)
@given(SEEDS, st.integers(0, 25), st.integers(0, 40), st.sampled_from([9.21, 23.0]), st.sampled_from([0.0, 4.0, 10.0]))
def test_candidate_pairs_are_exactly_the_dense_pairs_with_the_same_distances(seed, n, m, chi2, px):
    rng = np.random.default_rng(seed)
    z, g, S = matching_case(rng, n, m)
    Z = matching.mahalanobis_distances(z, g, S)
    d2 = (z[None, :, 0] - g[:, 0, None]) ** 2 + (z[None, :, 1] - g[:, 1, None]) ** 2
    want = {(j, i) for j, i in zip(*np.nonzero((Z < chi2) | (d2 < px * px)))}
    pairs = matching.candidate_pairs(z, g, S, chi2, px)
    got = list(zip(pairs.point.tolist(), pairs.meas.tolist()))
    assert len(got) == len(set(got)) == len(pairs)  # no pair twice
    assert set(got) == want
    # bit-identical distances: the same arithmetic as the dense form
    np.testing.assert_array_equal(pairs.Z, Z[pairs.point, pairs.meas])
    np.testing.assert_array_equal(pairs.d2, d2[pairs.point, pairs.meas])


@settings(max_examples=40, deadline=None)
@given(SEEDS, st.integers(1, 25), st.integers(1, 40))
def test_distances_by_components_equal_the_einsum_formula(seed, n, m):
    rng = np.random.default_rng(seed)
    z, g, S = matching_case(rng, n, m)
    a, b = matching.mahalanobis_distances(z, g, S), dense_einsum(z, g, S)
    np.testing.assert_array_equal(np.isinf(a), np.isinf(b))
    fin = np.isfinite(b)
    np.testing.assert_allclose(a[fin], b[fin], rtol=1e-12, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(SEEDS, st.integers(0, 25), st.integers(0, 40), st.sampled_from([5.99, 9.21, 23.0]), st.floats(0.0, 0.5))
def test_gating_and_matching_on_pairs_decide_as_on_the_dense_matrix(seed, n, m, gate, unlike_fraction):
    """Also with pairs removed (the appearance check): equal to the dense matrix with inf there."""
    rng = np.random.default_rng(seed)
    z, g, S = matching_case(rng, n, m)
    pairs = matching.candidate_pairs(z, g, S, max(gate, 23.0), 10.0)
    like = rng.uniform(size=len(pairs)) >= unlike_fraction
    Z_dense = matching.mahalanobis_distances(z, g, S)
    Z_dense[pairs.point[~like], pairs.meas[~like]] = np.inf
    p_d, i_d, a_d = matching.gate_and_match(Z_dense, gate)
    p_s, i_s, a_s = matching.gate_and_match_pairs(pairs.point[like], pairs.meas[like], pairs.Z[like], gate, len(z))
    np.testing.assert_array_equal(p_s, p_d)
    np.testing.assert_array_equal(i_s, i_d)
    np.testing.assert_array_equal(a_s, a_d)
    assert p_s.dtype == np.intp and i_s.dtype == np.intp and a_s.shape == (len(z),)
    near_d = matching.near_stored_features(matching.mahalanobis_distances(z, g, S), z, g, 23.0, 10.0)
    np.testing.assert_array_equal(matching.near_stored_pairs(pairs, len(z), 23.0, 10.0), near_d)


def test_pair_matching_breaks_ties_towards_the_lower_index():
    g = np.array([[100.0, 100.0], [100.0, 100.0], [200.0, 200.0]])  # points 0 and 1 identical
    z = np.array([[101.0, 100.0], [101.0, 100.0], [300.0, 300.0]])  # measurements 0 and 1 identical
    S = np.broadcast_to(np.eye(2) * 4.0, (3, 2, 2)).copy()
    pairs = matching.candidate_pairs(z, g, S, 23.0, 10.0)
    point_idx, meas_idx, ambiguous = matching.gate_and_match_pairs(pairs.point, pairs.meas, pairs.Z, 9.21, 3)
    assert point_idx.tolist() == [0] and meas_idx.tolist() == [0]
    assert ambiguous.tolist() == [False, True, False]


def test_pair_correlation_is_the_diagonal_of_the_correlation_matrix():
    rng = np.random.default_rng(1)
    T = rng.normal(size=(7, 81)).astype(np.float32)
    D = rng.normal(size=(7, 81)).astype(np.float32)
    np.testing.assert_allclose(appearance.pair_correlation(T, D), np.diag(appearance.correlation(T, D)), rtol=1e-5,
                               atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(SEEDS)
def test_inverse_2x2_is_the_inverse_or_flagged(seed):
    rng = np.random.default_rng(seed)
    S = random_spd(rng, 20, rng.uniform(0.1, 10.0))
    S[3] = [[1.0, 3.0], [3.0, 1.0]]
    S[4] = [[np.inf, 0.0], [0.0, 1.0]]
    S[5] = [[1.0, np.nan], [np.nan, 1.0]]
    S[6] = 0.0
    S_inv, ok = matching.inverse_2x2(S)
    assert ok.tolist() == [True] * 3 + [False] * 4 + [True] * 13
    np.testing.assert_allclose(S_inv[ok], np.linalg.inv(S[ok]), rtol=1e-9)
    assert (S_inv[~ok] == 0.0).all()


# ------------------------------------------------------------------------------------------------
# Detector
# ------------------------------------------------------------------------------------------------


def brute_close_pairs(xy, d):
    diff = xy[:, None, :] - xy[None, :, :]
    close = diff[..., 0] ** 2 + diff[..., 1] ** 2 < d * d
    return {(i, j) for i, j in zip(*np.nonzero(np.triu(close, 1)))}


@settings(max_examples=60, deadline=None)
@given(SEEDS, st.integers(0, 300), st.sampled_from([0.5, 3.0, 10.0, 40.0]), st.sampled_from(["uniform", "clusters", "wide"]))
def test_close_pairs_by_grid_are_all_pairs_closer_than_d(seed, k, d, layout):
    rng = np.random.default_rng(seed)
    if layout == "uniform":
        xy = rng.uniform(0, 640, (k, 2))
    elif layout == "clusters":
        centres = rng.uniform(0, 640, (max(1, k // 10), 2))
        xy = centres[rng.integers(0, len(centres), k)] + rng.normal(0.0, d, (k, 2))
    else:  # far more cells than points: the cell size grows, the pairs stay exact
        xy = rng.uniform(-1e7, 1e7, (k, 2))
        xy[: k // 2] = rng.uniform(0, 50, (k // 2, 2))
    if k:
        xy[rng.integers(0, k)] = xy[0]  # a duplicate
    src, dst = _close_pairs(xy, d) if k else (np.zeros(0, int), np.zeros(0, int))
    assert (src < dst).all()
    assert set(zip(src.tolist(), dst.tolist())) == brute_close_pairs(xy, d)


def test_close_pairs_ignore_points_without_a_position():
    xy = np.array([[0.0, 0.0], [np.nan, 1.0], [1.0, 0.0], [np.inf, 0.0], [0.5, 0.5]])
    src, dst = _close_pairs(xy, 2.0)
    assert set(zip(src.tolist(), dst.tolist())) == {(0, 2), (0, 4), (2, 4)}
    assert suppress_within(xy, 2.0).tolist() == [True, True, False, True, False]


def dilation_maxima(det: HarrisDetector, R: np.ndarray, valid) -> tuple[np.ndarray, np.ndarray]:
    """The local maxima as first written: R >= max(3x3 dilation, just above the threshold), in the
    valid region, outside the margin, raster order."""
    m, H, W = det.margin, det.height, det.width
    best = cv2.minMaxLoc(R[m : H - m, m : W - m])[1] if valid is None else cv2.minMaxLoc(R, valid)[1]
    threshold = max(det.cfg.harris_quality * best, det.cfg.harris_min_response)
    if not best > 0.0 or best < threshold:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    D = cv2.dilate(R, np.ones((3, 3), np.uint8))
    D = np.maximum(D, np.nextafter(np.float32(threshold), np.float32(np.inf)))
    cand = R >= D
    if valid is not None:
        cand &= valid != 0
    cand[:m], cand[H - m :], cand[:, :m], cand[:, W - m :] = False, False, False, False
    flat = np.flatnonzero(cand)
    return flat, R.reshape(-1)[flat]


def textured(rng, h, w, blocks):
    img = cv2.resize(rng.integers(0, 256, (h // blocks, w // blocks), dtype=np.uint8), (w, h),
                     interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(img, (0, 0), 0.8)


@settings(max_examples=25, deadline=None)
@given(SEEDS, st.sampled_from([4, 8, 16]), st.integers(0, 12), st.booleans(), st.booleans())
def test_threshold_first_local_maxima_equal_the_dilation(seed, blocks, border, with_mask, plateaus):
    rng = np.random.default_rng(seed)
    h, w = 96, 128
    img = textured(rng, h, w, blocks)
    if plateaus:  # equal neighbouring responses: both are maxima (>=), in both forms
        img = (img // 64 * 64).astype(np.uint8)
    mask = None
    if with_mask:
        mask = np.ones((h, w), np.uint8)
        mask[rng.integers(0, h) :, : rng.integers(0, w)] = 0
    det = HarrisDetector(MapperConfig(max_detections=40), w, h, border, mask)
    R = det.harris_response(img).copy()
    valid = det.valid_region(img)
    flat, score = det.candidate_maxima(R, valid)
    want_flat, want_score = dilation_maxima(det, R, valid)
    np.testing.assert_array_equal(flat, want_flat)
    np.testing.assert_array_equal(score, want_score)


def test_detector_output_does_not_depend_on_its_first_batch():
    """The adaptive first batch changes how many candidates are refined at first, never the result."""
    rng = np.random.default_rng(4)
    frames = [textured(rng, 240, 320, 4) for _ in range(6)]
    cfg = MapperConfig(max_detections=60, per_bin=3)
    adaptive = HarrisDetector(cfg, 320, 240, 8)
    for k, img in enumerate(frames):
        uv, score = adaptive(img)
        for first in (1, 64, 10**6):
            fixed = HarrisDetector(cfg, 320, 240, 8)
            fixed._first_batch = first
            uv_f, score_f = fixed(img)
            np.testing.assert_array_equal(uv_f, uv)
            np.testing.assert_array_equal(score_f, score)
        assert len(uv) == 60
    assert adaptive._first_batch < 10**6


def test_detector_output_does_not_depend_on_its_level():
    """Candidates are looked for first above a level the last frame set; whatever that level (none,
    one leaving too few candidates for the first batch, one leaving enough for the first batch but
    too few for the selection, so that the rest are taken mid-way), the result is the same."""
    rng = np.random.default_rng(5)
    frames = [textured(rng, 240, 320, 4) for _ in range(4)]
    cfg = MapperConfig(max_detections=60, per_bin=3)
    adaptive = HarrisDetector(cfg, 320, 240, 8)
    switched = 0
    for img in frames:
        uv, score = adaptive(img)
        full = HarrisDetector(cfg, 320, 240, 8)
        _, all_scores = full.candidate_maxima(full.harris_response(img).copy(), full.valid_region(img))
        ranked = np.sort(all_scores)[::-1]
        for level in (0.0, float(ranked[10]), float(ranked[100]), 1e30):
            for first in (8, 64, 10**6):
                d = HarrisDetector(cfg, 320, 240, 8)
                d._level, d._first_batch = level, first
                uv_l, score_l = d(img)
                np.testing.assert_array_equal(uv_l, uv)
                np.testing.assert_array_equal(score_l, score)
                if level == float(ranked[10]) and first == 8:  # 10 candidates above: the rest taken mid-way
                    assert d.n_candidates == len(all_scores)
                    switched += 1
        assert len(uv) == 60
    assert switched == len(frames)
    assert adaptive._level > 0.0


def test_frame_patches_are_the_rows_of_all_patches():
    """Patches cut on demand (a few rows at a time, or a subset of the measurements) equal the
    rows of the patches of every measurement, to the bit."""
    rng = np.random.default_rng(6)
    gray = textured(rng, 60, 80, 4)
    uv = np.column_stack([rng.uniform(-2, 81, 40), rng.uniform(-2, 61, 40)])
    every = appearance.patch_descriptors(gray, uv, 9)
    patches = appearance.FramePatches(gray, uv, 9)
    for index in (np.arange(40), np.array([3, 3, 17, 0]), np.zeros(0, np.intp), rng.permutation(40)[:7]):
        np.testing.assert_array_equal(patches.rows(index), every[index])
    part = np.array([1, 5, 9, 30])
    np.testing.assert_array_equal(patches.subset(part).rows(np.array([2, 0])), every[[9, 1]])
    given = appearance.GivenPatches(every)
    np.testing.assert_array_equal(given.subset(part).rows(np.array([3])), every[[30]])
    assert len(patches) == len(given) == 40


def random_features(rng, n):
    """Inverse-depth states (n, 6) and reference rotations (n, 3, 3) seen by a camera looking down."""
    from companion.method.geometry import so3_exp
    from companion.method.mapper import inverse_depth

    y = np.column_stack([rng.normal(0.0, 5.0, (n, 3)), rng.uniform(-3.2, 3.2, n), rng.uniform(-1.2, 1.2, n),
                         rng.uniform(0.01, 0.2, n)])
    R_nc = np.array([so3_exp(rng.normal(0.0, 0.3, 3)) for _ in range(n)]).reshape(n, 3, 3) @ np.array(
        [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    return y, inverse_depth.reference_rotation(R_nc)


@settings(max_examples=30, deadline=None)
@given(SEEDS, st.integers(0, 40))
def test_shared_ray_directions_equal_each_function_computing_its_own(seed, n):
    """The step computes eq. 3's direction terms once (inverse_depth.ray_directions); the drift
    Jacobian, the prediction and eq. 5 given them equal the same functions computing their own:
    to the bit on the same features; on a subset (the visible features) to the last bit or two,
    since the terms were computed over the whole batch, and NumPy's vectorised loops may round
    a batch of one differently from a longer one (4e-16 relative seen)."""
    from companion.method.geometry import camera_from_config
    from companion.config import CompanionConfig
    from companion.method.mapper import inverse_depth as idp
    from companion.method.mapper.projection import CameraPose

    rng = np.random.default_rng(seed)
    y, R_ref = random_features(rng, n)
    camera, mount = camera_from_config(CompanionConfig().camera)
    pose = CameraPose.from_body(rng.normal(0.0, 3.0, 3), quat_to_matrix(rng.normal(size=4) + [3, 0, 0, 0]), mount)
    d = idp.ray_directions(y, R_ref)
    np.testing.assert_array_equal(d.m_world, idp.world_direction(y, R_ref))
    dm_dpsi, dm_dtheta = idp.direction_derivatives(y[:, idp.PSI], y[:, idp.THETA])
    np.testing.assert_array_equal(d.dm_dpsi, dm_dpsi)
    np.testing.assert_array_equal(d.dm_dtheta, dm_dtheta)
    np.testing.assert_array_equal(idp.navigation_frame_jacobian(y, R_ref, pose.p, d),
                                  idp.navigation_frame_jacobian(y, R_ref, pose.p))
    uv, h_c = idp.measurement_model(y, R_ref, pose, camera, d)
    uv0, h_c0 = idp.measurement_model(y, R_ref, pose, camera)
    np.testing.assert_array_equal(uv, uv0)
    np.testing.assert_array_equal(h_c, h_c0)
    front = np.flatnonzero(h_c[:, 0] > 0)
    C_x, C_y = idp.measurement_jacobian(y[front], R_ref[front], pose, camera, h_c[front], d.take(front))
    C_x0, C_y0 = idp.measurement_jacobian(y[front], R_ref[front], pose, camera)
    for got, want in ((C_x, C_x0), (C_y, C_y0)):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * float(np.abs(want).max(initial=0.0)))


class LooksNonZero(np.ndarray):
    """An array that claims to have a non-zero entry: a zero P_x of this type takes the general
    path (the navigation terms computed and added) where a plain zero P_x skips them."""

    def any(self, *args, **kwargs):
        return True


def spd(rng, n, dim):
    A = rng.normal(size=(n, dim, dim))
    return A @ A.transpose(0, 2, 1) + 0.1 * np.eye(dim)


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # inf * 0 on the general path
@settings(max_examples=40, deadline=None)
@given(SEEDS, st.integers(0, 30), st.booleans())
def test_a_zero_navigation_covariance_is_skipped_exactly(seed, n, nonfinite):
    """With the correlated navigation model the measurement's P_x is zero; the innovation
    covariance, the EKF update and the initialisation then skip its terms. The results equal the
    general path's (the zero terms computed and added), also when C_x is not finite (inf * 0)."""
    from companion.config import CompanionConfig
    from companion.method.geometry import camera_from_config
    from companion.method.mapper import inverse_depth as idp, update
    from companion.method.mapper.projection import CameraPose

    rng = np.random.default_rng(seed)
    C_x, C_y = rng.normal(size=(n, 2, 6)) * 50, rng.normal(size=(n, 2, 6)) * 50
    if nonfinite and n:
        C_x[rng.integers(0, n), 1, 3] = np.inf
    P_y, R_img = spd(rng, n, 6), np.diag([0.7, 0.7])
    zero, general = np.zeros((6, 6)), np.zeros((6, 6)).view(LooksNonZero)
    assert not matching.navigation_term_vanishes(general, C_x)
    np.testing.assert_array_equal(matching.innovation_covariance(C_x, C_y, zero, P_y, R_img),
                                  np.asarray(matching.innovation_covariance(C_x, C_y, general, P_y, R_img)))
    y, innovation = rng.normal(size=(n, 6)), rng.normal(size=(n, 2))
    want = update.ekf_update(y, P_y, innovation, C_x, C_y, general, R_img)
    for got, w in zip(update.ekf_update(y, P_y, innovation, C_x, C_y, zero, R_img), want):
        np.testing.assert_array_equal(got, np.asarray(w))
    if matching.navigation_term_vanishes(zero, C_x):
        # the update's S is then the gate's: its inverse, taken from the gates' of all features
        # (a subset of them here, as the matched ones are), gives the same update
        S_inv, S_ok = matching.inverse_2x2(matching.innovation_covariance(C_x, C_y, zero, P_y, R_img))
        some = rng.permutation(n)[: n // 2]
        for got, w in zip(update.ekf_update(y[some], P_y[some], innovation[some], C_x[some], C_y[some], zero, R_img,
                                            (S_inv[some], S_ok[some])), want):
            np.testing.assert_array_equal(got, np.asarray(w)[some])
    camera, mount = camera_from_config(CompanionConfig().camera)
    pose = CameraPose.from_body(rng.normal(0.0, 3.0, 3), quat_to_matrix(rng.normal(size=4) + [3, 0, 0, 0]), mount)
    uv = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n)])
    ranges = rng.uniform(1.0, 100.0, n)
    for got, want in zip(idp.initialise_features(uv, ranges, pose, camera, R_img, 0.5, zero),
                         idp.initialise_features(uv, ranges, pose, camera, R_img, 0.5, general)):
        np.testing.assert_array_equal(got, np.asarray(want))


def clipped_patches(gray, uv, size):
    """patch_descriptors as first written: a clipped gather for every patch."""
    r = size // 2
    h, w = gray.shape
    cu = np.clip(np.rint(uv[:, 0]), 0, w - 1).astype(np.intp)
    cv = np.clip(np.rint(uv[:, 1]), 0, h - 1).astype(np.intp)
    off = np.arange(size) - r
    rows = np.clip(cv[:, None] + off[None, :], 0, h - 1)
    cols = np.clip(cu[:, None] + off[None, :], 0, w - 1)
    patch = gray[rows[:, :, None], cols[:, None, :]].reshape(len(uv), size * size).astype(np.float32)
    patch -= patch.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(patch, axis=1, keepdims=True)
    return np.where(norm > 1e-3, patch / np.maximum(norm, 1e-3), 0.0).astype(np.float32)


@settings(max_examples=30, deadline=None)
@given(SEEDS, st.sampled_from([3, 9, 11]), st.booleans())
def test_patches_by_one_gather_equal_the_clipped_gather(seed, size, near_edges):
    rng = np.random.default_rng(seed)
    gray = textured(rng, 60, 80, 4)
    gray[10:25, 30:50] = 77  # flat: zero descriptor
    lo = -3.0 if near_edges else size
    uv = np.column_stack([rng.uniform(lo, 79 - lo, 30), rng.uniform(lo, 59 - lo, 30)])
    uv[0] = [40.0, 17.0]
    got = appearance.patch_descriptors(gray, uv, size)
    np.testing.assert_array_equal(got, clipped_patches(gray, uv, size))
    assert got.dtype == np.float32 and not got[0].any()


# ------------------------------------------------------------------------------------------------
# Navigation state
# ------------------------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-10.0, 10.0), min_size=4, max_size=4))
def test_scalar_quaternion_rotation_is_bit_identical_to_quat_to_matrix(q):
    q = np.array(q)
    if np.linalg.norm(q) < 1e-3:
        q[0] = 1.0
    np.testing.assert_array_equal(rotation_from_quaternion(q), quat_to_matrix(q))


def nav_with(P_pose, q=(1.0, 0.0, 0.0, 0.0)):
    cov = np.eye(9) * 0.01
    idx = np.array([0, 1, 2, 6, 7, 8])
    cov[np.ix_(idx, idx)] = P_pose
    return NavState(1.0, np.zeros(3), np.zeros(3), np.array(q, float), cov)


@settings(max_examples=60, deadline=None)
@given(SEEDS, st.sampled_from(["spd", "diagonal", "negative_diagonal", "indefinite", "tiny_negative"]))
def test_navigation_check_decides_as_the_eigenvalues(seed, kind):
    rng = np.random.default_rng(seed)
    if kind == "spd":
        A = rng.normal(size=(6, 6))
        P = A @ A.T
    elif kind == "diagonal":
        P = np.diag(rng.uniform(0.0, 2.0, 6))
    elif kind == "negative_diagonal":
        P = np.diag(rng.uniform(0.0, 2.0, 6))
        P[rng.integers(0, 6), rng.integers(0, 6)] *= 1.0  # stays diagonal
        P[3, 3] = -rng.uniform(1e-6, 1.0)
    elif kind == "indefinite":
        P = np.diag(rng.uniform(0.5, 2.0, 6))
        P[0, 1] = P[1, 0] = 5.0
    else:
        P = np.diag(rng.uniform(0.5, 2.0, 6))
        P[2, 2] = -1e-12  # within the tolerance
    nav = nav_with(P)
    scale = max(1.0, float(np.max(np.abs(P))))
    psd = np.linalg.eigvalsh(P).min() >= -1e-9 * scale
    reason, P_x = _checked_pose_covariance(nav)
    assert (reason == "") == psd, reason
    assert check_nav(nav) == reason
    if psd:
        np.testing.assert_array_equal(P_x, 0.5 * (nav.pose_covariance + nav.pose_covariance.T))


def test_navigation_check_reasons():
    P = np.eye(6)
    assert _checked_pose_covariance(nav_with(P, q=(0.0, 0.0, 0.0, 0.0)))[0] == "nav quaternion has zero norm"
    bad = nav_with(P)
    bad.covariance[4, 4] = np.nan
    assert check_nav(bad) == "nav not finite"
    huge = nav_with(np.eye(6) * 6e307)  # the finite-sum shortcut overflows; the exact test says finite
    huge.covariance[:] = np.diag(np.full(9, 6e307))
    with np.errstate(over="ignore"):
        assert check_nav(huge) == ""
    v_nan = NavState(1.0, np.zeros(3), np.array([np.nan, 0, 0]), np.array([1.0, 0, 0, 0]), np.eye(9))
    assert check_nav(v_nan) == "nav not finite"
    t_inf = NavState(np.inf, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(9))
    assert check_nav(t_inf) == "nav not finite"
    asym = nav_with(P)
    asym.covariance[0, 1] = 0.5
    assert check_nav(asym) == "nav pose covariance not symmetric"
    assert check_nav(NavState(0.0, np.zeros(2), np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(9))).startswith("nav shapes")
    assert check_nav(NavState(0.0, "x", np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(9))) == "nav not numeric"


# ------------------------------------------------------------------------------------------------
# Daemon status figures
# ------------------------------------------------------------------------------------------------


def test_status_percentiles_cover_the_recent_window_only():
    p = Percentiles(maxlen=1000, window_s=10.0)
    for k in range(100):
        p.add(1000.0 if k < 50 else float(k), t=float(k))  # the first 50 (start-up) are huge
    s = p.summary(now=99.0)  # window (89, 99]
    assert s["n"] == 11 and s["max"] == 99.0 and s["window_s"] == 10.0
    assert p.summary(now=200.0) == {"n": 0, "p50": None, "p99": None, "max": None, "window_s": 10.0}
    q = Percentiles(maxlen=5, window_s=1e9)
    for k in range(8):
        q.add(float(k), t=float(k))
    assert q.summary(now=8.0)["n"] == 5 and q.summary(now=8.0)["p50"] == 5.0


def test_status_percentiles_take_samples_from_another_thread_while_summarising():
    p = Percentiles(maxlen=500, window_s=60.0)
    stop = threading.Event()

    def producer():
        k = 0
        while not stop.is_set() and k < 200_000:
            p.add(float(k % 7))
            k += 1

    t = threading.Thread(target=producer)
    t.start()
    try:
        for _ in range(300):
            s = p.summary()
            assert s["n"] == 0 or 0.0 <= s["p50"] <= 6.0
    finally:
        stop.set()
        t.join(5.0)
    assert p.summary()["n"] == 500


@pytest.mark.parametrize("bad", [np.zeros((0, 2)), np.full((3, 2), np.nan)])
def test_candidate_pairs_of_nothing_or_nan_are_empty(bad):
    g = np.array([[10.0, 10.0]])
    S = np.eye(2)[None]
    pairs = matching.candidate_pairs(bad, g, S, 23.0, 10.0)
    assert len(pairs) == 0
    assert matching.gate_and_match_pairs(pairs.point, pairs.meas, pairs.Z, 9.21, len(bad))[2].shape == (len(bad),)
