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
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])  # a third of the default's bytes
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


def _legend_rows(labels: list[str], width_px: int, item_px: int) -> int:
    per_row = max(1, width_px // item_px)
    return max(1, -(-len(labels) // per_row)) if labels else 0


def _legend_items(labels: list[str], x0: int, y0: int, width_px: int, item_px: int):
    """(x, y) baseline of each legend item laid out in rows of ``width_px``."""
    per_row = max(1, width_px // item_px)
    return [(x0 + (i % per_row) * item_px, y0 + (i // per_row) * 18) for i in range(len(labels))]


def _dashed(img, pts: np.ndarray, color, thickness: int, on_px: float = 8.0, off_px: float = 6.0) -> None:
    """A dashed polyline whose pattern follows the length drawn (not the sample spacing)."""
    p = pts.astype(float)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    period = on_px + off_px
    for k in range(int(s[-1] // period) + 1):
        a, b = k * period, min(k * period + on_px, s[-1])
        if b <= a:
            continue
        xa, ya = np.interp(a, s, p[:, 0]), np.interp(a, s, p[:, 1])
        xb, yb = np.interp(b, s, p[:, 0]), np.interp(b, s, p[:, 1])
        inner = (s > a) & (s < b)
        chain = np.vstack([[xa, ya], p[inner], [xb, yb]])
        cv2.polylines(img, [np.round(chain).astype(np.int32)], False, color, thickness, cv2.LINE_AA)


def line_chart(path, series: list[Series], title: str, xlabel: str, ylabel: str,
               size=(900, 420), ylim: tuple[float, float] | None = None) -> Path:
    """A line chart with axes, ticks, a title, the y label above the axis and the legend in rows
    below the x label (never over the data)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    item_px = 230
    rows = _legend_rows([s.label for s in series], w - 80, item_px)
    left, right, top, bottom = 70, 20, 50, 55 + 18 * rows
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
        _text(img, f"{t + 0.0:g}", (5, py + 4), 0.4, GREY)
    for t in nice_ticks(x0, x1, 8):
        px, _ = to_px(t, y0)
        cv2.line(img, (int(px), top), (int(px), h - bottom), LIGHT, 1)
        _text(img, f"{t + 0.0:g}", (px - 12, h - bottom + 16), 0.4, GREY)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), GREY, 1)
    clip = img.copy()  # lines are drawn on a copy and pasted back inside the axes only
    for s in series:
        px, py = to_px(s.x, s.y)
        py = np.clip(py, -10 * h, 10 * h)
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
                    overlay = clip.copy()
                    cv2.fillPoly(overlay, [poly], s.color)
                    cv2.addWeighted(overlay, 0.25, clip, 0.75, 0, clip)
                if s.dashed:
                    _dashed(clip, seg, s.color, s.thickness)
                else:
                    cv2.polylines(clip, [pts], False, s.color, s.thickness, cv2.LINE_AA)
            start = stop + 1
    img[top:h - bottom + 1, left:w - right + 1] = clip[top:h - bottom + 1, left:w - right + 1]
    cv2.rectangle(img, (left, top), (w - right, h - bottom), GREY, 1)
    _text(img, title, (left, 22), 0.6)
    _text(img, ylabel, (5, top - 10), 0.45)
    _text(img, xlabel, (w / 2 - 4 * len(xlabel), h - bottom + 36), 0.45)
    for (x, y), s in zip(_legend_items([s.label for s in series], left, h - bottom + 56, w - 80, item_px), series):
        if s.dashed:
            _dashed(img, np.array([[x, y - 4], [x + 30, y - 4]], float), s.color, 2, 6.0, 4.0)
        else:
            cv2.line(img, (x, y - 4), (x + 30, y - 4), s.color, 2)
        _text(img, s.label, (x + 36, y), 0.42)
    return write_png(path, img)


def bar_chart(path, groups: list[str], bars: dict[str, list[float]], title: str, ylabel: str,
              reference: tuple | list[tuple] | None = None, size=(760, 400)) -> Path:
    """Grouped bars: one group per label in ``groups``, one bar per key of ``bars``; optional
    horizontal reference lines ((value, label) or (value, label, BGR colour), or a list of them:
    the first solid, the others dashed). The legend (bars, then reference lines) sits in rows
    under the group labels."""
    refs = [] if reference is None else ([reference] if isinstance(reference, tuple) else list(reference))
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    item_px = 190
    refs = [(float(r[0]), str(r[1]), tuple(r[2]) if len(r) > 2 else BLACK) for r in refs]
    labels = list(bars) + [label for _, label, _ in refs]
    rows = _legend_rows(labels, w - 80, item_px)
    left, right, top, bottom = 70, 20, 50, 32 + 18 * rows
    values = np.array([v for vs in bars.values() for v in vs] + [v for v, _, _ in refs], float)
    finite = values[np.isfinite(values)]
    y1 = float(finite.max()) * 1.15 if finite.size and finite.max() > 0 else 1.0
    y0 = min(0.0, float(finite.min())) if finite.size else 0.0

    def py(v):
        return int(h - bottom - (v - y0) / (y1 - y0) * (h - top - bottom))

    for t in nice_ticks(y0, y1):
        cv2.line(img, (left, py(t)), (w - right, py(t)), LIGHT, 1)
        _text(img, f"{t + 0.0:g}", (5, py(t) + 4), 0.4, GREY)
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
            else:
                _text(img, "n/a", (x, py(0) - 4), 0.38, GREY)
        _text(img, g, (gx + group_w * 0.35 - 4 * len(g), h - bottom + 16), 0.45)
    for i, (v, _, col) in enumerate(refs):
        if i == 0:
            cv2.line(img, (left, py(v)), (w - right, py(v)), col, 1, cv2.LINE_AA)
        else:
            _dashed(img, np.array([[left, py(v)], [w - right, py(v)]], float), col, 1)
    # Values last, on a white patch, so that no reference line crosses them.
    for gi in range(n_groups):
        gx = left + gi * group_w + group_w * 0.15
        for bi, vs in enumerate(bars.values()):
            v = vs[gi] if gi < len(vs) else np.nan
            if np.isfinite(v):
                x, text = int(gx + bi * bar_w), f"{v:.1f}"
                (tw, th), _ = cv2.getTextSize(text, FONT, 0.38, 1)
                cv2.rectangle(img, (x - 1, py(v) - 6 - th), (x + tw + 1, py(v) - 2), WHITE, -1)
                _text(img, text, (x, py(v) - 4), 0.38)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), GREY, 1)
    _text(img, title, (left, 22), 0.6)
    _text(img, ylabel, (5, top - 10), 0.45)
    items = _legend_items(labels, left, h - bottom + 36, w - 80, item_px)
    for (x, y), (bi, name) in zip(items, enumerate(bars)):
        cv2.rectangle(img, (x, y - 10), (x + 15, y), PALETTE[bi % len(PALETTE)], -1)
        _text(img, name, (x + 21, y), 0.42)
    for i, ((x, y), (_, label, col)) in enumerate(zip(items[len(bars):], refs)):
        if i == 0:
            cv2.line(img, (x, y - 5), (x + 15, y - 5), col, 1, cv2.LINE_AA)
        else:
            _dashed(img, np.array([[x, y - 5], [x + 15, y - 5]], float), col, 1, 4.0, 3.0)
        _text(img, label, (x + 21, y), 0.42)
    return write_png(path, img)


def scale_bar_length(span_m: float) -> float:
    """A round length (1, 2 or 5 x 10^k m) of at most a quarter of ``span_m``."""
    want = max(span_m, 1e-9) / 4.0
    mag = 10 ** np.floor(np.log10(want))
    return float(max(m * mag for m in (1, 2, 5) if m * mag <= want * (1 + 1e-9)))


def height_map(path, heights: np.ndarray, north0_m: float, east0_m: float, cell_m: float,
               title: str, paths: list[tuple[np.ndarray, str, tuple[int, int, int]]] = (),
               outlines: list[np.ndarray] = (), vmin: float | None = None, vmax: float | None = None,
               scale_px: int | None = None, notes: list[str] = ()) -> Path:
    """A height grid as a colour image, north up, east right, unknown cells grey, with a colour
    bar (m; an end is marked ``<=``/``>=`` when cells lie beyond the range given), a north arrow,
    flight paths ((N, 2) north/east arrays with a label and colour), polygon outlines ((K, 2)
    north/east), and under the map the legend (in rows that fit its width), a scale bar and
    optional lines of ``notes``."""
    heights = np.asarray(heights, float)
    rows, cols = heights.shape  # rows = north cells, cols = east cells
    if scale_px is None:
        scale_px = int(max(1, min(8, 700 // max(rows, cols, 1))))
    known = np.isfinite(heights)
    lo = vmin if vmin is not None else (float(np.nanmin(heights)) if known.any() else 0.0)
    hi = vmax if vmax is not None else (float(np.nanmax(heights)) if known.any() else 1.0)
    hi = hi if hi > lo else lo + 1.0
    below = bool(known.any() and np.nanmin(heights) < lo)
    above = bool(known.any() and np.nanmax(heights) > hi)
    norm = np.clip((np.where(known, heights, lo) - lo) / (hi - lo), 0, 1)
    colour = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    colour[~known] = (200, 200, 200)
    colour = colour[::-1]  # north up: the last row (largest north) at the top
    colour = cv2.resize(colour, (cols * scale_px, rows * scale_px), interpolation=cv2.INTER_NEAREST)
    map_h, map_w = colour.shape[:2]
    pad_l, pad_t, pad_r = 20, 40, 120
    (title_w, _), _ = cv2.getTextSize(title, FONT, 0.55, 1)
    width = max(map_w + pad_l + pad_r, 360, title_w + 2 * pad_l)
    item_px = 120
    legend = [label for _, label, _ in paths] + ["unknown"]
    legend_rows = _legend_rows(legend, width - 2 * pad_l, item_px)
    pad_b = 14 + 18 * legend_rows + 30 + 18 * len(notes)
    H, W = map_h + pad_t + pad_b, width
    img = np.full((H, W, 3), 255, np.uint8)
    img[pad_t:pad_t + map_h, pad_l:pad_l + map_w] = colour
    cv2.rectangle(img, (pad_l - 1, pad_t - 1), (pad_l + map_w, pad_t + map_h), GREY, 1)

    def to_px(ne):
        ne = np.asarray(ne, float).reshape(-1, 2)
        x = pad_l + (ne[:, 1] - east0_m) / cell_m * scale_px
        y = pad_t + map_h - (ne[:, 0] - north0_m) / cell_m * scale_px
        return np.round(np.stack([x, y], axis=1)).astype(np.int32)

    for poly in outlines:
        cv2.polylines(img, [to_px(poly)], True, WHITE, 2, cv2.LINE_AA)
        cv2.polylines(img, [to_px(poly)], True, BLACK, 1, cv2.LINE_AA)
    for p, _, col in paths:
        pts = to_px(p)
        if len(pts) >= 2:  # a white halo keeps the path visible over any colour
            cv2.polylines(img, [pts], False, WHITE, 3, cv2.LINE_AA)
    for p, _, col in paths:
        pts = to_px(p)
        if len(pts) >= 2:
            cv2.polylines(img, [pts], False, col, 1, cv2.LINE_AA)
    # Legend under the map, in rows.
    y_leg = pad_t + map_h + 22
    items = _legend_items(legend, pad_l, y_leg, width - 2 * pad_l, item_px)
    for (x, y), (_, label, col) in zip(items, paths):
        cv2.line(img, (x, y - 4), (x + 25, y - 4), col, 2)
        _text(img, label, (x + 30, y), 0.42)
    x, y = items[-1]
    cv2.rectangle(img, (x, y - 10), (x + 25, y), (200, 200, 200), -1)
    _text(img, "unknown", (x + 30, y), 0.42)
    # Scale bar (a round number of metres) below the legend, then the notes.
    length_m = scale_bar_length(cols * cell_m)
    lx = max(1, int(round(length_m / cell_m * scale_px)))
    y = y_leg + 18 * legend_rows + 6
    cv2.line(img, (pad_l, y), (pad_l + lx, y), BLACK, 2)
    for xx in (pad_l, pad_l + lx):
        cv2.line(img, (xx, y - 4), (xx, y + 4), BLACK, 1)
    _text(img, f"{length_m:g} m", (pad_l + lx + 6, y + 4), 0.42)
    for i, note in enumerate(notes):
        _text(img, note, (pad_l, y + 24 + 18 * i), 0.4, (60, 60, 60))
    # Colour bar right of the map, north arrow above it.
    bar_h = max(map_h - 60, 60)
    bar_y = pad_t + 40
    ramp = np.linspace(1, 0, bar_h)[:, None]
    bar = cv2.applyColorMap((np.repeat(ramp, 15, axis=1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    bx = pad_l + map_w + 15
    img[bar_y:bar_y + bar_h, bx:bx + 15] = bar[: max(0, min(bar_h, H - bar_y))]
    for t in nice_ticks(lo, hi, 5):
        yy = int(bar_y + (hi - t) / (hi - lo) * bar_h)
        _text(img, f"{t + 0.0:g} m", (bx + 20, yy + 4), 0.4)
    if above:
        _text(img, f">= {hi:g}", (bx - 2, bar_y - 6), 0.38)
    if below:
        _text(img, f"<= {lo:g}", (bx - 2, bar_y + bar_h + 14), 0.38)
    ax, ay = bx + 7, pad_t + 24
    cv2.arrowedLine(img, (ax, ay), (ax, ay - 20), BLACK, 2, cv2.LINE_AA, tipLength=0.35)
    _text(img, "N", (ax + 8, ay - 6), 0.45)
    _text(img, title, (pad_l, 25), 0.55)
    return write_png(path, img)
