"""Appearance check for matching: normalised patches around corners (docs/mapper.md, "Appearance").

The seed matches by Mahalanobis distance alone (eqs. 10-12). On a repetitive texture, or while a
new feature's depth is still unknown (its search region is a long strip along the epipolar line),
several corners lie inside one gate and the nearest is often the wrong one; a run of such
mistakes along the epipolar line looks like parallax and converges to a ghost point (measured in
the simulated flight: features at 10 m above flat ground, 5 m under the camera). A corner's
neighbourhood tells them apart: each measurement carries a small grey-level patch, normalised to
zero mean and unit norm, and a pair is only considered when the normalised cross-correlation of
the measurement's patch with the feature's template (its patch at its last accepted match)
reaches a threshold.

Every function is batched over N corners.
"""

from __future__ import annotations

import numpy as np


def patch_descriptors(gray: np.ndarray, uv: np.ndarray, size: int) -> np.ndarray:
    """Normalised patches (N, size^2) float32 of a grey image (H, W) around pixels ``uv`` (N, 2)
    (raw image coordinates, rounded to the nearest pixel; the image is edge-replicated outside).

    Each row has zero mean and unit norm; a flat patch (no texture) is all zeros, which
    correlates with nothing.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    if n == 0 or size < 1:
        return np.zeros((n, max(size, 0) ** 2), np.float32)
    r = size // 2
    h, w = gray.shape[:2]
    centre = np.clip(np.rint(uv), 0, [w - 1, h - 1]).astype(np.intp)  # (N, 2) column, row
    off = np.arange(size) - r
    lo, hi = centre.min(axis=0), centre.max(axis=0)
    if lo.min() >= r and hi[0] <= w - 1 - r and hi[1] <= h - 1 - r and gray.flags.c_contiguous:
        # every patch inside the image (the usual case): one gather by flat pixel index
        flat = (centre[:, 1] * w + centre[:, 0])[:, None] + (off[:, None] * w + off[None, :]).reshape(-1)
        patch = np.take(gray.reshape(-1), flat).astype(np.float32)
    else:
        rows = np.clip(centre[:, 1, None] + off[None, :], 0, h - 1)
        cols = np.clip(centre[:, 0, None] + off[None, :], 0, w - 1)
        patch = gray[rows[:, :, None], cols[:, None, :]].reshape(n, size * size).astype(np.float32)
    patch -= patch.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(patch, axis=1, keepdims=True)
    patch /= np.maximum(norm, 1e-3)
    patch[~(norm[:, 0] > 1e-3)] = 0.0  # a flat patch (or none) correlates with nothing
    return patch


def correlation(templates: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (N, M) of templates (N, K) with descriptors (M, K), in [-1, 1]."""
    return templates @ descriptors.T


def pair_correlation(templates: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (P,) of paired rows: templates (P, K) with descriptors (P, K).
    The candidate-pair form of :func:`correlation` (only the few pairs inside a gate are compared)."""
    return np.einsum("pk,pk->p", templates, descriptors)
