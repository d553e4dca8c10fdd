"""PNG figures drawn with OpenCV only (no plotting library on the vehicle).

Three kinds: a map (height grid, north up, with paths and outlines), a line chart (side
profiles: altitude, true and mapped terrain) and a grouped bar chart (per-lap comparisons).
Every function writes a PNG atomically and returns its path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (150, 150, 150)
LIGHT = (225, 225, 225)
# BGR colours for series, chosen to stay distinct when printed in grey.
PALETTE = [(200, 90, 20), (40, 40, 220), (40, 160, 40), (0, 160, 230), (160, 60, 160), (90, 90, 90)]


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Atomic PNG write: a reader never sees a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode {path}")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)
    return path


def nice_ticks(lo: float, hi: float, count: int = 6) -> np.ndarray:
    """Round tick values covering [lo, hi] (1, 2, 5 x 10^k steps)."""
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(1, count)
    mag = 10 ** np.floor(np.log10(raw))
    step = mag * min((m for m in (1, 2, 5, 10) if m * mag >= raw), default=10)
    return np.arange(np.ceil(lo / step) * step, hi + step * 1e-9, step)


def _text(img, s, org, scale=0.45, color=BLACK, thickness=1):
    cv2.putText(img, s, (int(org[0]), int(org[1])), FONT, scale, color, thickness, cv2.LINE_AA)


@dataclass(frozen=True, slots=True)
class Series:
    """One line of a chart: x, y (same length, NaN breaks the line), a label and a style."""

    x: np.ndarray
    y: np.ndarray
    label: str
    color: tuple[int, int, int] = PALETTE[0]
    thickness: int = 2
    dashed: bool = False
    fill_to_bottom: bool = False


def line_chart(path, series: list[Series], title: str, xlabel: str, ylabel: str,
               size=(900, 420), ylim: tuple[float, float] | None = None) -> Path:
    """A line chart with axes, ticks, a legend and a title."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 70, 20, 40, 55
    xs = np.concatenate([np.asarray(s.x, float) for s in series]) if series else np.zeros(1)
    ys = np.concatenate([np.asarray(s.y, float) for s in series]) if series else np.zeros(1)
    xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
    x0, x1 = (float(xs.min()), float(xs.max())) if xs.size else (0.0, 1.0)
    if ylim is None:
        y0, y1 = (float(ys.min()), float(ys.max())) if ys.size else (0.0, 1.0)
        pad = 0.08 * max(y1 - y0, 1.0)
        y0, y1 = y0 - pad, y1 + pad
    else:
        y0, y1 = ylim
    x1 = x1 if x1 > x0 else x0 + 1.0
    y1 = y1 if y1 > y0 else y0 + 1.0

    def to_px(x, y):
        px = left + (np.asarray(x, float) - x0) / (x1 - x0) * (w - left - right)
        py = h - bottom - (np.asarray(y, float) - y0) / (y1 - y0) * (h - top - bottom)
        return px, py

    for t in nice_ticks(y0, y1):
        _, py = to_px(x0, t)
        cv2.line(img, (left, int(py)), (w - right, int(py)), LIGHT, 1)
        _text(img, f"{t:g}", (5, py + 4), 0.4, GREY)
    for t in nice_ticks(x0, x1, 8):
        px, _ = to_px(t, y0)
        cv2.line(img, (int(px), top), (int(px), h - bottom), LIGHT, 1)
        _text(img, f"{t:g}", (px - 12, h - bottom + 16), 0.4, GREY)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), GREY, 1)
    for s in series:
        px, py = to_px(s.x, s.y)
        ok = np.isfinite(px) & np.isfinite(py)
        # Split the polyline at NaN gaps.
        breaks = np.flatnonzero(~ok)
        start = 0
        for stop in list(breaks) + [len(px)]:
            seg = np.stack([px[start:stop], py[start:stop]], axis=1)
            if len(seg) >= 2:
                pts = np.round(seg).astype(np.int32)
                if s.fill_to_bottom:
                    poly = np.vstack([pts, [[pts[-1, 0], h - bottom], [pts[0, 0], h - bottom]]])
                    overlay = img.copy()
                    cv2.fillPoly(overlay, [poly], s.color)
                    cv2.addWeighted(overlay, 0.25, img, 0.75, 0, img)
                if s.dashed:
                    for i in range(0, len(pts) - 1, 2):
                        cv2.line(img, tuple(pts[i]), tuple(pts[i + 1]), s.color, s.thickness, cv2.LINE_AA)
                else:
                    cv2.polylines(img, [pts], False, s.color, s.thickness, cv2.LINE_AA)
            start = stop + 1
    _text(img, title, (left, 25), 0.6)
    _text(img, xlabel, (w / 2 - 40, h - 12), 0.45)
    _text(img, ylabel, (5, top - 8), 0.45)
    for i, s in enumerate(series):
        y = top + 18 + 18 * i
        cv2.line(img, (w - right - 200, y - 4), (w - right - 170, y - 4), s.color, 2)
        _text(img, s.label, (w - right - 165, y), 0.42)
    return write_png(path, img)


