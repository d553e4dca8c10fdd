"""Terrain map error against a reference surface (docs/replay.md, "Reference surface").

The reference is a CSV of points ``x,y,z``: a DSM grid (one point per cell centre) or a point
cloud. Points are binned into the map's cells (``floor(north / cell)``, ``floor(east / cell)``,
the terrain grid's own indexing) and reduced per cell to one height (mean, median or max); the
map is compared on the cells both cover:

    e_k = h_map,k - h_ref,k              (map minus reference, metres, up positive)
    bias = mean(e),  rmse = sqrt(mean(e^2)),  coverage = cells compared / reference cells

``coverage`` says how much of the reference surface the map holds; ``map_fraction_checked`` how
much of the map the reference could check. ``within_1m`` (the fraction of compared cells with
|e| <= 1 m) and the percentiles are robust to the few wild cells that dominate an RMSE.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.method.terrain.grid import TerrainGrid

Statistic = str  # "mean", "median", "max" or "pNN" (the NN-th percentile, 0-100)


def percentile_of(statistic: str) -> float | None:
    """The percentile (0-100) a ``"pNN"`` statistic names, None for mean, median and max;
    ValueError for anything else."""
    if statistic in ("mean", "median", "max"):
        return None
    if statistic.startswith("p"):
        try:
            q = float(statistic[1:])
        except ValueError:
            q = math.nan
        if 0.0 <= q <= 100.0:
            return q
    raise ValueError(f"statistic must be mean, median, max or pNN (a percentile 0-100, e.g. p90), got {statistic!r}")
_SHIFT = np.int64(1 << 32)
_BIAS = np.int64(1 << 31)


@dataclass(frozen=True, slots=True)
class CellHeights:
    """Heights per map cell: global cell indices ``ci`` (north), ``cj`` (east) (K,) int64, height (K,) m
    (up), and for map cells variance (K,) m^2 and evidence count (K,)."""

    ci: np.ndarray
    cj: np.ndarray
    height: np.ndarray
    variance: np.ndarray | None = None
    count: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ci)

    @property
    def keys(self) -> np.ndarray:
        return self.ci.astype(np.int64) * _SHIFT + (self.cj.astype(np.int64) + _BIAS)


def map_cells(grid: TerrainGrid) -> CellHeights:
    """Every cell of ``grid`` holding evidence."""
    ci, cj, h, v, n = [], [], [], [], []
    for tile in grid.tiles():
        T = tile.tile_cells
        ii, jj = np.nonzero(tile.known)
        ci.append(tile.tx * T + ii)
        cj.append(tile.ty * T + jj)
        h.append(tile.height[ii, jj].astype(np.float64))
        v.append(tile.variance[ii, jj].astype(np.float64))
        n.append(tile.count[ii, jj].astype(np.int64))
    if not ci:
        z = np.zeros(0, np.int64)
        return CellHeights(z, z.copy(), np.zeros(0), np.zeros(0), z.copy())
    return CellHeights(np.concatenate(ci).astype(np.int64), np.concatenate(cj).astype(np.int64),
                       np.concatenate(h), np.concatenate(v), np.concatenate(n))


# --------------------------------------------------------------------------------------------
# Reference surface
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ReferencePoints:
    """Points read from a reference CSV: xyz (N, 3) as written in the file, bad_lines skipped."""

    path: Path
    xyz: np.ndarray
    bad_lines: int
    first_problem: str = ""


def read_reference_csv(path: str | Path) -> ReferencePoints:
    """``x,y,z`` per line (comma or whitespace separated); an optional header line, blank lines and
    ``#`` comments are skipped; malformed or non-finite lines are counted and skipped. A file with
    no usable point raises ValueError naming it."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read reference surface: {exc}") from exc
    rows: list[tuple[float, float, float]] = []
    bad, first = 0, ""
    for line_no, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        fields = [f for f in text.replace(",", " ").split()]
        try:
            if len(fields) < 3:
                raise ValueError(f"{len(fields)} fields, expected x,y,z")
            x, y, z = (float(f) for f in fields[:3])
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                raise ValueError("not finite")
        except ValueError as exc:
            if not rows and bad == 0 and not any(c.isdigit() for c in text):
                continue  # a header line such as "x,y,z"
            bad += 1
            first = first or f"{path}: line {line_no}: {exc}"
            continue
        rows.append((x, y, z))
    if not rows:
        raise ValueError(f"{path}: no reference point (expected lines 'x,y,z')")
    return ReferencePoints(path, np.asarray(rows, float), bad, first)


PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_reference_ply(path: str | Path) -> ReferencePoints:
    """The vertices of a PLY point cloud (ascii, binary_little_endian or binary_big_endian; the
    ``vertex`` element's ``x``, ``y``, ``z`` properties, any others skipped; elements before it are
    not supported): the usual output of photogrammetry and SfM tools. Non-finite vertices are
    counted and skipped; a file that is not such a PLY raises ValueError naming it and why."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read reference surface: {exc.strerror or exc}") from exc
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body = data[data.index(b"\n", end) + 1:]
    fmt, n_vertex, props, element = None, None, [], None
    for raw in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            element = words[1]
            if element == "vertex":
                n_vertex = int(words[2])
            elif n_vertex is None:
                raise ValueError(f"{path}: element '{element}' comes before 'vertex' (not supported)")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list" or len(words) != 3 or words[1] not in PLY_TYPES:
                raise ValueError(f"{path}: vertex property {' '.join(words[1:])!r} not supported")
            props.append((words[2], PLY_TYPES[words[1]]))
    names = [name for name, _ in props]
    if n_vertex is None or not all(axis in names for axis in "xyz"):
        raise ValueError(f"{path}: no vertex element with x, y and z properties")
    if fmt == "ascii":
        rows = [line.split() for line in body.decode("ascii", "replace").splitlines()[:n_vertex]]
        try:
            table = np.array([[float(v) for v in row[: len(props)]] for row in rows if len(row) >= len(props)])
        except ValueError as exc:
            raise ValueError(f"{path}: vertex line not numbers: {exc}") from exc
        table = table.reshape(-1, len(props))
        xyz = table[:, [names.index(a) for a in "xyz"]]
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + code) for name, code in props])
        if len(body) < n_vertex * dtype.itemsize:
            raise ValueError(f"{path}: truncated: {n_vertex} vertices need {n_vertex * dtype.itemsize} bytes, "
                             f"{len(body)} there")
        table = np.frombuffer(body, dtype=dtype, count=n_vertex)
        xyz = np.column_stack([table[a].astype(np.float64) for a in "xyz"])
    else:
        raise ValueError(f"{path}: PLY format {fmt!r} not supported (ascii, binary_little_endian, binary_big_endian)")
    finite = np.isfinite(xyz).all(axis=1)
    bad = int(len(xyz) - np.count_nonzero(finite)) + (n_vertex - len(xyz))
    if not finite.any():
        raise ValueError(f"{path}: no usable vertex")
    return ReferencePoints(path, xyz[finite], bad, f"{path}: {bad} vertices not finite or missing" if bad else "")


def is_colmap_points(path: str | Path) -> bool:
    """A COLMAP model's ``points3D.txt`` (its coordinates are the model's world: the dataset frame)."""
    return Path(path).name.lower() == "points3d.txt"


def read_reference(path: str | Path) -> ReferencePoints:
    """A reference surface by its file: ``.ply`` a point cloud (:func:`read_reference_ply`), a COLMAP
    ``points3D.txt`` (:func:`companion.desk.recordings.colmap.read_points3d`), anything else
    ``x,y,z`` text (:func:`read_reference_csv`)."""
    if Path(path).suffix.lower() == ".ply":
        return read_reference_ply(path)
    if is_colmap_points(path):
        from companion.desk.recordings.colmap import read_points3d

        try:
            xyz, bad, first = read_points3d(path)
        except OSError as exc:
            raise ValueError(f"{path}: cannot read reference surface: {exc}") from exc
        if not len(xyz):
            raise ValueError(f"{path}: no 3D point (a model without points3D; expected 'POINT3D_ID X Y Z ...' lines)")
        return ReferencePoints(Path(path), xyz, bad, first)
    return read_reference_csv(path)


def bin_heights(north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray, cell_size_m: float,
                statistic: Statistic = "mean", min_points: int = 1) -> CellHeights:
    """Reduce points (N,) to one height per cell of size ``cell_size_m``: mean, median, max or the
    ``pNN`` percentile (linear between the two nearest ranks; for a point cloud's top surface
    ``p90`` keeps what ``max`` gives but not its single noisy points); cells with fewer than
    ``min_points`` points are left out."""
    q = percentile_of(statistic)
    ci = np.floor(np.asarray(north_m, float) / cell_size_m).astype(np.int64)
    cj = np.floor(np.asarray(east_m, float) / cell_size_m).astype(np.int64)
    h = np.asarray(height_m, float)
    keys = ci * _SHIFT + (cj + _BIAS)
    order = np.lexsort((h, keys))  # by cell, heights ascending inside a cell
    keys, h = keys[order], h[order]
    start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    count = np.diff(np.r_[start, len(keys)])
    if statistic == "mean":
        out = np.add.reduceat(h, start) / count if len(h) else np.zeros(0)
    elif statistic == "max":
        out = h[start + count - 1]
    elif q is not None:
        rank = (count - 1) * (q / 100.0)
        lo = np.floor(rank).astype(np.int64)
        hi = np.minimum(lo + 1, count - 1)
        out = h[start + lo] + (rank - lo) * (h[start + hi] - h[start + lo])
    else:
        lo, hi = start + (count - 1) // 2, start + count // 2
        out = 0.5 * (h[lo] + h[hi])
    k = keys[start]
    keep = count >= max(int(min_points), 1)
    k, out, count = k[keep], out[keep], count[keep]
    cell_i = np.floor_divide(k, _SHIFT)
    return CellHeights(cell_i, k - cell_i * _SHIFT - _BIAS, out, count=count)


def compare(map_: CellHeights, reference: CellHeights) -> dict[str, Any]:
    """Error statistics of the map against the reference over the cells both hold (see module doc)."""
    common, i_map, i_ref = np.intersect1d(map_.keys, reference.keys, assume_unique=True, return_indices=True)
    e = map_.height[i_map] - reference.height[i_ref]
    n = len(e)
    out: dict[str, Any] = {
        "cells_compared": int(n),
        "cells_reference": int(len(reference)),
        "cells_mapped": int(len(map_)),
        "coverage": n / len(reference) if len(reference) else 0.0,
        "map_fraction_checked": n / len(map_) if len(map_) else 0.0,
    }
    if n == 0:
        return out | {k: None for k in ("rmse_m", "bias_m", "mae_m", "median_abs_m", "p95_abs_m", "max_abs_m", "within_1m")}
    a = np.abs(e)
    return out | {
        "rmse_m": float(np.sqrt(np.mean(e * e))),
        "bias_m": float(np.mean(e)),
        "mae_m": float(np.mean(a)),
        "median_abs_m": float(np.median(a)),
        "p95_abs_m": float(np.percentile(a, 95)),
        "max_abs_m": float(a.max()),
        "within_1m": float(np.mean(a <= 1.0)),
    }


def reference_metrics(grid: TerrainGrid, north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray,
                      statistic: Statistic = "mean") -> dict[str, Any]:
    """Bin reference points (already in the map frame: north, east, altitude up) into the grid's
    cells and compare (:func:`compare`)."""
    ref = bin_heights(north_m, east_m, height_m, grid.cell_size_m, statistic)
    return compare(map_cells(grid), ref) | {"statistic": statistic}


# --------------------------------------------------------------------------------------------
# Dense rasters for figures
# --------------------------------------------------------------------------------------------


def dense_heights(cells: CellHeights, cell_size_m: float, max_side: int = 1200,
                  include_ne: np.ndarray | None = None, margin_cells: int = 2) -> tuple[np.ndarray, float, float, float]:
    """A dense (rows = north, cols = east) height raster over the cells' bounding box (grown to hold
    the points ``include_ne`` (M, 2), e.g. the flight path), NaN where unknown. Rasters wider than
    ``max_side`` are reduced by block means. Returns (heights, north0_m, east0_m, raster cell size)."""
    ci, cj = cells.ci, cells.cj
    lo_i, hi_i = (int(ci.min()), int(ci.max())) if len(ci) else (0, 0)
    lo_j, hi_j = (int(cj.min()), int(cj.max())) if len(cj) else (0, 0)
    if include_ne is not None and len(include_ne):
        pi = np.floor(np.asarray(include_ne)[:, 0] / cell_size_m).astype(np.int64)
        pj = np.floor(np.asarray(include_ne)[:, 1] / cell_size_m).astype(np.int64)
        if not len(ci):
            lo_i, hi_i, lo_j, hi_j = int(pi.min()), int(pi.max()), int(pj.min()), int(pj.max())
        lo_i, hi_i = min(lo_i, int(pi.min())), max(hi_i, int(pi.max()))
        lo_j, hi_j = min(lo_j, int(pj.min())), max(hi_j, int(pj.max()))
    lo_i, lo_j, hi_i, hi_j = lo_i - margin_cells, lo_j - margin_cells, hi_i + margin_cells, hi_j + margin_cells
    k = max(1, math.ceil(max(hi_i - lo_i + 1, hi_j - lo_j + 1) / max_side))
    rows, cols = math.ceil((hi_i - lo_i + 1) / k), math.ceil((hi_j - lo_j + 1) / k)
    total = np.zeros(rows * cols)
    weight = np.zeros(rows * cols)
    if len(ci):
        flat = ((ci - lo_i) // k) * cols + (cj - lo_j) // k
        np.add.at(total, flat, cells.height)
        np.add.at(weight, flat, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        heights = np.where(weight > 0, total / weight, np.nan).reshape(rows, cols)
    return heights, lo_i * cell_size_m, lo_j * cell_size_m, k * cell_size_m
