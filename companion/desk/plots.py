"""PNG report figures drawn with matplotlib (the ``desk`` extra; the vehicle never imports it).

Three kinds: a map (height grid, north up, with paths and outlines), a line chart (side
profiles: altitude, true and mapped terrain) and a grouped bar chart (per-lap comparisons).
Every function writes a PNG atomically and returns its path. matplotlib is imported when a
figure is drawn, not when this module is, because ``companion run`` builds every subcommand's
parser (and so imports this module) on the vehicle, where matplotlib is not installed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

INSTALL_HINT = "pip install 'companion[desk]'"
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (150, 150, 150)
UNKNOWN_RGB = (0.80, 0.80, 0.80)
# BGR colours for series (the callers' convention), chosen to stay distinct when printed in grey.
PALETTE = [(200, 90, 20), (40, 40, 220), (40, 160, 40), (0, 160, 230), (160, 60, 160), (90, 90, 90)]
DPI = 110
MAP_LONG_SIDE_IN = 7.0  # the map panel's longer side, whatever the area mapped (10 m or 1 km)


class DeskExtraMissing(RuntimeError):
    """matplotlib is not installed: the message says how to install it."""


def require() -> None:
    """Raise :class:`DeskExtraMissing` (one line, with the install command) when matplotlib is missing.
    Desk tools call this before their work, so that a long run does not fail at its figures."""
    _pyplot()


def _pyplot():
    try:
        import matplotlib
    except ModuleNotFoundError as exc:
        raise DeskExtraMissing(f"the figures need matplotlib, which is not installed: {INSTALL_HINT}") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def rgb(bgr: tuple[int, int, int]) -> tuple[float, float, float]:
    """A BGR 0-255 colour (the callers' convention, as OpenCV's) as matplotlib's RGB 0-1."""
    b, g, r = bgr
    return (r / 255.0, g / 255.0, b / 255.0)


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Atomic PNG write of a BGR image: a reader never sees a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise ValueError(f"cannot encode {path}")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)
    return path


def _save(fig, path: str | Path) -> Path:
    """Atomic write of a matplotlib figure, then the figure is closed (no pyplot state left)."""
    plt = _pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        fig.savefig(tmp, format="png", dpi=DPI, bbox_inches="tight", pad_inches=0.15)
    finally:
        plt.close(fig)
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


@dataclass(frozen=True, slots=True)
class Series:
    """One line of a chart: x, y (same length, NaN breaks the line), a label and a style
    (``color`` BGR 0-255, ``thickness`` in points)."""

    x: np.ndarray
    y: np.ndarray
    label: str
    color: tuple[int, int, int] = PALETTE[0]
    thickness: int = 2
    dashed: bool = False
    fill_to_bottom: bool = False


def _legend_below(ax, handles=None, labels=None, columns: int = 3) -> None:
    """The legend under the axes (never over the data), in rows of ``columns``."""
    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=min(columns, len(handles)),
                  frameon=False, fontsize=9)


