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
    c = np.rint(uv)
    x, y = c[:, 0], c[:, 1]
    # (NaN and inf fail these tests and take the clipped path below; four whole-array reductions
    # are cheaper than two along axis 0)
    if x.min() >= r and y.min() >= r and x.max() <= w - 1 - r and y.max() <= h - 1 - r and gray.flags.c_contiguous:
        # every patch inside the image (the usual case): one gather by flat pixel index
        flat = (y * w + x).astype(np.intp)[:, None] + _patch_offsets(size, w)
        patch = np.take(gray.reshape(-1), flat).astype(np.float32)
    else:
        off = np.arange(size) - r
        centre = np.clip(c, 0, [w - 1, h - 1]).astype(np.intp)  # (N, 2) column, row
        rows = np.clip(centre[:, 1, None] + off[None, :], 0, h - 1)
        cols = np.clip(centre[:, 0, None] + off[None, :], 0, w - 1)
        patch = gray[rows[:, :, None], cols[:, None, :]].reshape(n, size * size).astype(np.float32)
    # patch.mean(axis=1) and np.linalg.norm(patch, axis=1) spelt as the ufunc calls they make
    # (same values to the bit; a step cuts patches twice, and their wrappers cost as much as the
    # arithmetic on a few rows): the sum divided by the count in float64, stored as float32
    mean = np.add.reduce(patch, axis=1, keepdims=True)
    np.true_divide(mean, np.intp(size * size), out=mean, casting="unsafe")
    patch -= mean
    norm = np.sqrt(np.add.reduce(patch * patch, axis=1, keepdims=True))
    patch /= np.maximum(norm, 1e-3)
    flat_patch = ~(norm[:, 0] > 1e-3)
    if np.count_nonzero(flat_patch):
        patch[flat_patch] = 0.0  # a flat patch (or none) correlates with nothing
    return patch


_OFFSETS: dict[tuple[int, int], np.ndarray] = {}


def _patch_offsets(size: int, width: int) -> np.ndarray:
    """Flat index offsets (size^2,) of a patch's pixels from its centre in an image ``width`` wide
    (made once per patch size and image width)."""
    offsets = _OFFSETS.get((size, width))
    if offsets is None:
        off = np.arange(size) - size // 2
        offsets = _OFFSETS[(size, width)] = (off[:, None] * width + off[None, :]).reshape(-1)
    return offsets


class FramePatches:
    """The normalised patches of one frame's measurements, cut only when asked for.

    A step needs few of them: those of the measurements in gated pairs (the appearance check),
    and those of the matched and the initialised measurements (the templates they leave), about
    a third of the frame's corners at 50 features. ``rows(index)`` equals
    ``patch_descriptors(gray, uv, size)[index]`` to the bit (each patch is normalised on its
    own). gray (H, W) uint8; uv (N, 2) raw pixels; size: the patch edge (px).
    """

    __slots__ = ("gray", "uv", "size")

    def __init__(self, gray: np.ndarray, uv: np.ndarray, size: int):
        self.gray = gray
        self.uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        self.size = int(size)

    def __len__(self) -> int:
        return len(self.uv)

    def rows(self, index: np.ndarray) -> np.ndarray:
        """Patches (k, size^2) float32 of the measurements at ``index`` (k,)."""
        return patch_descriptors(self.gray, self.uv[index], self.size)

    def subset(self, index: np.ndarray) -> "FramePatches":
        """The patches of the measurements at ``index`` (k,) only, renumbered 0..k-1."""
        return FramePatches(self.gray, self.uv[index], self.size)


class GivenPatches:
    """Patches handed in by a caller (N, K) float32, with :class:`FramePatches`' interface."""

    __slots__ = ("patches",)

    def __init__(self, patches: np.ndarray):
        self.patches = patches

    def __len__(self) -> int:
        return len(self.patches)

    def rows(self, index: np.ndarray) -> np.ndarray:
        return self.patches[index]

    def subset(self, index: np.ndarray) -> "GivenPatches":
        return GivenPatches(self.patches[index])


def correlation(templates: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (N, M) of templates (N, K) with descriptors (M, K), in [-1, 1]."""
    return templates @ descriptors.T


def pair_correlation(templates: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (P,) of paired rows: templates (P, K) with descriptors (P, K).
    The candidate-pair form of :func:`correlation` (only the few pairs inside a gate are compared)."""
    return np.einsum("pk,pk->p", templates, descriptors)
