"""Rises and flat surfaces seen by dense optical flow (docs/mapper.md, "Rises seen by dense flow",
"Surfaces seen by dense flow").

The corner mapper measures a surface only where Harris corners stand out among the frame's
strongest. A face in shade, a mast against bright fields, a wall of dull render have texture, but
little contrast: their corners lose to the ground's, and the map learns of them metres before the
vehicle meets them. Dense optical flow needs texture, not contrast. Between the current frame and
one taken ``s`` frames earlier, both with the navigation's camera pose, the flow of each pixel of a
lattice gives a second line of sight to the same surface point, and the two lines give its range.

From those points the stage keeps two things. What the corners may miss and the law must not: a
cell whose top stands well above the ground around it in the same frame (a *rise*), seen so in
most of the last few frames. Such a cell gets a floor, the least the terrain there reaches
(docs/terrain.md, "Floors"), as a young corner feature's bound does. Heights are compared within
one frame, so the error a pair of navigation poses puts into every range of that pair (a few
centimetres of baseline, a few hundredths of a degree of attitude) moves a cell's top and its
ground together and cancels in the rise. And what the corners map only here and there: the
height of every cell whose points lie on one flat surface (docs/mapper.md, "Surfaces seen by
dense flow"), each the mean of a few frames' looks with that pair error in its variance, so the
ground between the corners has a height of its own.

The ranger is a stage of its own beside the corner mapper (:class:`FlowRanger`: navigation state
and image in, floors and surfaces out): it shares nothing with the mapper's features, so the service runs it in a
thread of its own on the other core, off the path from a frame to its setpoint.

Everything here is batched numpy and OpenCV on one grey frame; no I/O.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, fields

import cv2
import numpy as np

from companion.config import MapperConfig
from companion.method.geometry import CameraMount, PinholeCamera
from companion.method.mapper.features import as_gray
from companion.method.mapper.mapper import check_nav
from companion.method.mapper.projection import CameraPose
from companion.method.messages import NavState, TerrainFloors, TerrainPoints
from companion.method.terrain.grid import pack_key, unpack_key

# OpenCV's DIS optical flow, its fastest preset: 3.2-3.5 ms a 640 x 480 flow on one core of the
# development machine; the medium preset takes ten times as long, for ranges of the same order
# within 22 m of the mast's face (docs/quality/notes.md).
_DIS_PRESET = cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST
# A pair whose camera moved less than this has no parallax worth a flow (m).
_MIN_BASELINE_M = 0.3
# Parallax below this is indistinguishable from the flow's noise (rad): no range.
_MIN_PARALLAX_RAD = 0.002


def triangulate_midpoint(c1: np.ndarray, r1: np.ndarray, c2: np.ndarray, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range along each line of sight of the first camera to the point nearest both lines, and the
    parallax between the lines (docs/mapper.md, "Rises seen by dense flow").

    ``c1``, ``c2`` (3,): camera centres; ``r1``, ``r2`` (N, 3): unit directions of the two lines of
    sight of each point. The point ``c1 + a r1`` nearest the line ``c2 + t r2`` has, with
    ``b = c2 - c1`` and ``k = r1 . r2``::

        a = (r1 . b - k (r2 . b)) / (1 - k^2)

    (set the derivatives of ``|c1 + a r1 - c2 - t r2|^2`` in ``a`` and ``t`` to zero). Returns
    ``a`` (N,), NaN where the lines are parallel, and the parallax ``arccos k`` (N,) in radians."""
    b = np.asarray(c2, dtype=np.float64) - np.asarray(c1, dtype=np.float64)
    k = np.clip(np.einsum("ij,ij->i", r1, r2), -1.0, 1.0)
    den = 1.0 - k * k
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(den > 1e-15, (r1 @ b - k * (r2 @ b)) / den, np.nan)
    return a, np.arccos(k)


