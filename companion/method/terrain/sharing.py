"""Terrain evidence from other vehicles, in the map the avoidance law reads (docs/terrain.md,
"Evidence from other vehicles").

Each other vehicle (a *source*) publishes its own map: tiles of (height, variance, count) in its
own local frame. :class:`SharedEvidence` keeps, per source, the latest tile it sent for each tile
key, placed in this vehicle's frame by the offset between the two frames' origins rounded to whole
cells (a source's cell lands on exactly one of ours; the rounding moves it by at most half a
cell). Nothing of a source is ever fused into this vehicle's own grid: the own grid stays this
vehicle's evidence alone (what it publishes), and the law reads both through :class:`SharedView`,
which fuses them per cell at query time (:func:`fuse_cells`). Hence, by construction:

* a tile received twice, or published again unchanged, counts once: it replaces its
  predecessor;
* a vehicle never takes its own evidence back from another (its own name is refused as a
  source, and sources publish only their own evidence);
* a source can be trusted less (``weight`` < 1 multiplies its variances by ``1 / weight``) or
  withdrawn (:meth:`SharedEvidence.withdraw`): its cells leave the law's map at the next query.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.method.terrain.grid import Corridor
from companion.method.terrain.tile import Tile


@dataclass
class _Source:
    shift: tuple[int, int]                                          # (cells north, cells east)
    up: float = 0.0                                                 # metres its heights rise by, in ours
    weight: float = 1.0
    raw: dict[tuple[int, int], Tile] = field(default_factory=dict)  # its tiles as received, its frame
    placed: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)


class SharedEvidence:
    """Other vehicles' maps, each placed in this vehicle's frame (module docstring)."""

    def __init__(self, own_vehicle: str, cell_size_m: float, tile_cells: int) -> None:
        self.own_vehicle = own_vehicle
        self.cell_size_m = float(cell_size_m)
        self.tile_cells = int(tile_cells)
        self._sources: dict[str, _Source] = {}

    @property
    def sources(self) -> list[str]:
        return sorted(self._sources)

    def set_frame(self, source: str, offset_m: tuple[float, float, float], weight: float | None = None) -> None:
        """Where ``source``'s origin lies in this vehicle's frame (north, east, up; m), and how much
        it is trusted (0 < weight <= 1). ``up`` takes the source's published heights to ours: its
        origin's height above ours plus its map's ``frame_shift_m`` (its tiles are in its map's
        own frame). A changed north or east offset re-places every tile already received; a
        changed ``up`` costs nothing (it is added at :meth:`lookup`)."""
        if source == self.own_vehicle:
            raise ValueError(f"{source!r} is this vehicle: its own evidence is never taken back from another")
        north, east, up = (float(v) for v in offset_m)
        if not all(math.isfinite(v) for v in (north, east, up)):
            raise ValueError(f"offset of {source!r} must be finite, got {offset_m!r}")
        shift = (int(round(north / self.cell_size_m)), int(round(east / self.cell_size_m)))
        src = self._sources.get(source)
        if src is None:
            src = self._sources[source] = _Source(shift)
        src.up = up  # added at lookup: a source's vertical frame moves often, its cells rarely
        if weight is not None:
            if not 0.0 < weight <= 1.0:
                raise ValueError(f"weight of {source!r} must be in (0, 1], got {weight}")
            src.weight = float(weight)
        if shift != src.shift:
            src.shift = shift
            src.placed.clear()
            for tile in src.raw.values():
                self._place(src, tile)

    def put(self, source: str, tile: Tile) -> bool:
        """A tile from ``source`` (in its frame); False when the source has no frame yet (call
        :meth:`set_frame` first) or the tile's lattice is not this map's."""
        src = self._sources.get(source)
        if src is None or tile.tile_cells != self.tile_cells or not math.isclose(tile.cell_size_m, self.cell_size_m):
            return False
        old = src.raw.get((tile.tx, tile.ty))
        src.raw[(tile.tx, tile.ty)] = tile
        if old is not None:
            self._place(src, old, clear=True)  # its cells first emptied: the new tile replaces it
        self._place(src, tile)
        return True

    def withdraw(self, source: str) -> None:
        """Forget everything ``source`` sent."""
        self._sources.pop(source, None)

    def _place(self, src: _Source, tile: Tile, clear: bool = False) -> None:
        """Write ``tile``'s cells (or empty them) at their place in this vehicle's lattice."""
        t = self.tile_cells
        di, dj = src.shift
        gi0, gj0 = tile.tx * t + di, tile.ty * t + dj  # the tile's south-west cell, ours
        for ti in range(gi0 // t, (gi0 + t - 1) // t + 1):
            for tj in range(gj0 // t, (gj0 + t - 1) // t + 1):
                i0, j0 = max(gi0, ti * t), max(gj0, tj * t)                   # overlap, global cells
                i1, j1 = min(gi0 + t, (ti + 1) * t), min(gj0 + t, (tj + 1) * t)
                dst = src.placed.get((ti, tj))
                if dst is None:
                    if clear:
                        continue
                    dst = src.placed[(ti, tj)] = (np.full((t, t), np.nan, np.float32), np.full((t, t), np.inf, np.float32),
                                                  np.zeros((t, t), np.uint32))
                a, b = slice(i0 - ti * t, i1 - ti * t), slice(j0 - tj * t, j1 - tj * t)  # in our tile
                s, u = slice(i0 - gi0, i1 - gi0), slice(j0 - gj0, j1 - gj0)          # in theirs
                if clear:
                    dst[0][a, b], dst[1][a, b], dst[2][a, b] = np.nan, np.inf, 0
                else:
                    dst[0][a, b], dst[1][a, b], dst[2][a, b] = tile.height[s, u], tile.variance[s, u], tile.count[s, u]

    def lookup(self, source: str, ci: np.ndarray, cj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``source``'s height, variance (divided by its weight) and count at our cells (K,)."""
        src = self._sources[source]
        t = self.tile_cells
        h = np.full(len(ci), np.nan)
        v = np.full(len(ci), np.inf)
        n = np.zeros(len(ci), np.int64)
        ti, tj = np.floor_divide(ci, t), np.floor_divide(cj, t)
        for key in set(zip(ti.tolist(), tj.tolist())):
            layers = src.placed.get(key)
            if layers is None:
                continue
            sel = (ti == key[0]) & (tj == key[1])
            li, lj = ci[sel] - key[0] * t, cj[sel] - key[1] * t
            h[sel], v[sel], n[sel] = layers[0][li, lj], layers[1][li, lj] / src.weight, layers[2][li, lj]
        return h + src.up, v, n


