"""Procedural textures for the simulated world, deterministic from a seed.

What the mapper needs from a texture is Harris corners: high-contrast polygonal blobs, field
boundaries that meet at angles, window corners. Sizes are in metres and converted with the
texel size, so a texture looks the same at any resolution. Drawing uses OpenCV primitives.

``synthesize(spec)`` is the entry point (``spec`` a :class:`drivers.sim.world.TextureSpec`);
it returns ``(height_px, width_px) uint8``. Wrapping textures (the ground) are seamless: shapes
crossing an edge are drawn again on the other side and the noise is filtered with wrap-around.
"""

from __future__ import annotations

import cv2
import numpy as np

_SHIFT = 4  # sub-texel precision bits for cv2 drawing


def synthesize(spec) -> np.ndarray:
    """Texture pixels (height_px, width_px) uint8 for a TextureSpec, shade applied."""
    rng = np.random.default_rng(spec.seed)
    shape = (spec.height_px, spec.width_px)
    if spec.kind == "fields":
        img = fields(shape, spec.texel_m, rng, spec.wrap)
    elif spec.kind == "windows":
        img = wall_with_windows(shape, spec.windows, rng)
    elif spec.kind == "plain":
        img = plain(shape, spec.texel_m, rng)
    elif spec.kind == "gravel":
        img = gravel(shape, spec.texel_m, rng)
    elif spec.kind == "leaves":
        img = leaves(shape, spec.texel_m, rng)
    else:
        raise ValueError(f"unknown texture kind {spec.kind!r}")
    contrast = float(getattr(spec, "contrast", 1.0))
    if contrast != 1.0:  # fainter texture: the spread about the mean grey shrinks, the mean stays
        mean = float(img.mean())
        img = cv2.convertScaleAbs(img, alpha=contrast, beta=(1.0 - contrast) * mean)
    if spec.shade != 1.0:
        img = cv2.convertScaleAbs(img, alpha=float(spec.shade))
    return img


# ---- drawing helpers -------------------------------------------------------------------------


def _offsets(bbox_min: np.ndarray, bbox_max: np.ndarray, shape: tuple[int, int], wrap: bool) -> list[np.ndarray]:
    """Translations at which a shape must be drawn: itself, plus its images across wrapped edges."""
    if not wrap:
        return [np.zeros(2)]
    h, w = shape
    out = []
    for dx in (-w, 0, w):
        for dy in (-h, 0, h):
            if bbox_max[0] + dx >= 0 and bbox_min[0] + dx < w and bbox_max[1] + dy >= 0 and bbox_min[1] + dy < h:
                out.append(np.array([dx, dy]))
    return out


def _polygons(img: np.ndarray, polys: np.ndarray, grays: np.ndarray, wrap: bool) -> None:
    """Fill convex polygons (K, M, 2) in texel coordinates with the given grays (K,)."""
    scale = 1 << _SHIFT
    mins, maxs = polys.min(axis=1), polys.max(axis=1)
    for poly, lo, hi, g in zip(polys, mins, maxs, grays):
        for off in _offsets(lo, hi, img.shape, wrap):
            cv2.fillConvexPoly(img, np.round((poly + off) * scale).astype(np.int32), int(g), cv2.LINE_AA, _SHIFT)


def _random_convex(rng: np.random.Generator, centres: np.ndarray, radii: np.ndarray, vertices: int,
                   irregularity: float) -> np.ndarray:
    """(K, vertices, 2) random polygons around ``centres`` with radii ``radii`` (texels), near-convex."""
    k = len(centres)
    step = 2 * np.pi / vertices
    # Evenly spread angles, jittered by less than half a step so their order (and convexity) holds.
    angles = (np.arange(vertices) * step)[None, :] + rng.uniform(0, 2 * np.pi, (k, 1))
    angles = angles + rng.uniform(-0.4, 0.4, (k, vertices)) * step * irregularity
    r = radii[:, None] * rng.uniform(1 - 0.3 * irregularity, 1.0, (k, vertices))
    return centres[:, None, :] + np.stack([r * np.cos(angles), r * np.sin(angles)], axis=-1)


def _add_noise(img: np.ndarray, sigma_gray: float, blur_texels: float, rng: np.random.Generator, wrap: bool) -> np.ndarray:
    """Add smooth noise (uniform noise low-passed by a Gaussian) of about ``sigma_gray`` gray levels."""
    noise = rng.integers(0, 256, img.shape, dtype=np.uint8)
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT101
    pad = int(3 * blur_texels) + 1
    padded = cv2.copyMakeBorder(noise, pad, pad, pad, pad, border)
    smooth = cv2.GaussianBlur(padded, (0, 0), blur_texels)[pad:-pad, pad:-pad]
    # Blurring uniform noise (std 74) by sigma b shrinks its std by about 2 b sqrt(pi).
    gain = sigma_gray / (74.0 / (2 * blur_texels * np.sqrt(np.pi)))
    return cv2.addWeighted(img, 1.0, smooth, gain, -128.0 * gain)


def _blur(img: np.ndarray, sigma: float, wrap: bool) -> np.ndarray:
    pad = int(3 * sigma) + 1
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT101
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, border)
    return cv2.GaussianBlur(padded, (0, 0), sigma)[pad:-pad, pad:-pad]


