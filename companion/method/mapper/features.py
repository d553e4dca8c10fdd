"""Harris corner detector with bins, a per-bin cap and a minimum separation (seed 000, II.C).

The paper: "a modified Harris corner detector ... partitions the image into bins, and sets a
maximum number of features in each bin. Also, a minimum distance between features can be set.
The feature locations are passed to the mapping algorithm in order of their Harris corner
score, up to a maximum number."

Pipeline for one grey frame (``H x W``, ``uint8``):

1. ``harris_response``: OpenCV's Harris response ``R = det(M) - k tr(M)^2`` per pixel.
2. ``candidate_maxima``: 3x3 local maxima of ``R`` above ``max(quality * R_best, floor)``,
   inside the valid region (image edges, a caller's mask and black borders eroded by the
   margin). One image-wide pass finds the pixels above the threshold (a few percent); the
   local-maximum test then runs on those only. ``__call__`` looks first above a higher level set
   by the last frame (``maxima_above``; the strongest candidates are the same) and takes all of
   them only when those are too few.
3. ``refine_corners``: sub-pixel corner positions of the strongest candidates (OpenCV's
   ``cornerSubPix``, Förstner's gradient-orthogonality least squares); a corner that moves out
   of the valid region is dropped.
4. ``select_features`` on the refined positions: in descending score order, the greedy
   minimum-distance suppression (a feature is dropped when a stronger *kept* feature lies
   closer than ``min_distance_px``, across bin borders too), then at most ``per_bin`` per bin,
   then at most ``max_detections``. Every rule holds for what is returned.

Coordinates are raw pixels, ``x`` = column, ``y`` = row, pixel centres at integers (OpenCV's
and :class:`companion.geometry.PinholeCamera`'s convention).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.config import MapperConfig

__all__ = [
    "HarrisDetector",
    "as_gray",
    "black_border_depths",
    "black_border_valid",
    "detect_corners",
    "detect_edgels",
    "refine_corners",
    "select_features",
    "select_ordered",
    "strongest",
    "suppress_within",
]

SOBEL_APERTURE = 3  # cornerHarris' derivative kernel; the response at a pixel sees block//2 + 1 around it
# cornerSubPix: at most 3 iterations or a step below 0.05 px (measured: more buys < 0.005 px)
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 3, 0.05)

# The next frame looks for candidates above this fraction of the response of the weakest candidate
# refined in this one. Measured on the rendered flight at 50 features: that response changes by at
# most 15 % from frame to frame, and 0.7 leaves 1.4 times the candidates a frame refines (0.5: 1.8
# times, 20 us slower; 0.85: two frames in 300 had to look again). A frame whose response drops
# more than that looks again at all candidates: slower, the same result.
LEVEL_FRACTION = 0.7

_EMPTY_UV = np.zeros((0, 2))
_EMPTY_SCORE = np.zeros(0)


# --------------------------------------------------------------------------------------------
# Input checking
# --------------------------------------------------------------------------------------------


def as_gray(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Grey ``uint8 (H, W)`` from a grey ``(H, W)`` / ``(H, W, 1)`` or BGR ``(H, W, 3)`` ``uint8``
    image. Anything else raises :class:`ValueError` naming what is wrong."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (8-bit grey or BGR), got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        if image.shape[0] == 0 or image.shape[1] == 0:
            raise ValueError(f"image is empty, shape {image.shape}")
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY, dst=out)
    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) grey or (H, W, 3) BGR, got shape {image.shape}")
    if image.size == 0:
        raise ValueError(f"image is empty, shape {image.shape}")
    return np.ascontiguousarray(image)


def _as_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A caller's validity mask (non-zero = usable) as ``uint8 (H, W)`` 0/255."""
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask shape {mask.shape} does not match the image shape {shape}")
    if not (mask.dtype == bool or np.issubdtype(mask.dtype, np.integer)):
        raise ValueError(f"mask must be bool or integer (non-zero = usable), got dtype {mask.dtype}")
    return np.where(mask != 0, np.uint8(255), np.uint8(0))


def effective_margin(cfg: MapperConfig, border_px: int) -> int:
    """Margin (px) kept from image edges and masked or black regions: ``border_px``, but never
    less than the detector's own reach (the Harris window and the refinement window), so that
    nothing outside the valid region shapes a returned corner."""
    if border_px < 0:
        raise ValueError(f"border_px must be >= 0, got {border_px}")
    reach = max(cfg.harris_block_size // 2 + SOBEL_APERTURE // 2, cfg.subpix_window_px + 1)
    return max(int(np.ceil(border_px)), reach)


# --------------------------------------------------------------------------------------------
# Valid region
# --------------------------------------------------------------------------------------------


def _erode(valid: np.ndarray, margin: int) -> np.ndarray:
    """Pixels with no invalid pixel in the ``(2 margin + 1)^2`` box around them (uint8 0/255).
    The image edge itself is handled separately (OpenCV's erosion ignores outside pixels)."""
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * margin + 1, 2 * margin + 1))
    return cv2.erode(valid, kernel)