def bar_chart(path, groups: list[str], bars: dict[str, list[float]], title: str, ylabel: str,
              reference: tuple[float, str] | None = None, size=(760, 400)) -> Path:
    """Grouped bars: one group per label in ``groups``, one bar per key of ``bars``; an optional
    horizontal reference line (value, label)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 70, 20, 40, 50
    values = np.array([v for vs in bars.values() for v in vs] + ([reference[0]] if reference else []), float)
    finite = values[np.isfinite(values)]
    y1 = float(finite.max()) * 1.15 if finite.size and finite.max() > 0 else 1.0
    y0 = min(0.0, float(finite.min())) if finite.size else 0.0

    def py(v):
        return int(h - bottom - (v - y0) / (y1 - y0) * (h - top - bottom))

    for t in nice_ticks(y0, y1):
        cv2.line(img, (left, py(t)), (w - right, py(t)), LIGHT, 1)
        _text(img, f"{t:g}", (5, py(t) + 4), 0.4, GREY)
    n_groups, n_bars = len(groups), max(1, len(bars))
    group_w = (w - left - right) / max(1, n_groups)
    bar_w = group_w * 0.7 / n_bars
    for gi, g in enumerate(groups):
        gx = left + gi * group_w + group_w * 0.15
        for bi, (name, vs) in enumerate(bars.items()):
            v = vs[gi] if gi < len(vs) else np.nan
            x = int(gx + bi * bar_w)
            if np.isfinite(v):
                cv2.rectangle(img, (x, py(v)), (int(x + bar_w - 3), py(0)), PALETTE[bi % len(PALETTE)], -1)
                _text(img, f"{v:.1f}", (x, py(v) - 4), 0.38)
            else:
                _text(img, "n/a", (x, py(0) - 4), 0.38, GREY)
        _text(img, g, (gx + group_w * 0.2, h - bottom + 18), 0.45)
    if reference:
        cv2.line(img, (left, py(reference[0])), (w - right, py(reference[0])), BLACK, 1, cv2.LINE_AA)
        _text(img, reference[1], (left + 5, py(reference[0]) - 5), 0.4)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), GREY, 1)
    _text(img, title, (left, 25), 0.6)
    _text(img, ylabel, (5, top - 8), 0.45)
    for bi, name in enumerate(bars):
        y = top + 18 + 18 * bi
        cv2.rectangle(img, (w - right - 190, y - 10), (w - right - 175, y), PALETTE[bi % len(PALETTE)], -1)
        _text(img, name, (w - right - 168, y), 0.42)
    return write_png(path, img)


def height_map(path, heights: np.ndarray, north0_m: float, east0_m: float, cell_m: float,
               title: str, paths: list[tuple[np.ndarray, str, tuple[int, int, int]]] = (),
               outlines: list[np.ndarray] = (), vmin: float | None = None, vmax: float | None = None,
               scale_px: int | None = None) -> Path:
    """A height grid as a colour image, north up, east right, unknown cells grey, with a colour
    bar (m), a scale bar, flight paths ((N, 2) north/east arrays with a label and colour) and
    polygon outlines ((K, 2) north/east)."""
    heights = np.asarray(heights, float)
    rows, cols = heights.shape  # rows = north cells, cols = east cells
    if scale_px is None:
        scale_px = int(max(1, min(8, 700 // max(rows, cols, 1))))
    known = np.isfinite(heights)
    lo = vmin if vmin is not None else (float(np.nanmin(heights)) if known.any() else 0.0)
    hi = vmax if vmax is not None else (float(np.nanmax(heights)) if known.any() else 1.0)
    hi = hi if hi > lo else lo + 1.0
    norm = np.clip((np.where(known, heights, lo) - lo) / (hi - lo), 0, 1)
    colour = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    colour[~known] = (200, 200, 200)
    colour = colour[::-1]  # north up: the last row (largest north) at the top
    colour = cv2.resize(colour, (cols * scale_px, rows * scale_px), interpolation=cv2.INTER_NEAREST)
    pad_l, pad_t, pad_r, pad_b = 20, 40, 110, 50
    H, W = colour.shape[0] + pad_t + pad_b, colour.shape[1] + pad_l + pad_r
    img = np.full((H, W, 3), 255, np.uint8)
    img[pad_t:pad_t + colour.shape[0], pad_l:pad_l + colour.shape[1]] = colour

    def to_px(ne):
        ne = np.asarray(ne, float).reshape(-1, 2)
        x = pad_l + (ne[:, 1] - east0_m) / cell_m * scale_px
        y = pad_t + colour.shape[0] - (ne[:, 0] - north0_m) / cell_m * scale_px
        return np.round(np.stack([x, y], axis=1)).astype(np.int32)

    for poly in outlines:
        cv2.polylines(img, [to_px(poly)], True, WHITE, 2, cv2.LINE_AA)
        cv2.polylines(img, [to_px(poly)], True, BLACK, 1, cv2.LINE_AA)
    for i, (p, label, col) in enumerate(paths):
        pts = to_px(p)
        if len(pts) >= 2:
            cv2.polylines(img, [pts], False, col, 2, cv2.LINE_AA)
        y = pad_t + colour.shape[0] + 20 + 0 * i
        x = pad_l + 160 * i
        cv2.line(img, (x, y + 12), (x + 25, y + 12), col, 2)
        _text(img, label, (x + 30, y + 16), 0.42)
    # Colour bar.
    bar_h = colour.shape[0]
    ramp = np.linspace(1, 0, bar_h)[:, None]
    bar = cv2.applyColorMap((np.repeat(ramp, 15, axis=1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    bx = pad_l + colour.shape[1] + 15
    img[pad_t:pad_t + bar_h, bx:bx + 15] = bar
    for t in nice_ticks(lo, hi, 5):
        y = int(pad_t + (hi - t) / (hi - lo) * bar_h)
        _text(img, f"{t:g} m", (bx + 20, y + 4), 0.4)
    # Scale bar (a round number of metres) and north arrow.
    span_m = cols * cell_m
    length_m = float(nice_ticks(0, span_m / 4, 1)[-1]) or cell_m
    lx = int(length_m / cell_m * scale_px)
    y = H - 12
    cv2.line(img, (pad_l, y), (pad_l + lx, y), BLACK, 2)
    _text(img, f"{length_m:g} m", (pad_l + lx + 6, y + 4), 0.42)
    _text(img, "N ^", (W - 50, 25), 0.5)
    _text(img, title, (pad_l, 25), 0.6)
    return write_png(path, img)
