"""Binned Harris detector (seed 000, II.C): corners where they are, and every selection rule held.

Synthetic frames with exactly known corners: a checkerboard seen through a homography (X
junctions) and axis-free rectangles (L corners), rendered by supersampling the continuous
scene, blurred like a lens and given sensor noise.
"""

import time

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import MapperConfig
from companion.mapper.features import HarrisDetector, detect_corners, suppress_within

SUPERSAMPLE = 4


def _sample_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous coordinates of SUPERSAMPLE^2 samples per pixel (pixel centres at integers)."""
    ys, xs = np.mgrid[0 : height * SUPERSAMPLE, 0 : width * SUPERSAMPLE].astype(np.float64)
    return (xs + 0.5) / SUPERSAMPLE - 0.5, (ys + 0.5) / SUPERSAMPLE - 0.5


def _finish(value: np.ndarray, width: int, height: int, blur: float, noise: float, rng) -> np.ndarray:
    """Average the samples into pixels, blur, add noise, quantise to uint8."""
    img = value.reshape(height, SUPERSAMPLE, width, SUPERSAMPLE).mean(axis=(1, 3))
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_checkerboard(rng, width=320, height=240, square=24.0, n=(10, 7), angle_deg=17.0, offset=(40.0, 15.0), blur=0.8, noise=2.0):
    """Checkerboard of ``n`` squares (board units = px) through a homography. Returns the image
    and the true inner corners (M, 2) in pixels."""
    a = np.radians(angle_deg)
    Hm = np.array([[np.cos(a), -np.sin(a), offset[0]], [np.sin(a), np.cos(a), offset[1]], [3e-4, 2e-4, 1.0]])
    xs, ys = _sample_grid(width, height)
    p = np.linalg.inv(Hm) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    u, v = p[0] / p[2], p[1] / p[2]
    inside = (u >= 0) & (u < n[0] * square) & (v >= 0) & (v < n[1] * square)
    parity = (np.floor(u / square) + np.floor(v / square)) % 2 == 0
    value = np.where(inside, np.where(parity, 210.0, 40.0), 125.0)
    img = _finish(value, width, height, blur, noise, rng)
    g = np.stack(np.meshgrid(np.arange(1, n[0]) * square, np.arange(1, n[1]) * square), -1).reshape(-1, 2)
    q = Hm @ np.column_stack([g, np.ones(len(g))]).T
    return img, (q[:2] / q[2]).T


def render_rectangles(rng, width=320, height=240, count=12, blur=0.8, noise=2.0):
    """Non-overlapping axis-aligned rectangles with sub-pixel edges on a plain background.
    Returns the image and the true corners (4 count, 2)."""
    xs, ys = _sample_grid(width, height)
    value = np.full(xs.shape, 70.0)
    corners: list[tuple[float, float]] = []
    cells = [(cx, cy) for cy in range(3) for cx in range(4)][:count]
    cw, ch = (width - 20) / 4, (height - 20) / 3
    for i, (cx, cy) in enumerate(cells):
        x0 = 10 + cx * cw + rng.uniform(8, 18)
        y0 = 10 + cy * ch + rng.uniform(8, 18)
        x1 = x0 + rng.uniform(0.45, 0.6) * cw
        y1 = y0 + rng.uniform(0.45, 0.6) * ch
        value[(xs >= x0) & (xs < x1) & (ys >= y0) & (ys < y1)] = 190.0 if i % 2 else 150.0
        # the continuous edge is at x0 / x1, so are the corners
        corners += [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
    return _finish(value, width, height, blur, noise, rng), np.array(corners)


def textured_frame(rng, width=640, height=480, count=300) -> np.ndarray:
    """A busy frame (random filled rectangles, blurred, noisy) like a terrain image."""
    img = np.full((height, width), 128, np.uint8)
    for _ in range(count):
        x, y = rng.integers(0, width), rng.integers(0, height)
        w, h = rng.integers(5, 60, 2)
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), int(rng.integers(20, 256)), -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    return np.clip(img + rng.normal(0, 2, img.shape), 1, 255).astype(np.uint8)


def nearest(uv: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each detection to the nearest true corner, and from each true corner to
    the nearest detection."""
    d = np.linalg.norm(uv[:, None, :] - truth[None, :, :], axis=2)
    return d.min(axis=1), d.min(axis=0)


def cfg_with(**kw) -> MapperConfig:
    import dataclasses

    return dataclasses.replace(MapperConfig(), **kw)