def _window_max(a: np.ndarray, margin: int) -> np.ndarray:
    """Sliding maximum of a non-negative 1-D integer array over ``[i - margin, i + margin]``
    (0 outside), by a 1-D grey dilation."""
    col = a.astype(np.float32).reshape(-1, 1)
    kernel = np.ones((2 * margin + 1, 1), np.uint8)
    out = cv2.dilate(col, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out.reshape(-1).astype(np.int64)


def black_border_depths(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Depth of the black (value 0) border seen from each side of the image, per line:
    ``left (H,)``, ``right (H,)``, ``top (W,)``, ``bottom (W,)`` (0 = no border on that line), or
    ``None`` when no edge pixel is black.

    A black border is a zero pixel reachable from the image edge along its row or its column
    through zero pixels only (undistorted frames, fisheye circles, letterboxing): in row ``y``
    the pixels ``x < left[y]`` and ``x > W - 1 - right[y]``, in column ``x`` the pixels
    ``y < top[x]`` and ``y > H - 1 - bottom[x]``. Black pixels inside the picture (a shadow, a
    dark window) are texture, not border.
    """
    H, W = gray.shape
    # (count_nonzero == length is .all() at a third of its cost)
    if (np.count_nonzero(gray[0]) == W and np.count_nonzero(gray[-1]) == W and np.count_nonzero(gray[:, 0]) == H
            and np.count_nonzero(gray[:, -1]) == H):
        return None  # no zero on the image edge: no border to reach (the common case, cheap)
    # whole-row scans only: a row-wise argmax on a bool array stops at the first True, so
    # right, top and bottom are read as rows of flipped / transposed copies
    T = cv2.transpose(gray)
    return _zeros_before_first_nonzero(gray), _zeros_before_first_nonzero(cv2.flip(gray, 1)), \
        _zeros_before_first_nonzero(T), _zeros_before_first_nonzero(cv2.flip(T, 1))


def _zeros_before_first_nonzero(lines: np.ndarray) -> np.ndarray:
    """Per row of ``lines (k, n)``, the count of zeros before its first non-zero pixel (``n``
    for an all-zero row)."""
    nz = lines != 0
    first = nz.argmax(axis=1)
    first[~nz[np.arange(len(first)), first]] = lines.shape[1]
    return first


def black_border_valid(depths, shape: tuple[int, int], margin: int, out: np.ndarray | None = None) -> np.ndarray | None:
    """Valid-pixel mask (``uint8 (H, W)``, non-zero = usable) outside a black border given by
    :func:`black_border_depths`, or ``None`` when the border is thinner than the edge margin
    (which is applied anyway).

    A pixel is valid when no border pixel lies in the ``(2 margin + 1)^2`` box around it, so
    row ``y`` is valid on ``[x_lo[y], x_hi[y]]`` with ``x_lo`` = the deepest left border within
    ``+-margin`` rows plus the margin (likewise ``x_hi``, and ``y_lo``, ``y_hi`` per column); the
    mask is the intersection of the row and column intervals."""
    H, W = shape
    left, right, top, bottom = depths
    x_lo = _window_max(left, margin) + margin
    x_hi = W - 1 - margin - _window_max(right, margin)
    y_lo = _window_max(top, margin) + margin
    y_hi = H - 1 - margin - _window_max(bottom, margin)
    if x_lo.max() <= margin and x_hi.min() >= W - 1 - margin and y_lo.max() <= margin and y_hi.min() >= H - 1 - margin:
        return None
    if out is None:
        out = np.empty((H, W), np.uint8)
    valid = out.view(bool)
    tmp = np.empty((H, W), bool)
    xs = np.arange(W, dtype=np.int32)[None, :]
    ys = np.arange(H, dtype=np.int32)[:, None]
    np.greater_equal(xs, x_lo.astype(np.int32)[:, None], out=valid)
    valid &= np.less_equal(xs, x_hi.astype(np.int32)[:, None], out=tmp)
    valid &= np.greater_equal(ys, y_lo.astype(np.int32)[None, :], out=tmp)
    valid &= np.less_equal(ys, y_hi.astype(np.int32)[None, :], out=tmp)
    return out


# --------------------------------------------------------------------------------------------
# Selection: greedy minimum distance, per-bin cap, maximum count
# --------------------------------------------------------------------------------------------


def _close_pairs(xy: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs ``(i, j)``, ``i < j``, of finite points ``xy (K, 2)`` closer than ``d``: by a sweep
    along ``x`` for the few hundred points of a frame at 50 features (fewer NumPy calls), through
    a grid of cells for more (fewer pairs to test). Points that are not finite are close to nothing."""
    if not math.isfinite(xy.sum()):  # (a finite sum: every point finite) a point with no position is close to nothing
        idx = np.flatnonzero(np.isfinite(xy).all(axis=1))
        src, dst = _close_pairs(xy[idx], d) if len(idx) else (idx, idx)
        return idx[src], idx[dst]
    # the sweep tests about K d / (x extent) pairs per point (spread points)
    if len(xy) * d <= _SWEEP_MAX_PAIRS_PER_POINT * (float(xy[:, 0].max()) - float(xy[:, 0].min())):
        return _close_pairs_by_sweep(xy, d)
    return _close_pairs_by_grid(xy, d)


# Past this many pairs per point the grid's fixed calls cost less than the sweep's pairs
# (measured at 10 px on 640 x 480: the same cost near 400-550 points, 6-9 pairs each).
_SWEEP_MAX_PAIRS_PER_POINT = 6


def _close_pairs_by_sweep(xy: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_close_pairs` of finite points ``xy (K, 2)``: with the points sorted by ``x``, each
    point's candidates are the run of points after it less than ``d`` further along ``x``
    (``searchsorted``); the exact distance test keeps the close ones. When the runs are long
    (many points, or points crowded along ``x``), :func:`_close_pairs_by_grid` instead."""
    if len(xy) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    x, y = xy[:, 0], xy[:, 1]
    order = np.argsort(x)  # (any order of equal x: the set of pairs is the same)
    xs = x[order]
    # a window a hair wider than d (the exact test decides), wider than any rounding of xs + d
    width = d + 1e-9 * (d + abs(float(xs[0])) + abs(float(xs[-1])))
    count = np.searchsorted(xs, xs + width, side="left") - np.arange(1, len(xs) + 1)  # (>= 0)
    if int(count.sum()) > 2 * _SWEEP_MAX_PAIRS_PER_POINT * len(xs):  # crowded along x after all
        return _close_pairs_by_grid(xy, d)
    a = np.repeat(np.arange(len(xs)), count)  # sorted positions of each pair, b > a
    b = a + 1 + (np.arange(a.size) - np.repeat(np.cumsum(count) - count, count))
    i, j = order[a], order[b]
    dx, dy = x[i] - x[j], y[i] - y[j]
    # squares are cheaper than hypot, but d * d underflows for absurdly small d
    close = (dx * dx + dy * dy < d * d if d > 1e-100 else np.hypot(dx, dy) < d).nonzero()[0]
    i, j = i[close], j[close]
    return np.minimum(i, j), np.maximum(i, j)


def _close_pairs_by_grid(xy: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_close_pairs` of finite points ``xy (K, 2)``.

    The points are binned into square cells of side ``c >= d``, so two points closer than ``d``
    are in the same or adjacent cells. The cells are numbered row by row and counted, so the
    points of the three cells ``cx - 1 .. cx + 1`` of a row are one run of the points sorted by
    cell, found by two look-ups in the running count: each point meets only the points of its
    3 x 3 cells (a few), not all ``K``."""
    x, y = xy[:, 0], xy[:, 1]
    x0, y0 = float(x.min()), float(y.min())
    # cells no smaller than d, and at most 250 per axis (plus a spare one each side): the count
    # table stays small whatever the spread of the points, and a cell number fits 16 bits
    c = max(d, (float(x.max()) - x0) / _CELLS_PER_AXIS, (float(y.max()) - y0) / _CELLS_PER_AXIS)
    cxy = ((xy - (x0, y0)) / c).astype(np.intp) + 1
    cx, cy = cxy[:, 0], cxy[:, 1]
    ncx = int(cx.max()) + 2
    cell = cy * ncx + cx
    order = np.argsort(cell.astype(np.uint16), kind="stable")  # (16-bit keys: a radix sort, 3x faster)
    run_start = np.zeros(ncx * (int(cy.max()) + 2) + 1, np.intp)  # points in cells before each cell
    np.cumsum(np.bincount(cell, minlength=len(run_start) - 1), out=run_start[1:])
    # for each point, the rows cy - 1, cy, cy + 1: first cell cx - 1, three cells long (3K,)
    first_cell = (cell[None, :] + np.array([[-ncx - 1], [-1], [ncx - 1]])).reshape(-1)
    start = run_start[first_cell]
    count = run_start[first_cell + 3] - start
    src = np.repeat(np.arange(3 * len(xy)) % len(xy), count)
    first = np.cumsum(count) - count
    dst = order[np.arange(src.size) - np.repeat(first - start, count)]
    keep = (src < dst).nonzero()[0]  # indices, then gathers (faster than boolean indexes)
    src, dst = src[keep], dst[keep]
    dx, dy = x[src] - x[dst], y[src] - y[dst]
    # squares are cheaper than hypot, but d * d underflows for absurdly small d
    close = (dx * dx + dy * dy < d * d if d > 1e-100 else np.hypot(dx, dy) < d).nonzero()[0]
    return src[close], dst[close]


_CELLS_PER_AXIS = 250  # (250 + 3)^2 cell numbers < 2^16


def suppress_within(xy: np.ndarray, d: float) -> np.ndarray:
    """Greedy minimum-distance suppression of points ``xy (K, 2)`` given in descending score
    order: point ``j`` is kept unless a *kept* point ``i < j`` lies closer than ``d``.
    Returns a bool ``(K,)`` mask, identical to the sequential greedy loop.

    The sequential loop is replaced by rounds over the conflict pairs: a point whose stronger
    neighbours are all dropped is kept, a point with a kept stronger neighbour is dropped, the
    rest wait. Each round decides at least the strongest undecided point; in practice a few
    rounds decide all."""
    K = len(xy)
    if K == 0 or d <= 0:
        return np.ones(K, bool)
    hi, lo = _close_pairs(xy, d)
    challenged = np.zeros(K, bool)
    challenged[lo] = True
    kept = ~challenged  # no stronger point nearby: kept whatever happens
    dropped = np.zeros(K, bool)
    for _ in range(K):  # bounded: each round decides at least the strongest undecided point
        undecided = ~(kept | dropped)
        if not undecided.any():
            break
        blocked = np.zeros(K, bool)
        blocked[lo[kept[hi]]] = True
        waiting = np.zeros(K, bool)
        waiting[lo[undecided[hi]]] = True
        dropped |= undecided & blocked
        kept |= undecided & ~(blocked | waiting)
    return kept


def _bin_rank(xy: np.ndarray, width: int, height: int, bins_x: int, bins_y: int) -> np.ndarray:
    """Rank ``(K,)`` of each point within its bin (0 = strongest), points in descending score
    order: the running count of earlier points in the same bin."""
    bx = np.minimum((xy[:, 0] * (bins_x / width)).astype(np.int64), bins_x - 1)
    by = np.minimum((xy[:, 1] * (bins_y / height)).astype(np.int64), bins_y - 1)
    b = by * bins_x + bx  # coordinates are >= 0 inside the image
    # stable: score order inside each bin (16-bit keys, the usual case, are radix-sorted: 3x faster)
    order = np.argsort(b.astype(np.uint16) if bins_x * bins_y <= 1 << 16 else b, kind="stable")
    sb = b[order]
    new_group = np.empty(len(sb), bool)
    new_group[:1] = True
    np.not_equal(sb[1:], sb[:-1], out=new_group[1:])
    # index where each point's group starts, carried forward over the group
    group_start = np.maximum.accumulate(np.where(new_group, np.arange(len(sb)), 0))
    rank = np.empty(len(b), np.int64)
    rank[order] = np.arange(len(sb)) - group_start
    return rank


def strongest(score: np.ndarray, T: int) -> np.ndarray:
    """Indices of the ``T`` highest scores, strongest first, ties in index order: exactly
    ``argsort(-score, kind="stable")[:T]``, by a partial sort (frames of dense texture give ten
    thousand candidates of which a few hundred are ever looked at)."""
    if T >= len(score):
        return np.argsort(-score, kind="stable")
    neg = -score
    kth = np.partition(neg, T - 1)[T - 1]
    top = np.flatnonzero(neg <= kth)  # every tie of the T-th score, in index order
    return top[np.argsort(neg[top], kind="stable")][:T]


def select_ordered(xy: np.ndarray, cfg: MapperConfig, width: int, height: int) -> np.ndarray:
    """One pass of the rule over points ``xy (K, 2)`` already in descending score order:
    indices (ascending) of the greedy minimum distance, then at most ``per_bin`` per bin, then
    at most ``max_detections``."""
    keep = np.flatnonzero(suppress_within(xy, cfg.min_distance_px))
    keep = keep[_bin_rank(xy[keep], width, height, cfg.bins_x, cfg.bins_y) < cfg.per_bin]
    return keep[: cfg.max_detections]


def select_features(
    xy: np.ndarray, cfg: MapperConfig, width: int, height: int, score: np.ndarray | None = None
) -> np.ndarray:
    """Indices of the features to pass on (seed 000, II.C), strongest first: in descending score
    order, the greedy minimum distance, then at most ``per_bin`` per bin, then at most
    ``max_detections``.

    ``xy (K, 2)``: points; ``score (K,)``: their scores, or ``None`` when ``xy`` is already in
    descending score order (ties: the lower index is stronger).

    The greedy decisions for the strongest ``T`` points do not depend on weaker ones, so the
    work starts on the strongest few and takes more only when they yield too few features."""
    K = len(xy)
    T = min(K, _first_batch(cfg))
    while True:
        order = np.arange(T) if score is None else strongest(score, T)
        keep = select_ordered(xy[order], cfg, width, height)
        if len(keep) >= cfg.max_detections or T == K:
            return order[keep]
        T = min(K, 4 * T)


def _first_batch(cfg: MapperConfig) -> int:
    """How many of the strongest candidates to look at first (usually enough to fill)."""
    return max(2 * cfg.max_detections, 64)


# --------------------------------------------------------------------------------------------
# Sub-pixel refinement
# --------------------------------------------------------------------------------------------


def refine_corners(gray: np.ndarray, xy0: np.ndarray, window: int) -> np.ndarray:
    """Sub-pixel corner positions ``(N, 2)`` float64 near integer pixels ``xy0 (N, 2)``.

    OpenCV's ``cornerSubPix`` (Förstner): around a corner ``q`` every image gradient ``g_i`` at
    pixel ``p_i`` is orthogonal to ``p_i - q`` or zero, so ``q`` solves
    ``sum w g g^T q = sum w g g^T p`` over a ``(2 window + 1)^2`` patch, iterated with the patch
    re-centred. Needed because the Harris peak of a blurred L corner sits ~1-2 px inside it.
    A point that would leave its window is left where it was (OpenCV's rule).
    """
    pts = np.array(xy0, dtype=np.float32).reshape(-1, 1, 2)  # a copy: refined in place
    cv2.cornerSubPix(gray, pts, (window, window), (-1, -1), _SUBPIX_CRITERIA)
    return pts.reshape(-1, 2).astype(np.float64)


# --------------------------------------------------------------------------------------------
# The detector
# --------------------------------------------------------------------------------------------


class HarrisDetector:
    """Binned Harris detector for frames of one size; callable ``detector(image) -> (uv, score)``.

    Buffers (response, dilation, candidate mask), the eroded static mask and the margins are
    prepared once here; a call allocates only what depends on the frame's content. The buffers
    make a detector single-threaded: one per stream and thread.

    Parameters: ``cfg`` (``max_detections``, ``bins_x``, ``bins_y``, ``per_bin``,
    ``min_distance_px``, ``harris_k``, ``harris_block_size``, ``harris_quality``,
    ``harris_min_response``, ``subpix_window_px``); frame ``width`` and ``height`` (px);
    ``border_px`` kept from the image edges and from masked or black-border regions; optional
    static ``mask (H, W)`` (non-zero = usable), e.g. a vignetting or airframe mask.
    """

    def __init__(self, cfg: MapperConfig, width: int, height: int, border_px: int = 0, mask: np.ndarray | None = None):
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"frame size must be positive, got {width}x{height}")
        self.cfg = cfg
        self.width, self.height = int(width), int(height)
        self.border_px = border_px
        self.margin = effective_margin(cfg, border_px)
        shape = (self.height, self.width)
        self._gray = np.empty(shape, np.uint8)  # BGR -> grey target
        self._response = np.empty(shape, np.float32)
        self._border_valid = np.empty(shape, np.uint8)
        self._border_depths: tuple[np.ndarray, ...] | None = None  # last black border seen
        self._border_mask: np.ndarray | None = None
        self._above = np.zeros(shape, bool)  # pixels above the threshold
        self._static_valid = None
        if mask is not None:
            valid = _erode(_as_mask(mask, shape), self.margin)
            m = self.margin  # the edge margin too, so that the frame's best response is a valid one
            valid[:m], valid[self.height - m :], valid[:, :m], valid[:, self.width - m :] = 0, 0, 0, 0
            self._static_valid = valid
        # Image-edge margin for the sub-pixel positions: in_image semantics (u >= border_px).
        self._edge = float(border_px)
        self.n_candidates = 0  # local maxima examined in the last frame (diagnostics)
        self._first_batch = _first_batch(cfg)  # strongest candidates refined first (adapted per frame)
        self._level = 0.0  # response above which the candidates are looked for first (adapted per frame)

    # -- pipeline steps, in order -------------------------------------------------------------

    def harris_response(self, gray: np.ndarray) -> np.ndarray:
        """``R = det(M) - k tr(M)^2`` per pixel, float32 ``(H, W)`` (OpenCV, 8-bit scaling)."""
        return cv2.cornerHarris(gray, self.cfg.harris_block_size, SOBEL_APERTURE, self.cfg.harris_k, dst=self._response)

    def valid_region(self, gray: np.ndarray) -> np.ndarray | None:
        """Valid-pixel mask (non-zero = usable) from the static mask and any black border, or
        ``None`` when only the image-edge margin applies."""
        depths = black_border_depths(gray)
        if depths is None:
            return self._static_valid
        # An undistorted stream has the same border in every frame: reuse the last mask.
        if self._border_depths is not None and all(np.array_equal(a, b) for a, b in zip(depths, self._border_depths)):
            return self._border_mask
        border = black_border_valid(depths, (self.height, self.width), self.margin, out=self._border_valid)
        if border is not None and self._static_valid is not None:
            border = cv2.bitwise_and(border, self._static_valid, dst=border)
        self._border_depths = depths
        self._border_mask = self._static_valid if border is None else border
        return self._border_mask

    def response_threshold(self, R: np.ndarray, valid: np.ndarray | None) -> float | None:
        """The corner threshold ``max(quality * R_best, floor)`` of this frame, with ``R_best`` the
        best response inside the valid region; ``None`` when no pixel can pass it."""
        m, H, W = self.margin, self.height, self.width
        if valid is None:
            best = cv2.minMaxLoc(R[m : H - m, m : W - m])[1]
        else:
            best = cv2.minMaxLoc(R, valid)[1]
        threshold = max(self.cfg.harris_quality * best, self.cfg.harris_min_response)
        if not best > 0.0 or best < threshold:
            return None
        return threshold

    def candidate_maxima(self, R: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Flat pixel indices ``(K,)`` (``y * W + x``) and float32 responses ``(K,)`` of the 3x3
        local maxima of ``R`` above the threshold inside the valid region, in raster order."""
        threshold = self.response_threshold(R, valid)
        if threshold is None:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        return self.maxima_above(R, valid, threshold)

    def maxima_above(self, R: np.ndarray, valid: np.ndarray | None, level: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`candidate_maxima` with responses strictly above ``level`` (>= the threshold):
        exactly the frame's candidates whose response exceeds ``level``, in raster order."""
        m, H, W = self.margin, self.height, self.width
        # Strictly above the level (so a flat response, R == threshold == 0, is never a corner),
        # in float32 as R is, outside the top and bottom margins.
        above = self._above
        np.greater(R, np.float32(level), out=above)
        above[:m] = False
        above[H - m :] = False
        flat = above.reshape(-1).nonzero()[0]  # raster order
        # 3x3 local maximum: R >= each of the 8 neighbours. Left and right first (about two
        # thirds of the pixels above the level fail those), without a look-up: a neighbour
        # below the level is below R here, and one above it is the next set pixel in raster
        # order. Then the other six on the rest. Every neighbour index is inside the frame (rows
        # m..H-m-1, m >= 2); a pixel in the side margins may compare with a pixel of the next or
        # previous row and is dropped below anyway.
        Rf = R.reshape(-1)
        value = Rf[flat]
        keep = np.ones(len(flat), bool)
        run = flat[1:] == flat[:-1] + 1  # pixel k + 1 is pixel k's right neighbour
        keep[1:] &= ~run | (value[1:] >= value[:-1])
        keep[:-1] &= ~run | (value[:-1] >= value[1:])
        # (indices of the kept, then a gather: a boolean index over an irregular mask is slower)
        kept = keep.nonzero()[0]
        flat, value = flat[kept], value[kept]
        keep = (value >= Rf[flat - W]) & (value >= Rf[flat + W])
        for offset in (-W - 1, -W + 1, W - 1, W + 1):
            keep &= value >= Rf[flat + offset]
        x = flat % W
        keep &= (x >= m) & (x < W - m)
        if valid is not None:
            keep &= valid.reshape(-1)[flat] != 0
        kept = keep.nonzero()[0]
        return flat[kept], value[kept]

    def refine(self, gray: np.ndarray, flat: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel positions ``(N, 2)`` of the candidates at flat pixel indices ``(N,)`` and
        ``inside (N,)``: ``False`` where the refined corner lies outside the valid region (the
        true corner is in the margin: not a feature)."""
        y0, x0 = np.divmod(flat, self.width)
        w = self.cfg.subpix_window_px
        if w <= 0 or len(flat) == 0:
            return np.column_stack([x0, y0]).astype(np.float64), np.ones(len(flat), bool)
        xy0 = np.empty((len(flat), 2), np.float32)  # integer pixels, exact in float32
        xy0[:, 0] = x0
        xy0[:, 1] = y0
        xy = refine_corners(gray, xy0, w)
        e = self._edge
        inside = (xy[:, 0] >= e) & (xy[:, 0] <= self.width - 1 - e) & (xy[:, 1] >= e) & (xy[:, 1] <= self.height - 1 - e)
        if valid is not None:
            # If the pixel at floor(xy) is valid, xy itself is more than the margin (Chebyshev)
            # from every invalid pixel: a point within the margin square [q - m, q + m]^2 of an
            # invalid pixel q has its floor pixel inside that square too (m is an integer).
            px = np.floor(xy).astype(np.int64)
            px[:, 0] = np.clip(px[:, 0], 0, self.width - 1)
            px[:, 1] = np.clip(px[:, 1], 0, self.height - 1)
            inside &= valid[px[:, 1], px[:, 0]] != 0
        return xy, inside

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``uv (N, 2)`` float64 raw pixels (x = column, y = row, sub-pixel) and Harris
        ``score (N,)`` float64, descending, ``N <= max_detections``."""
        gray = as_gray(image, out=self._gray)  # out is used only for BGR input
        if gray.shape != (self.height, self.width):
            raise ValueError(f"image is {gray.shape[1]}x{gray.shape[0]}, detector built for {self.width}x{self.height}")
        if 2 * self.margin >= min(self.height, self.width):
            return _EMPTY_UV.copy(), _EMPTY_SCORE.copy()  # no pixel is far enough from the edges
        R = self.harris_response(gray)
        valid = self.valid_region(gray)
        threshold = self.response_threshold(R, valid)
        if threshold is None:
            self.n_candidates = 0
            return _EMPTY_UV.copy(), _EMPTY_SCORE.copy()
        # Only the strongest candidates are ever refined (below), so the local-maximum test first
        # looks at the pixels above a level set by the last frame (LEVEL_FRACTION of the response
        # of its weakest refined candidate: ~7 times the threshold, and a quarter of the pixels
        # above it). The candidates above the level are exactly the frame's candidates above it,
        # so the strongest of them are the frame's strongest; when they are too few, all are taken.
        level = max(threshold, self._level)
        flat, score = self.maxima_above(R, valid, level)
        if level > threshold and len(flat) < self._first_batch:
            level = threshold
            flat, score = self.maxima_above(R, valid, level)
        self.n_candidates = len(flat)
        if len(flat) == 0:
            return _EMPTY_UV.copy(), _EMPTY_SCORE.copy()
        # Refine first, then select on the refined positions, so that every rule holds for what
        # is returned. Only the strongest T candidates are refined; as in select_features, more
        # are taken (and only those refined) when they cannot fill max_detections.
        # The first batch is what the previous frame needed plus a margin (consecutive frames are
        # alike): one refinement and one selection pass for most frames. The result does not
        # depend on the batch size (the decisions for the strongest T do not depend on weaker ones).
        cfg, K = self.cfg, len(flat)
        T = min(K, self._first_batch)
        order = strongest(score, T)
        uv, inside = self.refine(gray, flat[order], valid)
        while True:
            ok = np.flatnonzero(inside)
            keep = ok[select_ordered(uv[ok], cfg, self.width, self.height)]
            if len(keep) >= cfg.max_detections or (T == K and level == threshold):
                needed = int(keep[-1]) + 1 if len(keep) >= cfg.max_detections else K
                self._first_batch = max(64, needed + needed // 8 + 8)
                self._level = LEVEL_FRACTION * float(score[order[T - 1]])
                return uv[keep], score[order[keep]].astype(np.float64)
            done = T
            if T == K:
                # every candidate above the level is refined and more are needed: all of them
                # (the ones refined are the strongest T of these too, in the same order)
                level = threshold
                flat, score = self.maxima_above(R, valid, level)
                K = self.n_candidates = len(flat)
            # take as many more as this batch's yield says are needed (refining costs ~1 us each)
            T = min(K, 4 * T, max(T + 16, int(1.25 * T * cfg.max_detections / max(len(keep), 1))))
            order = strongest(score, T)  # the first `done` are the ones refined already
            more, more_inside = self.refine(gray, flat[order[done:]], valid)
            uv, inside = np.concatenate([uv, more]), np.concatenate([inside, more_inside])


def detect_corners(
    image: np.ndarray, cfg: MapperConfig, border_px: int = 0, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Binned Harris corners of one frame (seed 000, II.C).

    ``image``: ``uint8`` grey ``(H, W)`` or BGR ``(H, W, 3)``; ``mask``: optional ``(H, W)``,
    non-zero = usable. Returns ``uv (N, 2)`` float64 raw pixels (x = column, y = row,
    sub-pixel) and ``score (N,)`` float64 Harris response, descending, ``N <= max_detections``.
    For a stream of frames build a :class:`HarrisDetector` once instead.
    """
    gray = as_gray(image)
    H, W = gray.shape
    return HarrisDetector(cfg, W, H, border_px, mask)(gray)


# --------------------------------------------------------------------------------------------
# Edgels: points on straight image edges, where corners leave room
# --------------------------------------------------------------------------------------------

# Pre-smoothing before the edge detector (px): sensor noise makes no edges, a 1 px blur moves none.
EDGEL_BLUR_SIGMA_PX = 1.0
# OpenCV's Canny on a 3x3 Sobel: a sharp step of D grey levels gives a gradient of ~4 D.
_SOBEL_STEP_GAIN = 4.0
# Edge pixels looked at in a frame per edgel asked for, strongest first (a strong edge gives two
# pixels per spacing-wide cell and one edgel per spacing: 16 leave room for several edges).
_EDGEL_CANDIDATES_PER_EDGEL = 16
# Reach of the filters around a bin (px): Canny's 3x3 Sobel and its non-maximum suppression
# (1 px each) and the sub-pixel fit's samples (up to 2.5 px across the edge).
_EDGEL_PAD_PX = 3
# Reach of the ``EDGEL_BLUR_SIGMA_PX`` blur (px): OpenCV's 8-bit kernel is 2 round(3 sigma) + 1 wide.
_BLUR_REACH_PX = 3


def detect_edgels(
    gray: np.ndarray, corners_uv: np.ndarray, cfg: MapperConfig, border_px: int = 0, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edgels of a grey frame ``(H, W)`` uint8: points on image edges in the bins where the corner
    detector found nothing (docs/mapper.md, "Edgels").

    A plain surface (a roof, the top of a wall) has no corners, but its outline against what lies
    behind it is an edge, and an edge measures one coordinate: the distance across it. Pixels on
    Canny's edges (thin, after a ``EDGEL_BLUR_SIGMA_PX`` blur; a step of at least
    ``edgel_min_step_grey``) are taken in the bins where the corner detector found nothing
    (``corners_uv (N, 2)``, raw pixels), strongest gradient first, under the corners' rules: no
    closer than ``min_distance_px`` to a corner or a stronger edgel, at most ``per_bin`` per bin,
    at most ``max_edgels``; each is moved across its edge to the sub-pixel peak of the gradient.
    So textured ground, where corners are, gives none; a plain face gives its outline.

    ``valid (H, W)``: the usable pixels (non-zero), e.g. :meth:`HarrisDetector.valid_region`, so
    that a mask's or a black border's outline makes no edgels; by default the image-edge margin and
    any black border.

    Returns ``uv (E, 2)`` float64 raw pixels, ``normal (E, 2)`` unit vectors across the edge (the
    grey-level gradient's direction) and ``strength (E,)`` the gradient (grey levels per pixel),
    in that order."""
    gray = np.asarray(gray)
    H, W = gray.shape[:2]
    empty = (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    m = effective_margin(cfg, border_px)
    if cfg.max_edgels <= 0 or 2 * m >= min(H, W):
        return empty
    # only bins without a corner take edgels: Canny runs on those bins only (each bin row's runs
    # of such bins, padded by the filters' reach), the rest of the frame is never filtered
    corners = np.asarray(corners_uv, dtype=float).reshape(-1, 2)
    corners = corners[np.isfinite(corners).all(axis=1)]
    no_corner = np.bincount(bin_of(corners, W, H, cfg.bins_x, cfg.bins_y), minlength=cfg.bins_x * cfg.bins_y) == 0
    if not no_corner.any():
        return empty
    if valid is None:  # the corner detector's valid region when given, else the black border's
        depths = black_border_depths(gray)
        valid = None if depths is None else black_border_valid(depths, (H, W), m)
    high = _SOBEL_STEP_GAIN * cfg.edgel_min_step_grey
    # the smoothed image is needed only in those bins and within the filters' reach of them: it is
    # blurred crop by crop (each crop padded by the blur's reach, so its pixels are those of a
    # whole-frame blur); elsewhere ``smooth`` is never read
    smooth = np.empty((H, W), np.float32)
    flats, gxs, gys = [], [], []
    # pixel x is in bin floor(x bins_x / W) (as bin_of): bin b spans ceil(b W / bins_x) .. ceil((b + 1) W / bins_x) - 1
    x_edge = -(-np.arange(cfg.bins_x + 1) * W // cfg.bins_x)
    y_edge = -(-np.arange(cfg.bins_y + 1) * H // cfg.bins_y)
    lo_x, hi_x, lo_y, hi_y = m, W - m, m, H - m  # the image-edge margin
    for by, row in enumerate(no_corner.reshape(cfg.bins_y, cfg.bins_x)):
        for b0, b1 in _runs(row):
            y0, y1, x0, x1 = y_edge[by], y_edge[by + 1], x_edge[b0], x_edge[b1]
            # the bins themselves, inside the image-edge margin (bins wholly in it are not filtered)
            u0, u1, v0, v1 = max(x0, lo_x), min(x1, hi_x), max(y0, lo_y), min(y1, hi_y)
            if u0 >= u1 or v0 >= v1:
                continue
            Y0, Y1, X0, X1 = _grown((y0, y1, x0, x1), _EDGEL_PAD_PX, H, W)  # what the filters read
            BY0, BY1, BX0, BX1 = _grown((Y0, Y1, X0, X1), _BLUR_REACH_PX, H, W)  # what their input's blur reads
            blurred = cv2.GaussianBlur(gray[BY0:BY1, BX0:BX1], (0, 0), EDGEL_BLUR_SIGMA_PX)
            crop = np.ascontiguousarray(blurred[Y0 - BY0:Y1 - BY0, X0 - BX0:X1 - BX0])
            smooth[Y0:Y1, X0:X1] = crop  # (as float32, for the sub-pixel fit)
            # Canny's own 3x3 Sobel (replicated border), computed once: the edges and the gradient
            dx, dy = cv2.spatialGradient(crop, ksize=3, borderType=cv2.BORDER_REPLICATE)
            edges = cv2.Canny(dx, dy, 0.5 * high, high, L2gradient=True)
            found = cv2.findNonZero(edges[v0 - Y0:v1 - Y0, u0 - X0:u1 - X0])  # (x, y), row by row
            if found is None:
                continue
            found = found.reshape(-1, 2)
            at = (found[:, 1] + (v0 - Y0)) * (X1 - X0) + found[:, 0] + (u0 - X0)  # in the crop
            flats.append((found[:, 1] + v0) * W + found[:, 0] + u0)
            gxs.append(dx.reshape(-1)[at])
            gys.append(dy.reshape(-1)[at])
    if not flats:
        return empty
    flat = np.concatenate(flats)
    gx, gy = np.concatenate(gxs).astype(np.int64), np.concatenate(gys).astype(np.int64)
    if valid is not None:
        usable = valid.reshape(-1)[flat] != 0
        flat, gx, gy = flat[usable], gx[usable], gy[usable]
    if len(flat) == 0:
        return empty
    # the strongest _EDGEL_CANDIDATES_PER_EDGEL x max_edgels pixels (by the squared Sobel gradient,
    # an integer; ties in frame order, row by row: the key is unique), of those the strongest of
    # each cell of half the spacing (two in one cell are too close anyway), then strongest first
    # under the spacing and the per-bin cap
    key = (gx * gx + gy * gy) * (H * W) + (H * W - 1 - flat)
    top = strongest(key, min(len(key), _EDGEL_CANDIDATES_PER_EDGEL * cfg.max_edgels))
    flat, gx, gy = flat[top], gx[top], gy[top]
    iy, ix = np.divmod(flat, W)
    # the gradient in grey levels per pixel (the 3x3 Sobel of a step of D levels is 4 D, over 2 px)
    gx, gy = gx / (2.0 * _SOBEL_STEP_GAIN), gy / (2.0 * _SOBEL_STEP_GAIN)
    strength = np.sqrt(gx * gx + gy * gy)
    cell = max(1, int(cfg.min_distance_px // 2))
    cell_id = (iy // cell) * (W // cell + 1) + ix // cell
    _, first = np.unique(cell_id, return_index=True)  # (strongest first: the first of each cell)
    pick = np.sort(first)
    xy = np.column_stack([ix[pick], iy[pick]]).astype(np.float64)
    # the corners first (kept: they are the detector's), then the edgels strongest first
    kept = suppress_within(np.concatenate([corners, xy]), cfg.min_distance_px)[len(corners):]
    keep = np.flatnonzero(kept)
    keep = keep[_bin_rank(xy[keep], W, H, cfg.bins_x, cfg.bins_y) < cfg.per_bin][: cfg.max_edgels]
    chosen = pick[keep]
    strength = strength[chosen]
    normal = np.column_stack([gx[chosen], gy[chosen]]) / strength[:, None]
    return _refine_across(smooth, xy[keep], normal), normal, strength


def _grown(box: tuple[int, int, int, int], by: int, H: int, W: int) -> tuple[int, int, int, int]:
    """The pixel box ``(y0, y1, x0, x1)`` (half-open) grown by ``by`` px on every side, inside the
    ``(H, W)`` image."""
    y0, y1, x0, x1 = box
    return max(y0 - by, 0), min(y1 + by, H), max(x0 - by, 0), min(x1 + by, W)


def _refine_across(smooth: np.ndarray, xy: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Edgels ``xy (E, 2)`` moved across their edge (along the unit ``normal``) to the sub-pixel
    peak of the grey-level derivative: the derivative at -1, 0 and +1 px along the normal (central
    differences of bilinear samples of ``smooth``), the vertex of the parabola through them
    (Canny's pixel is up to half a pixel off; a corner gets cornerSubPix)."""
    if len(xy) == 0:
        return xy
    k = np.array([-1.5, -0.5, 0.5, 1.5])
    pts = xy[:, None, :] + k[None, :, None] * normal[:, None, :]  # (E, 4, 2)
    grey = cv2.remap(np.asarray(smooth, np.float32), pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    d = np.diff(grey.astype(np.float64), axis=1)  # derivative at -1, 0, +1 px (E, 3)
    curvature = d[:, 0] - 2.0 * d[:, 1] + d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (d[:, 0] - d[:, 2]) / curvature, 0.0)
    offset = np.clip(np.nan_to_num(offset), -0.5, 0.5)
    return xy + offset[:, None] * normal


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` of the runs of True in a short 1-D bool array (a row of bins)."""
    runs, start = [], None
    for i, on in enumerate(mask.tolist()):
        if on and start is None:
            start = i
        elif not on and start is not None:
            runs.append((start, i))
            start = None
    if start is not None:
        runs.append((start, len(mask)))
    return runs


def bin_of(xy: np.ndarray, width: int, height: int, bins_x: int, bins_y: int) -> np.ndarray:
    """Bin number ``(K,)`` (row by row) of points ``xy (K, 2)`` inside the image."""
    bx = np.clip((xy[:, 0] * (bins_x / width)).astype(np.int64), 0, bins_x - 1)
    by = np.clip((xy[:, 1] * (bins_y / height)).astype(np.int64), 0, bins_y - 1)
    return by * bins_x + bx