def range_sigma(range_m: np.ndarray, parallax_rad: np.ndarray, angle_sigma_rad: float) -> np.ndarray:
    """Standard deviation (m) of a triangulated range (N,) whose two lines of sight each carry an
    independent direction error of ``angle_sigma_rad``: ``sqrt(2) r sigma / parallax``.

    In the triangle of the two centres and the point, with the parallax ``alpha`` at the point, a
    turn ``d`` of the second line moves the point along the first by ``r2 d / sin(alpha)``, and a
    turn of the first moves it along itself by ``r1 d cos(alpha) / sin(alpha)`` (the sine rule); for
    the small parallaxes of a forward-moving camera ``r1 ~ r2 = r`` and ``sin(alpha) ~ alpha``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return math.sqrt(2.0) * np.asarray(range_m) * angle_sigma_rad / np.maximum(parallax_rad, 1e-12)


def cell_rises(north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray, cell_m: float,
               ground_radius_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell of ``cell_m`` holding two points or more: the index of its second highest point
    (its top, robust to one wild point), and how far that stands above the ground around it: the
    lowest of the median heights of the cells within ``ground_radius_m`` (the cell's own included).

    north_m, east_m, height_m: (N,) points of one frame. Returns ``top`` (C,) point indices,
    ``rise`` (C,) metres, ``cell_ij`` (C, 2) the cells' integer indices."""
    h = np.asarray(height_m, dtype=np.float64)
    if len(h) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2), np.int64)
    ci = np.floor(np.asarray(north_m) / cell_m).astype(np.int64)
    cj = np.floor(np.asarray(east_m) / cell_m).astype(np.int64)
    i0, j0 = int(ci.min()), int(cj.min())
    ni, nj = int(ci.max()) - i0 + 1, int(cj.max()) - j0 + 1
    flat = (ci - i0) * nj + (cj - j0)
    order = np.lexsort((h, flat))  # by cell, then height ascending
    fs, hs = flat[order], h[order]
    starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
    ends = np.r_[starts[1:], len(fs)]
    count = ends - starts
    median = np.full(ni * nj, np.inf, dtype=np.float32)
    median[fs[starts]] = hs[starts + (count - 1) // 2]
    r = int(math.floor(ground_radius_m / cell_m + 1e-9))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    ground = cv2.erode(median.reshape(ni, nj), disc, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf).reshape(-1)
    two = count >= 2
    top = order[ends[two] - 2]
    rise = h[top] - ground[flat[top]].astype(np.float64)
    return top, rise, np.column_stack([ci[top], cj[top]])


@dataclass(frozen=True, slots=True)
class RangedPoints:
    """The lattice points of one frame ranged by the flow, the pairs' points together (N rows):
    ``positions_ned_m`` (N, 3), ``range_m`` (N,) along ``rays_ned`` (N, 3), the unit lines of sight
    of the current frame, ``range_sigma_m`` (N,), ``parallax_rad`` (N,), ``pair`` (N,) the index of the pair's separation in
    ``FlowDepth.separations`` (0: the nearest)."""

    positions_ned_m: np.ndarray
    range_m: np.ndarray
    range_sigma_m: np.ndarray
    rays_ned: np.ndarray
    parallax_rad: np.ndarray
    pair: np.ndarray

    def __len__(self) -> int:
        return len(self.range_sigma_m)

    def select(self, keep: np.ndarray) -> "RangedPoints":
        """The rows where ``keep`` (N,) bool is True."""
        return RangedPoints(self.positions_ned_m[keep], self.range_m[keep], self.range_sigma_m[keep], self.rays_ned[keep],
                            self.parallax_rad[keep], self.pair[keep])

    @classmethod
    def empty(cls) -> "RangedPoints":
        z = np.zeros(0)
        return cls(np.zeros((0, 3)), z, z, np.zeros((0, 3)), z, np.zeros(0, np.int64))


_RANGED_FIELDS = tuple(f.name for f in fields(RangedPoints))


def flat_cells(north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray, cell_m: float, min_points: int,
               flat_m: float, min_neighbours: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells of one frame whose points lie on one flat surface (docs/mapper.md, "Surfaces seen
    by dense flow"): at least ``min_points`` points in the cell, their heights within ``flat_m`` of
    each other (second highest minus second lowest, robust to one wild point at each end), and at
    least ``min_neighbours`` of the eight neighbouring cells holding ``min_points`` or more with a
    median height within ``flat_m`` of the cell's, none farther. A wall's cell fails the first test
    (its points climb the face), the ground beside a wall or a roof's edge the second; a mast in a
    cell of ground points fails the first with two of its points.

    north_m, east_m, height_m: (N,) points of one frame. Returns ``cell_ij`` (C, 2) the flat cells'
    integer indices, ``median_m`` (C,) their median heights, ``members`` (N,) the index into those
    C cells of each point (-1: not in a flat cell)."""
    h = np.asarray(height_m, dtype=np.float64)
    none = (np.zeros((0, 2), np.int64), np.zeros(0), np.full(len(h), -1, np.int64))
    if len(h) == 0:
        return none
    ci = np.floor(np.asarray(north_m) / cell_m).astype(np.int64)
    cj = np.floor(np.asarray(east_m) / cell_m).astype(np.int64)
    i0, j0 = int(ci.min()) - 1, int(cj.min()) - 1
    ni, nj = int(ci.max()) - i0 + 2, int(cj.max()) - j0 + 2  # a border of empty cells
    flat = (ci - i0) * nj + (cj - j0)
    order = np.lexsort((h, flat))
    fs, hs = flat[order], h[order]
    starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]])
    ends = np.r_[starts[1:], len(fs)]
    count = ends - starts
    full = count >= max(min_points, 3)
    median = np.full(ni * nj, np.nan)
    lower, upper = (count - 1) // 2, count // 2
    median[fs[starts[full]]] = 0.5 * (hs[starts + lower] + hs[starts + upper])[full]
    spread = hs[np.maximum(ends - 2, starts)] - hs[np.minimum(starts + 1, ends - 1)]
    grid = median.reshape(ni, nj)
    n_near = np.zeros((ni, nj), np.int64)
    worst = np.zeros((ni, nj))
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            other = np.full((ni, nj), np.nan)
            other[max(di, 0):ni + min(di, 0), max(dj, 0):nj + min(dj, 0)] = \
                grid[max(-di, 0):ni - max(di, 0), max(-dj, 0):nj - max(dj, 0)]
            seen = np.isfinite(other) & np.isfinite(grid)
            n_near += seen
            worst = np.where(seen, np.maximum(worst, np.abs(other - grid)), worst)
    cells = fs[starts[full & (spread <= flat_m)]]
    ok = (n_near.reshape(-1)[cells] >= min_neighbours) & (worst.reshape(-1)[cells] <= flat_m)
    cells = cells[ok]
    if len(cells) == 0:
        return none
    index = np.full(ni * nj, -1, np.int64)
    index[cells] = np.arange(len(cells))
    ij = np.column_stack([cells // nj + i0, cells % nj + j0])
    return ij, median[cells], index[flat]


def _cell_medians(member: np.ndarray, values: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The (lower) median of ``values`` (N,) per cell ``member`` (N,) in 0..C-1, ``count`` (C,) > 0."""
    order = np.lexsort((values, member))
    starts = np.searchsorted(member[order], np.arange(len(count)))
    return values[order][starts + (count.astype(np.int64) - 1) // 2]


def surface_heights(ranged: RangedPoints, camera_alt_m: float, cfg: MapperConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's evidence of the flat surfaces its nearest pair ranged (docs/mapper.md, "Surfaces
    seen by dense flow"): per flat cell (:func:`flat_cells`) the median height of its points and
    that median's variance::

        v = (pi / 2) mean(sigma_z^2) / n  +  (d s)^2,   s^2 = ((sigma_b / r)^2 + sigma_theta^2) / alpha^2

    The first term is the median of ``n`` independent heights, each its range sigma times the
    vertical part of its line of sight. The second is the error the pair's poses put into every
    range of the frame at once. A point's range ``r`` is where the line of sight from the earlier
    camera meets this one's at the parallax ``alpha``: an error ``delta`` of that camera's centre
    across its line of sight moves the line by ``delta`` and the meeting point by ``delta / alpha``
    along this one's, a turn ``theta`` of that camera by ``r theta / alpha``; either scales the
    range by ``s`` (``delta / r`` and ``theta`` are the angles they turn the line by, seen from the
    point), and a range scaled by ``1 + s`` moves the point's height by ``s`` times its depth below
    the camera, ``d = h_cam - h``. ``sigma_b`` and ``sigma_theta`` are the navigation's errors between
    two frames a pair apart (``flow_pair_position_sigma_m``, ``flow_pair_attitude_sigma_deg``);
    ``r`` and ``alpha`` are the medians of the cell's points. Within one frame that second term is
    one error shared by the cells; from frame to frame it is independent, so a cell seen in ``k``
    frames knows its height to ``v / k``.

    Returns ``cell_ij`` (C, 2), ``height_m`` (C,), ``variance_m2`` (C,)."""
    near = ranged.select(ranged.pair == 0)
    if len(near) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
    X = near.positions_ned_m
    ij, median, member = flat_cells(X[:, 0], X[:, 1], -X[:, 2], cfg.flow_cell_m, cfg.flow_surface_min_points,
                                    cfg.flow_surface_flat_m)
    if len(median) == 0:
        return ij, median, np.zeros(0)
    inside = member >= 0
    m = member[inside]
    n = np.bincount(m, minlength=len(median)).astype(np.float64)
    sz2 = (near.range_sigma_m[inside] * near.rays_ned[inside, 2]) ** 2
    scatter = 0.5 * math.pi * np.bincount(m, weights=sz2, minlength=len(median)) / (n * n)
    parallax = _cell_medians(m, near.parallax_rad[inside], n)
    range_m = _cell_medians(m, near.range_m[inside], n)
    s2 = ((cfg.flow_pair_position_sigma_m / range_m) ** 2 + math.radians(cfg.flow_pair_attitude_sigma_deg) ** 2) / parallax**2
    depth = np.maximum(camera_alt_m - median, 0.0)
    return ij, median, scatter + depth * depth * s2


class SurfaceLooks:
    """Each cell's looks at its flat surface, ``looks`` frames' worth averaged before the map gets
    them (docs/mapper.md, "Surfaces seen by dense flow"). A frame's heights share one error of the
    pair's poses: one frame in twenty puts a whole swath of cells a metre too high (two of its
    sigmas), and a cell whose only evidence that is would hold the law a metre up until the next
    look. Averaged, ``k`` independent looks (the frames' errors are white from one measured frame
    to the next) give the information-weighted mean ``h = sum(h_i / v_i) / sum(1 / v_i)`` with the
    variance ``1 / sum(1 / v_i)``: the mean of three equal looks is off by a metre as rarely as one
    look is off by 1.7 m. Each look goes to the map once: a cell's sums start again after it is given. A cell
    not seen for ``2 looks`` measured frames is forgotten with what it held (it left the view)."""

    def __init__(self, looks: int):
        self.looks = max(int(looks), 1)
        self.clear()

    def clear(self) -> None:
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 2))  # sum 1/v, sum h/v
        self._count = np.zeros(0, np.int64)
        self._seen = np.zeros(0, np.int64)
        self._frame = 0

    def add(self, cell_ij: np.ndarray, height_m: np.ndarray, variance_m2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame's flat cells (:func:`surface_heights`) in; the cells that now hold ``looks``
        looks out, as (cell_ij (C, 2), mean height (C,), its variance (C,))."""
        self._frame += 1
        keep = self._seen >= self._frame - 2 * self.looks
        ij = np.asarray(cell_ij, dtype=np.int64).reshape(-1, 2)
        keys = np.concatenate([self._keys[keep], pack_key(ij[:, 0], ij[:, 1])])
        sums = np.concatenate([self._sums[keep], np.column_stack([1.0 / variance_m2, height_m / variance_m2])])
        count = np.concatenate([self._count[keep], np.ones(len(height_m), np.int64)])
        seen = np.concatenate([self._seen[keep], np.full(len(height_m), self._frame)])
        self._keys, where = np.unique(keys, return_inverse=True)
        self._sums = np.zeros((len(self._keys), 2))
        np.add.at(self._sums, where, sums)
        self._count = np.bincount(where, weights=count, minlength=len(self._keys)).astype(np.int64)
        self._seen = np.zeros(len(self._keys), np.int64)
        np.maximum.at(self._seen, where, seen)
        ready = self._count >= self.looks
        out_ij = np.column_stack(unpack_key(self._keys[ready]))
        info, info_h = self._sums[ready, 0], self._sums[ready, 1]
        self._sums[ready] = 0.0
        self._count[ready] = 0
        return out_ij, info_h / info, 1.0 / info


@dataclass(frozen=True, slots=True)
class FlowRises:
    """One frame's rises and surfaces: ``floors_ned_m`` (K, 3) the floor of each cell that rose in most
    of the last frames (its top moved ``floor_sigma`` range sigmas farther along its line of sight);
    ``surface_ij`` (C, 2), ``surface_height_m`` (C,), ``surface_variance_m2`` (C,) the flat cells'
    heights (:func:`surface_heights`; empty with ``flow_surface`` off); and what the frame measured:
    ``n_ranged`` points, ``n_rising`` cells rising in this frame."""

    floors_ned_m: np.ndarray
    surface_ij: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    surface_height_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    surface_variance_m2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_ranged: int = 0
    n_rising: int = 0

    @classmethod
    def empty(cls) -> "FlowRises":
        return cls(np.zeros((0, 3)))


class FlowDepth:
    """Dense flow against the frames ``flow_frames_apart`` back, ranges on a lattice, rises per cell
    (module docstring; docs/mapper.md, "Rises seen by dense flow"). One per camera stream."""

    def __init__(self, cfg: MapperConfig, camera: PinholeCamera):
        self.cfg = cfg
        self.camera = camera
        self.separations = tuple(sorted({int(s) for s in cfg.flow_frames_apart if int(s) > 0}))
        self._frames: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=max(self.separations, default=0) + 1)
        self._rising: deque[set[tuple[int, int]]] = deque(maxlen=max(cfg.flow_persist_window, 1))
        self._dis = cv2.DISOpticalFlow_create(_DIS_PRESET)
        self._lattice: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._lattice_shape: tuple[int, int] | None = None
        self._frame = 0  # frames seen since the last reset
        self._looks = SurfaceLooks(cfg.flow_surface_looks)

    def reset(self) -> None:
        """Forget the frames (a gap in the stream, a refused pose)."""
        self._frames.clear()
        self._rising.clear()
        self._looks.clear()
        self._frame = 0

    def _lattice_rays(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The lattice's pixel rows and columns and their camera-frame unit rays (N, 3)."""
        if self._lattice is None or self._lattice_shape != tuple(shape):
            step = self.cfg.flow_lattice_px
            vv, uu = np.mgrid[step // 2:shape[0]:step, step // 2:shape[1]:step]
            v, u = vv.ravel(), uu.ravel()
            self._lattice = (v, u, self._unit_rays(np.column_stack([u, v]).astype(np.float64)))
            self._lattice_shape = tuple(shape)
        return self._lattice

    def _unit_rays(self, uv_raw: np.ndarray) -> np.ndarray:
        """Unit rays (N, 3) in the camera frame through raw pixels (N, 2)."""
        return self.camera.ray(self.camera.undistort(uv_raw))

    def _remember(self, gray: np.ndarray, p_c: np.ndarray, R_nc: np.ndarray) -> None:
        """Keep the frame and its camera pose for the pairs of later frames."""
        self._frames.append((gray.copy(), np.asarray(p_c, dtype=np.float64).copy(), np.asarray(R_nc, dtype=np.float64).copy()))

    def ranged(self, gray: np.ndarray, p_c: np.ndarray, R_nc: np.ndarray) -> RangedPoints:
        """The lattice points of ``gray`` ranged against the stored frames, the pairs' points
        together. Stores the frame (with its camera centre ``p_c`` (3,) and attitude ``R_nc`` (3, 3))
        for later ones."""
        cfg, cam = self.cfg, self.camera
        H, W = gray.shape
        v, u, rays_c = self._lattice_rays(gray.shape)
        r1 = rays_c @ np.asarray(R_nc).T
        uv = np.column_stack([u, v]).astype(np.float64)
        angle_sigma = cfg.flow_pixel_sigma_px / cam.fx
        out: list[RangedPoints] = []
        for index, s in enumerate(self.separations):
            if len(self._frames) < s:
                continue
            g0, p0, R0 = self._frames[-s]
            if g0.shape != gray.shape or np.linalg.norm(p0 - p_c) < _MIN_BASELINE_M:
                continue  # a stream whose frame size changed, or a camera that hardly moved
            ahead = self._dis.calc(gray, g0, None)   # this frame -> the earlier one
            back = self._dis.calc(g0, gray, None)    # and back, for the consistency check
            f = ahead[v, u].astype(np.float64)
            uv0 = uv + f
            inside = cam.in_image(uv0)
            fb = back[np.clip(np.rint(uv0[:, 1]).astype(np.int64), 0, H - 1), np.clip(np.rint(uv0[:, 0]).astype(np.int64), 0, W - 1)]
            ok = inside & (np.hypot(f[:, 0] + fb[:, 0], f[:, 1] + fb[:, 1]) <= cfg.flow_max_fb_px)
            r0 = self._unit_rays(uv0) @ np.asarray(R0).T
            a, parallax = triangulate_midpoint(p_c, r1, p0, r0)
            sig = range_sigma(a, parallax, angle_sigma)
            with np.errstate(invalid="ignore"):
                ok &= (a >= cfg.flow_min_range_m) & (parallax >= _MIN_PARALLAX_RAD) & (sig <= cfg.flow_max_range_sigma_m)
            out.append(RangedPoints(p_c + a[ok, None] * r1[ok], a[ok], sig[ok], r1[ok], parallax[ok],
                                    np.full(int(np.count_nonzero(ok)), index, np.int64)))
        self._remember(gray, p_c, R_nc)
        if not out:
            return RangedPoints.empty()
        return RangedPoints(*(np.concatenate([getattr(r, f) for r in out]) for f in _RANGED_FIELDS))

    def will_measure(self) -> bool:
        """Whether the next frame given to :meth:`step` is one the flow measures."""
        return self._frame % self.cfg.flow_every_frames == 0

    def step(self, gray: np.ndarray, p_c: np.ndarray, R_nc: np.ndarray) -> FlowRises:
        """One frame: its ranged points (:meth:`ranged`), the cells rising more than
        ``flow_min_rise_m`` above the ground around them (:func:`cell_rises`), and a floor for each
        that rose in at least ``flow_persist_frames`` of the last ``flow_persist_window`` frames
        measured; with ``flow_surface``, the flat cells that now hold ``flow_surface_looks`` looks
        (:class:`SurfaceLooks`). Only every ``flow_every_frames``-th frame is measured; the others
        are stored for later pairs and give nothing."""
        cfg = self.cfg
        measured = self.will_measure()
        self._frame += 1
        if not measured:
            self._remember(gray, p_c, R_nc)
            return FlowRises.empty()
        ranged = self.ranged(gray, p_c, R_nc)
        pts, sig, rays = ranged.positions_ned_m, ranged.range_sigma_m, ranged.rays_ned
        top, rise, ij = cell_rises(pts[:, 0], pts[:, 1], -pts[:, 2], cfg.flow_cell_m, cfg.flow_ground_radius_m)
        up = rise > cfg.flow_min_rise_m
        cells = [tuple(c) for c in ij[up].tolist()]
        self._rising.append(set(cells))
        votes = np.array([sum(c in seen for seen in self._rising) for c in cells], dtype=np.int64)
        held = top[up][votes >= cfg.flow_persist_frames]
        # the lower end of the top's range interval: farther along a line of sight that looks down
        floors = pts[held] + (cfg.floor_sigma * sig[held])[:, None] * rays[held]
        floors = np.where((rays[held, 2] > 0)[:, None], floors, pts[held])
        if not cfg.flow_surface:
            return FlowRises(floors, n_ranged=len(pts), n_rising=len(cells))
        ij_s, h_s, v_s = self._looks.add(*surface_heights(ranged, -float(p_c[2]), cfg))
        return FlowRises(floors, ij_s, h_s, v_s, n_ranged=len(pts), n_rising=len(cells))


@dataclass(frozen=True, slots=True)
class FlowStep:
    """What :meth:`FlowRanger.step` gives for one frame: ``floors``, the rising cells' floors as rows
    no feature owns (feature id -1, docs/terrain.md, "A bound no feature owns"), for
    ``TerrainGrid.raise_floors``; ``surface``, one height per flat cell with its variance
    (:func:`surface_heights`, at the cell's centre, feature id -1), for ``TerrainGrid.insert`` with
    ``keep_floors``; ``n_ranged`` lattice points ranged, ``n_rising`` cells rising in this frame;
    ``measured``: whether this frame was one the flow measured (every ``flow_every_frames``-th);
    ``refused``: why the navigation state was not used ("" when it was)."""

    floors: TerrainFloors
    surface: TerrainPoints = field(default_factory=lambda: TerrainPoints.empty(0.0))
    n_ranged: int = 0
    n_rising: int = 0
    measured: bool = False
    refused: str = ""


class FlowRanger:
    """The dense-flow stage: ``step(nav, image) -> FlowStep``, one per camera stream, beside the
    corner mapper (module docstring). A navigation state the mapper would refuse (not finite, a
    covariance not symmetric positive semi-definite) is refused here too, and the stored frames are
    forgotten: a pair across it would range with a pose nobody trusts."""

    def __init__(self, cfg: MapperConfig, camera: PinholeCamera, mount: CameraMount):
        if cfg.flow_persist_frames > cfg.flow_persist_window:
            raise ValueError(f"mapper.flow_persist_frames ({cfg.flow_persist_frames}) must not exceed "
                             f"mapper.flow_persist_window ({cfg.flow_persist_window}): no cell could ever get a floor")
        self.mount = mount
        self.depth = FlowDepth(cfg, camera)

    def reset(self) -> None:
        """Forget the stored frames and the cells' votes (a gap in the stream, a map reset)."""
        self.depth.reset()

    def will_measure(self) -> bool:
        """Whether the next frame given to :meth:`step` is one the flow measures (a stored frame
        costs a copy; a measured one its flows)."""
        return self.depth.will_measure()

    def step(self, nav: NavState, image: np.ndarray) -> FlowStep:
        """Range ``image`` ((H, W) grey or (H, W, 3) BGR uint8) taken at ``nav`` against the stored
        frames and return the floors of the cells that rose (:meth:`FlowDepth.step`)."""
        t_s = float(nav.t_s) if math.isfinite(nav.t_s) else 0.0
        reason = check_nav(nav)
        if reason:
            self.depth.reset()
            return FlowStep(TerrainFloors.empty(t_s), refused=reason)
        pose = CameraPose.from_nav(nav.position_ned_m, nav.quaternion_wxyz, self.mount)
        gray = as_gray(np.asarray(image))  # a malformed image raises before any state changes
        measured = self.will_measure()
        rises = self.depth.step(gray, pose.p_c, pose.R_nc)
        floors = TerrainFloors(t_s, rises.floors_ned_m, feature_ids=np.full(len(rises.floors_ned_m), -1, dtype=np.int64))
        return FlowStep(floors, self._surface_points(t_s, rises), n_ranged=rises.n_ranged, n_rising=rises.n_rising,
                        measured=measured)

    def _surface_points(self, t_s: float, rises: FlowRises) -> TerrainPoints:
        """The flat cells' heights as points at the cells' centres, their horizontal sigma a tenth
        of a cell (each stays in its own cell: docs/terrain.md, "Fusion", step 2)."""
        n = len(rises.surface_height_m)
        if n == 0:
            return TerrainPoints.empty(t_s)
        c = self.depth.cfg.flow_cell_m
        pos = np.column_stack([(rises.surface_ij + 0.5) * c, -rises.surface_height_m])
        cov = np.zeros((n, 3, 3))
        cov[:, 0, 0] = cov[:, 1, 1] = (0.1 * c) ** 2
        cov[:, 2, 2] = rises.surface_variance_m2
        return TerrainPoints(t_s, pos, cov, np.full(n, -1, dtype=np.int64))