def line_chart(path, series: list[Series], title: str, xlabel: str, ylabel: str,
               size=(900, 420), ylim: tuple[float, float] | None = None) -> Path:
    """A line chart: axes with units in the labels, a grid, the title, and the legend below the
    x label. ``size`` is the axes' area in pixels (width, height) before the legend is added."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(size[0] / DPI, size[1] / DPI))
    for s in series:
        x, y = np.asarray(s.x, float), np.asarray(s.y, float)
        if s.fill_to_bottom:
            ax.fill_between(x, y, np.nanmin(y) if np.isfinite(y).any() else 0.0, color=rgb(s.color), alpha=0.25,
                            linewidth=0)
        ax.plot(x, y, color=rgb(s.color), linewidth=max(0.8, 0.9 * s.thickness), linestyle="--" if s.dashed else "-",
                label=s.label)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_title(title, fontsize=11, loc="left")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, color="0.9")
    ax.margins(x=0)
    _legend_below(ax, columns=3)
    return _save(fig, path)


def bar_chart(path, groups: list[str], bars: dict[str, list[float]], title: str, ylabel: str,
              reference: tuple | list[tuple] | None = None, size=(760, 400)) -> Path:
    """Grouped bars: one group per label in ``groups``, one bar per key of ``bars`` with its value
    above it ("n/a" for NaN); optional horizontal reference lines ((value, label) or (value, label,
    BGR colour), or a list of them: the first solid, the others dashed). Legend below the axes."""
    plt = _pyplot()
    refs = [] if reference is None else ([reference] if isinstance(reference, tuple) else list(reference))
    refs = [(float(r[0]), str(r[1]), tuple(r[2]) if len(r) > 2 else BLACK) for r in refs]
    fig, ax = plt.subplots(figsize=(size[0] / DPI, size[1] / DPI))
    n_bars = max(1, len(bars))
    width = 0.8 / n_bars
    centres = np.arange(len(groups), dtype=float)
    for bi, (name, values) in enumerate(bars.items()):
        v = np.full(len(groups), np.nan)
        given = np.asarray(values, float)[: len(groups)]
        v[: len(given)] = given
        x = centres - 0.4 + (bi + 0.5) * width
        drawn = ax.bar(x, np.where(np.isfinite(v), v, 0.0), width * 0.92, color=rgb(PALETTE[bi % len(PALETTE)]),
                       label=name)
        ax.bar_label(drawn, labels=[f"{t:.1f}" if np.isfinite(t) else "n/a" for t in v], fontsize=8, padding=2)
    for i, (value, label, colour) in enumerate(refs):
        ax.axhline(value, color=rgb(colour), linewidth=1.2, linestyle="-" if i == 0 else "--", label=label)
    finite = np.array([t for vs in bars.values() for t in vs] + [r[0] for r in refs], float)
    finite = finite[np.isfinite(finite)]
    top = float(finite.max()) * 1.15 if finite.size and finite.max() > 0 else 1.0
    ax.set_ylim(min(0.0, float(finite.min())) if finite.size else 0.0, top)
    ax.set_xticks(centres, groups)
    ax.set_title(title, fontsize=11, loc="left")
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", color="0.9")
    ax.set_axisbelow(True)
    _legend_below(ax, columns=3)
    return _save(fig, path)


def scale_bar_length(span_m: float) -> float:
    """A round length (1, 2 or 5 x 10^k m) of at most a quarter of ``span_m``."""
    want = max(span_m, 1e-9) / 4.0
    mag = 10 ** np.floor(np.log10(want))
    return float(max(m * mag for m in (1, 2, 5) if m * mag <= want * (1 + 1e-9)))


def height_map(path, heights: np.ndarray, north0_m: float, east0_m: float, cell_m: float,
               title: str, paths: list[tuple[np.ndarray, str, tuple[int, int, int]]] = (),
               outlines: list[np.ndarray] = (), vmin: float | None = None, vmax: float | None = None,
               scale_px: int | None = None, notes: list[str] = ()) -> Path:
    """A height grid ``(rows = north cells, cols = east cells)`` as a colour image, north up, east
    right, axes in metres (north and east of the grid's origin ``north0_m``, ``east0_m``), unknown
    (NaN) cells light grey, a colour bar in metres (an end drawn as an arrow when cells lie
    beyond ``vmin``/``vmax``), flight paths ((N, 2) north/east arrays with a label and BGR colour),
    polygon outlines ((K, 2) north/east) and ``notes`` under the legend.

    The map panel's longer side is ``MAP_LONG_SIDE_IN`` inches whatever the area, so a 10 m and
    a 1 km map both come out readable; ``scale_px`` is accepted for the callers and not used."""
    plt = _pyplot()
    from matplotlib.patches import Patch

    heights = np.asarray(heights, float)
    rows, cols = heights.shape
    known = np.isfinite(heights)
    lo = vmin if vmin is not None else (float(np.nanmin(heights)) if known.any() else 0.0)
    hi = vmax if vmax is not None else (float(np.nanmax(heights)) if known.any() else 1.0)
    hi = hi if hi > lo else lo + 1.0
    below = bool(known.any() and np.nanmin(heights) < lo)
    above = bool(known.any() and np.nanmax(heights) > hi)
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[(below, above)]
    north_span, east_span = max(rows, 1) * cell_m, max(cols, 1) * cell_m
    scale = MAP_LONG_SIDE_IN / max(north_span, east_span)
    panel_w, panel_h = max(east_span * scale, 2.5), max(north_span * scale, 2.5)
    fig, ax = plt.subplots(figsize=(panel_w + 1.6, panel_h + 0.9))
    cmap = plt.get_cmap("viridis").with_extremes(bad=UNKNOWN_RGB)
    extent = (east0_m, east0_m + cols * cell_m, north0_m, north0_m + rows * cell_m)
    image = ax.imshow(np.ma.masked_invalid(heights), origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi,
                      interpolation="nearest")
    for poly in outlines:
        ring = np.vstack([np.asarray(poly, float), np.asarray(poly, float)[:1]])
        ax.plot(ring[:, 1], ring[:, 0], color="white", linewidth=2.5)
        ax.plot(ring[:, 1], ring[:, 0], color="black", linewidth=1.0)
    for p, label, colour in paths:
        p = np.asarray(p, float).reshape(-1, 2)
        ax.plot(p[:, 1], p[:, 0], color="white", linewidth=2.6)  # a halo keeps the path visible on any colour
        ax.plot(p[:, 1], p[:, 0], color=rgb(colour), linewidth=1.2, label=label)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title, fontsize=10, loc="left")
    bar = fig.colorbar(image, ax=ax, extend=extend, fraction=0.046, pad=0.03)
    bar.set_label("height (m)")
    bar.ax.yaxis.set_major_formatter("{x:g}")
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Patch(facecolor=UNKNOWN_RGB, edgecolor="0.5", label="unknown"))
    labels.append("unknown")
    _legend_below(ax, handles, labels, columns=4)
    if notes:  # under the legend, left-aligned with the axes
        ax.annotate("\n".join(notes), xy=(0.0, 0.0), xycoords=ax.get_legend(), xytext=(0, -4),
                    textcoords="offset points", fontsize=8, color="0.25", va="top", ha="left")
    return _save(fig, path)