def fuse_cells(h: np.ndarray, v: np.ndarray, n: np.ndarray, h_s: np.ndarray, v_s: np.ndarray, n_s: np.ndarray,
               gate_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse another vehicle's estimate of each cell's top (h_s, v_s, n_s) into ours (h, v, n), all
    (K,), as the grid fuses a point (docs/terrain.md, "Fusion"): where only one is known it is taken;
    where both are and they agree within ``gate_sigma`` innovation sigmas, their information adds
    (``h = (h/v + h_s/v_s) / (1/v + 1/v_s)``, ``v = 1 / (1/v + 1/v_s)``); where the other's is far
    above, it is a higher surface and is taken; far below, the face of what we see, it is left.
    Counts add where a source is used."""
    mine, theirs = (n > 0) & np.isfinite(h), (n_s > 0) & np.isfinite(h_s)
    out_h, out_v, out_n = h.astype(float).copy(), v.astype(float).copy(), n.astype(np.int64).copy()
    only = theirs & ~mine
    out_h[only], out_v[only], out_n[only] = h_s[only], v_s[only], n_s[only]
    both = theirs & mine
    with np.errstate(invalid="ignore", divide="ignore"):
        gap = h_s - h
        agree = both & (np.abs(gap) <= gate_sigma * np.sqrt(v + v_s))
        above = both & (gap > 0) & ~agree
        info = 1.0 / v[agree] + 1.0 / v_s[agree]
        out_h[agree] = (h[agree] / v[agree] + h_s[agree] / v_s[agree]) / info
        out_v[agree] = 1.0 / info
    out_h[above], out_v[above] = h_s[above], v_s[above]
    out_n[agree | above] += n_s[agree | above]
    return out_h, out_v, out_n


class SharedView:
    """A terrain grid as the law reads it, with other vehicles' evidence fused in (module
    docstring): :meth:`corridor` fuses, everything else is the own grid's."""

    def __init__(self, grid, shared: SharedEvidence, gate_sigma: float = 3.0) -> None:
        self._grid = grid
        self._shared = shared
        self._gate = float(gate_sigma)

    def __getattr__(self, name: str):
        return getattr(self._grid, name)

    def corridor(self, origin_ne, direction_ne, length_m: float, half_width_m: float) -> Corridor:
        c = self._grid.corridor(origin_ne, direction_ne, length_m, half_width_m)
        if not self._shared.sources or not len(c):
            return c
        cell = self._grid.cell_size_m
        ci = np.floor(c.north_m / cell).astype(np.int64)
        cj = np.floor(c.east_m / cell).astype(np.int64)
        h, v, n = c.height_m, c.variance, c.count
        hv = c.height_variance if c.height_variance is not None else c.variance
        for source in self._shared.sources:
            h_s, v_s, n_s = self._shared.lookup(source, ci, cj)
            h_new, v_new, n_new = fuse_cells(h, v, n, h_s, v_s, n_s, self._gate)
            # The surface variance follows the fused one where a source was used.
            changed = n_new != n
            hv = np.where(changed, v_new, hv)
            h, v, n = h_new, v_new, n_new
        return Corridor(c.north_m, c.east_m, c.along_m, c.cross_m, h, v, n, c.ceiling_m, hv, c.floor_m)