# ---- textures ---------------------------------------------------------------------------------


def fields(shape: tuple[int, int], texel_m: float, rng: np.random.Generator, wrap: bool = False) -> np.ndarray:
    """Farmland seen from low altitude: field patches (straight boundaries meeting at corners),
    smaller patches of soil and scrub, and rocks; a little grass noise on top."""
    h, w = shape
    area_m2 = h * w * texel_m**2
    img = np.full(shape, 115, np.uint8)
    # Fields: rotated rectangles 6-25 m, drawn over each other into a patchwork.
    n = max(1, int(area_m2 / 120))
    centres = rng.uniform([0, 0], [w, h], (n, 2))
    half = rng.uniform(3.0, 12.5, (n, 2)) / texel_m
    yaw = rng.uniform(0, np.pi, n)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)[None] * half[:, None, :]
    rects = centres[:, None, :] + np.stack([corners[..., 0] * c - corners[..., 1] * s,
                                            corners[..., 0] * s + corners[..., 1] * c], axis=-1)
    _polygons(img, rects, rng.integers(70, 180, n), wrap)
    # Patches: irregular blobs 1-4 m.
    n = max(1, int(area_m2 / 14))
    patches = _random_convex(rng, rng.uniform([0, 0], [w, h], (n, 2)), rng.uniform(0.5, 2.0, n) / texel_m, 5, 0.8)
    _polygons(img, patches, rng.integers(50, 200, n), wrap)
    # Rocks and bushes: small, dark or bright, 0.2-0.7 m: the corners seen at 15-40 m. Triangles and
    # quadrilaterals: Harris responds to sharp corners, hardly to the obtuse ones of rounder shapes.
    n = max(2, int(area_m2 / 1.2))
    rocks3 = _random_convex(rng, rng.uniform([0, 0], [w, h], (n // 2, 2)), rng.uniform(0.12, 0.35, n // 2) / texel_m, 3, 0.8)
    rocks4 = _random_convex(rng, rng.uniform([0, 0], [w, h], (n - n // 2, 2)), rng.uniform(0.12, 0.35, n - n // 2) / texel_m, 4, 1.0)
    dark = rng.random(n) < 0.6
    grays = np.where(dark, rng.integers(15, 60, n), rng.integers(185, 245, n))
    _polygons(img, rocks3, grays[: n // 2], wrap)
    _polygons(img, rocks4, grays[n // 2:], wrap)
    return _add_noise(img, 6.0, 1.0, rng, wrap)


def wall_with_windows(shape: tuple[int, int], windows: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """A plain rendered wall with dark window panes at texel rectangles ``[c0, r0, c1, r1)``.

    Nothing else on the wall carries contrast, so above the last row of windows the wall gives no
    corners (the seed paper's building was mapped only up to its windows).
    """
    img = np.full(shape, int(rng.integers(150, 175)), np.uint8)
    img = _add_noise(img, 1.5, 2.0, rng, False)
    if windows is not None:
        grays = rng.integers(20, 60, len(windows))
        for (c0, r0, c1, r1), g in zip(windows, grays):
            img[r0:r1, c0:c1] = g
            # A faint reflection gradient inside the pane, low contrast so it adds no corners.
            ramp = np.linspace(0, 12, r1 - r0, dtype=np.float32)[:, None]
            img[r0:r1, c0:c1] = np.clip(img[r0:r1, c0:c1] + ramp, 0, 255).astype(np.uint8)
    return img


def plain(shape: tuple[int, int], texel_m: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform surface (render, roofing membrane) with faint smooth noise: no trackable corners."""
    img = np.full(shape, int(rng.integers(135, 165)), np.uint8)
    return _add_noise(img, 1.5, 3.0, rng, False)


def gravel(shape: tuple[int, int], texel_m: float, rng: np.random.Generator) -> np.ndarray:
    """Gravel roof: mid-gray with many small dark and light stones."""
    h, w = shape
    img = np.full(shape, 120, np.uint8)
    n = max(1, int(h * w * texel_m**2 / 0.5))
    stones = _random_convex(rng, rng.uniform([0, 0], [w, h], (n, 2)), rng.uniform(0.08, 0.2, n) / texel_m, 5, 1.0)
    _polygons(img, stones, np.where(rng.random(n) < 0.5, rng.integers(30, 80, n), rng.integers(170, 230, n)), False)
    return _blur(_add_noise(img, 5.0, 1.0, rng, False), 0.6, False)


def leaves(shape: tuple[int, int], texel_m: float, rng: np.random.Generator) -> np.ndarray:
    """Foliage: overlapping leaf clusters of varied brightness on a dark background."""
    h, w = shape
    img = np.full(shape, 55, np.uint8)
    n = max(1, int(h * w * texel_m**2 / 0.35))
    clusters = _random_convex(rng, rng.uniform([0, 0], [w, h], (n, 2)), rng.uniform(0.15, 0.5, n) / texel_m, 6, 1.0)
    _polygons(img, clusters, rng.integers(20, 170, n), False)
    return _blur(_add_noise(img, 6.0, 1.0, rng, False), 0.6, False)
