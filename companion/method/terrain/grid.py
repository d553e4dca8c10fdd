"""The terrain evidence grid: tiles created on demand in the local NED frame (seed 000, II.E).

Storage: one pool of tile layers ``(capacity, T, T)`` (height f32, variance f32, count u32, and
the fusion state: disagreement f32 (evidence from below) and pending f32 (a higher height waiting
for confirmation, NaN none); the free space: ceiling f32 (the lowest height a line of sight crossed
the cell at, +inf none), evidence weight f32 and floor f32 (the least the terrain reaches, -inf
none); the time of its last height update f32 (for the navigation's frame); 36 bytes a cell) and
a sorted array of packed tile keys, so every batched operation is one ``searchsorted`` plus fancy
indexing, and memory follows the tiles that exist (the area observed), never a bounding box. Fusion rules: :mod:`companion.terrain.fusion`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from companion.config import TerrainConfig
from companion.method.messages import FreeSpaceRays, TerrainFloors, TerrainPoints
from companion.method.terrain import fusion
from companion.method.terrain.frame import FrameTracker
from companion.method.terrain.tile import Tile

_KEY_SHIFT = np.int64(1 << 32)
_KEY_BIAS = np.int64(1 << 31)
_COUNT_MAX = np.iinfo(np.uint32).max
_CONTRADICTION_MEMORY = 4096  # cells remembered before the stale ones are forgotten
_NEIGHBOUR_DI = np.array([-1, -1, -1, 0, 0, 1, 1, 1])  # the eight neighbours of a cell
_NEIGHBOUR_DJ = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
_AROUND_DI = np.r_[0, _NEIGHBOUR_DI]  # a cell (or block) and its eight neighbours, itself first
_AROUND_DJ = np.r_[0, _NEIGHBOUR_DJ]


def pack_key(tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Tile indices -> one int64 per tile (tx in the high 32 bits, ty biased in the low 32)."""
    return np.asarray(tx, dtype=np.int64) * _KEY_SHIFT + (np.asarray(ty, dtype=np.int64) + _KEY_BIAS)


def unpack_key(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    key = np.asarray(key, dtype=np.int64)
    tx = np.floor_divide(key, _KEY_SHIFT)
    return tx, key - tx * _KEY_SHIFT - _KEY_BIAS


@dataclass(frozen=True, slots=True)
class InsertStats:
    """Outcome of one :meth:`TerrainGrid.insert` (counts of points unless named cells).

    inserted: points that changed some cell's height (agreeing, or confirming a higher surface).
    rejected_outlier: valid points that changed no height: below every cell they touch (counted
    as disagreement), or above and not yet confirmed (kept as the cell's pending height).
    cells_touched: cells the batch reached; cells_raised: cells that took a higher surface;
    cells_reset: cells brought down by persistent evidence from below; lone_points: points that
    came into an empty cell standing alone far above everything near them (kept pending, like a
    point above a mapped cell: a second one near it confirms them). From
    :meth:`TerrainGrid.add_evidence` also lone_floors: floors withdrawn because the feature that
    raised them ended and nothing near them backs them."""

    inserted: int = 0
    rejected_invalid: int = 0
    rejected_outlier: int = 0
    rejected_imprecise: int = 0
    cells_touched: int = 0
    cells_raised: int = 0
    cells_reset: int = 0
    lone_points: int = 0
    lone_floors: int = 0


@dataclass(frozen=True, slots=True)
class CarveStats:
    """Outcome of one :meth:`TerrainGrid.carve`: rays used, cells whose ceiling came down, cells a
    ray passed under (contradicting their height), cells cleared (their height gone), pending
    heights and floors dropped."""

    rays: int = 0
    cells_lowered: int = 0
    cells_passed_under: int = 0
    cells_cleared: int = 0
    pending_dropped: int = 0
    floors_dropped: int = 0


@dataclass(frozen=True, slots=True, eq=False)
class Corridor:
    """Cells whose centre lies within ``half_width`` of a horizontal segment, sorted along track.

    Every array is (K,): north_m, east_m (cell centre), along_m (projection on the direction from
    the origin; negative for cells beside or behind the origin), cross_m (distance to the
    segment's line), height_m (NaN unknown), variance (inf unknown), count, ceiling_m (the lowest
    height a line of sight crossed the cell at; inf none), height_variance (the variance of the
    surface height the cell's evidence gives: its variance times its evidence weight where that is
    below one point, since a point's share of a cell is uncertainty about where it lies, not about
    how high; inf unknown), floor_m (the least the terrain in the cell reaches, from features not
    yet converged; -inf none).
    """

    north_m: np.ndarray
    east_m: np.ndarray
    along_m: np.ndarray
    cross_m: np.ndarray
    height_m: np.ndarray
    variance: np.ndarray
    count: np.ndarray
    ceiling_m: np.ndarray | None = None
    height_variance: np.ndarray | None = None
    floor_m: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.along_m)

    @property
    def known(self) -> np.ndarray:
        return self.count > 0

    def most_restrictive(self) -> int | None:
        """Index of the highest known cell (the nearest of equals), or None if none is known."""
        if not self.known.any():
            return None
        return int(np.nanargmax(self.height_m))


class TerrainGrid:
    """Evidence grid of terrain altitudes (m, up) over the local NED frame, in tiles on demand."""

    def __init__(
        self,
        cell_size_m: float = 1.0,
        tile_cells: int = 32,
        *,
        spread_sigma: float = 2.0,
        max_spread_cells: int = 3,
        min_height_sigma_m: float = 0.05,
        max_horizontal_sigma_m: float = 2.0,
        gate_sigma: float = 3.0,
        below_gate_sigma: float = 3.0,
        gate_min_count: int = 2,
        reset_evidence: float = 20.0,
        process_noise_m2: float = 1e-4,
        max_abs_coordinate_m: float = 1e6,
        carve_start_m: float = 2.0,
        carve_end_margin_m: float = 1.5,
        carve_margin_m: float = 0.5,
        carve_rays: float = 3.0,
        carve_lateral_sigma_m: float = 0.5,
        lone_rise_m: float = 1.5,
        lone_block_cells: int = 4,
        frame_tracker: FrameTracker | None = None,
    ) -> None:
        if not (np.isfinite(cell_size_m) and cell_size_m > 0):
            raise ValueError(f"cell_size_m must be positive and finite, got {cell_size_m}")
        if not (1 <= int(tile_cells) <= 0xFFFF):
            raise ValueError(f"tile_cells must be in 1..65535, got {tile_cells}")
        if max_abs_coordinate_m / (cell_size_m * tile_cells) >= 2**30:
            raise ValueError("max_abs_coordinate_m is too large for the tile key range")
        self.cell_size_m = float(cell_size_m)
        self.tile_cells = int(tile_cells)
        self.spread_sigma = float(spread_sigma)
        self.max_spread_cells = int(max_spread_cells)
        self.min_height_sigma_m = float(min_height_sigma_m)
        self.max_horizontal_sigma_m = float(max_horizontal_sigma_m)
        self.gate_sigma = float(gate_sigma)
        self.below_gate_sigma = float(below_gate_sigma)
        self.gate_min_count = int(gate_min_count)
        self.reset_evidence = float(reset_evidence)
        self.process_noise_m2 = float(process_noise_m2)
        self.max_abs_coordinate_m = float(max_abs_coordinate_m)
        self.carve_start_m = float(carve_start_m)
        self.carve_end_margin_m = float(carve_end_margin_m)
        self.carve_margin_m = float(carve_margin_m)
        self.carve_rays = float(carve_rays)
        self.carve_lateral_sigma_m = float(carve_lateral_sigma_m)
        if not (lone_rise_m > 0):
            raise ValueError(f"lone_rise_m must be positive (inf: off), got {lone_rise_m}")
        if not int(lone_block_cells) >= 1:
            raise ValueError(f"lone_block_cells must be at least 1, got {lone_block_cells}")
        self.lone_rise_m = float(lone_rise_m)
        # Blocks tile the tiles: the largest divisor of tile_cells not above the setting.
        self.lone_block_cells = max(d for d in range(1, min(int(lone_block_cells), self.tile_cells) + 1)
                                    if self.tile_cells % d == 0)
        # The map's vertical frame kept on the navigation's (frame.py); None: never moved.
        self.frame = frame_tracker
        # Every height is stored in the map's own frame (the frame its evidence was first fused in);
        # the navigation's frame is that plus this offset (m, up): moving the map is one addition,
        # and a tile changes only when its evidence does (docs/terrain.md, "The navigation's frame").
        self._offset = 0.0
        self._shifts = 0
        self._epoch: float | None = None  # time of the first evidence: the update layer counts from it
        t = self.tile_cells
        self._cells_per_tile = t * t
        self._n_tiles = 0
        self._keys = np.zeros(0, dtype=np.int64)  # sorted packed keys
        self._key_slots = np.zeros(0, dtype=np.int64)  # pool slot of each sorted key
        self._slot_key: list[tuple[int, int]] = []
        self._alloc(0)
        # Pending floors (docs/terrain.md, "Floors"): a bound seen once, waiting for a second. Few
        # cells hold one, so they are a side table (pool cell indices, sorted; heights), not a layer.
        self._pf_cells = np.zeros(0, dtype=np.int64)
        self._pf_height = np.zeros(0)
        # The features whose lines of sight passed under a cell while its disagreement stands
        # (pool cell index -> feature ids; few cells at a time, "Free space").
        self._contradicted_by: dict[int, set[int]] = {}
        # Which feature set each floor (pool cells, sorted; feature ids): a floor follows its feature.
        self._fo_cells = np.zeros(0, dtype=np.int64)
        self._fo_ids = np.zeros(0, dtype=np.int64)
        self._dirty: set[tuple[int, int]] = set()
        # Conservative bounds on every known height (may be stale-wide after a cell is lowered).
        self._h_lo = np.inf
        self._h_hi = -np.inf

    @classmethod
    def from_config(cls, cfg: TerrainConfig) -> "TerrainGrid":
        return cls(
            cfg.cell_size_m,
            cfg.tile_cells,
            spread_sigma=cfg.spread_sigma,
            max_spread_cells=cfg.max_spread_cells,
            min_height_sigma_m=cfg.min_height_sigma_m,
            max_horizontal_sigma_m=cfg.max_horizontal_sigma_m,
            gate_sigma=cfg.gate_sigma,
            below_gate_sigma=cfg.below_gate_sigma,
            gate_min_count=cfg.gate_min_count,
            reset_evidence=cfg.reset_evidence,
            process_noise_m2=cfg.process_noise_m2,
            max_abs_coordinate_m=cfg.max_abs_coordinate_m,
            carve_start_m=cfg.carve_start_m,
            carve_end_margin_m=cfg.carve_end_margin_m,
            carve_margin_m=cfg.carve_margin_m,
            carve_rays=cfg.carve_rays,
            carve_lateral_sigma_m=cfg.carve_lateral_sigma_m,
            lone_rise_m=cfg.lone_rise_m,
            lone_block_cells=cfg.lone_block_cells,
            frame_tracker=FrameTracker(cfg.frame_min_age_s, cfg.frame_window_s, cfg.frame_min_points,
                                       cfg.frame_max_offset_m, cfg.frame_deadband_m) if cfg.frame_tracking else None,
        )

    # ---------------------------------------------------------------------------------- storage

    def _alloc(self, capacity: int) -> None:
        t = self.tile_cells
        self._h = np.full((capacity, t, t), np.nan, dtype=np.float32)
        self._v = np.full((capacity, t, t), np.inf, dtype=np.float32)
        self._n = np.zeros((capacity, t, t), dtype=np.uint32)
        self._d = np.zeros((capacity, t, t), dtype=np.float32)  # evidence from below (points)
        self._p = np.full((capacity, t, t), np.nan, dtype=np.float32)  # pending higher height (m)
        self._c = np.full((capacity, t, t), np.inf, dtype=np.float32)  # ceiling: free space above (m)
        self._w = np.zeros((capacity, t, t), dtype=np.float32)  # evidence weight: points' shares agreeing
        self._f = np.full((capacity, t, t), -np.inf, dtype=np.float32)  # floor: the least the terrain reaches (m)
        self._u = np.full((capacity, t, t), -np.inf, dtype=np.float32)  # last height update (s since _epoch)

    def _layers(self) -> tuple[np.ndarray, ...]:
        return (self._h, self._v, self._n, self._d, self._p, self._c, self._w, self._f, self._u)

    def _grow(self, needed: int) -> None:
        cap = len(self._h)
        if needed <= cap:
            return
        old = self._layers()
        self._alloc(max(needed, cap + cap // 2, 16))
        for new, o in zip(self._layers(), old):
            new[: self._n_tiles] = o[: self._n_tiles]

    def _slots_of(self, keys: np.ndarray) -> np.ndarray:
        """Pool slot of each packed key, -1 where the tile does not exist. keys: (M,) int64."""
        if self._n_tiles == 0:
            return np.full(keys.shape, -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self._keys, keys), self._n_tiles - 1)
        return np.where(self._keys[pos] == keys, self._key_slots[pos], -1)

    def _ensure_tiles(self, keys: np.ndarray) -> np.ndarray:
        """Pool slots of unique packed ``keys``, creating the missing tiles. A new tile is dirty (to
        be published) even if it holds no height yet: carving and floors create tiles too, and every
        tile the map holds is one a subscriber or a map query gets."""
        slots = self._slots_of(keys)
        missing = slots < 0
        if missing.any():
            new_keys = keys[missing]
            first = self._n_tiles
            self._grow(first + len(new_keys))
            new_slots = np.arange(first, first + len(new_keys), dtype=np.int64)
            self._n_tiles += len(new_keys)
            tx, ty = unpack_key(new_keys)
            self._slot_key.extend(zip(tx.tolist(), ty.tolist()))
            self._dirty.update(zip(tx.tolist(), ty.tolist()))
            keys_all = np.concatenate([self._keys, new_keys])
            slots_all = np.concatenate([self._key_slots, new_slots])
            order = np.argsort(keys_all, kind="stable")
            self._keys, self._key_slots = keys_all[order], slots_all[order]
            slots[missing] = new_slots
        return slots

    def _pool_cells(self, north_m: np.ndarray, east_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The distinct cells holding positions (M,), as flat indices into the pool's layers, sorted,
        and each position's index into them (creating the tiles that do not exist yet)."""
        keys, local = self._cells(*self.cell_index(north_m, east_m))
        uk, where = np.unique(keys, return_inverse=True)
        return np.unique(self._ensure_tiles(uk)[where] * self._cells_per_tile + local, return_inverse=True)

    def _cells(self, ci: np.ndarray, cj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global cell indices -> (packed tile key, index inside the tile's flattened layers)."""
        t = self.tile_cells
        if t & (t - 1) == 0:  # power of two: an arithmetic shift is floor division, also below zero
            b = t.bit_length() - 1
            tx, ty = ci >> b, cj >> b
            return pack_key(tx, ty), ((ci & (t - 1)) << b) | (cj & (t - 1))
        tx, ty = np.floor_divide(ci, t), np.floor_divide(cj, t)
        return pack_key(tx, ty), (ci - tx * t) * t + (cj - ty * t)

    def _gather(self, ci: np.ndarray, cj: np.ndarray, bounds: bool = False) -> tuple[np.ndarray, ...]:
        """(height, variance, count) of cells by global index; NaN / inf / 0 where no tile. With
        ``bounds`` also (ceiling, floor, evidence weight): inf / -inf / 0 where no tile. Heights,
        ceilings and floors in the navigation's frame."""
        keys, local = self._cells(ci, cj)
        slots = self._slots_of(keys)
        have = slots >= 0
        flat = np.where(have, slots * self._cells_per_tile + local, 0)
        layers = [(self._h, np.nan, np.float64), (self._v, np.inf, np.float64), (self._n, 0, np.int64)]
        if bounds:
            layers += [(self._c, np.inf, np.float64), (self._f, -np.inf, np.float64), (self._w, 0.0, np.float64)]
        if not self._n_tiles:
            return tuple(np.full(len(ci), empty, dtype=dt) for _, empty, dt in layers)
        if have.all():  # every cell in a tile (a query over mapped ground): no stand-in values
            out = [layer.reshape(-1)[flat].astype(dt) for layer, _, dt in layers]
        else:
            out = [np.where(have, layer.reshape(-1)[flat], empty).astype(dt) for layer, empty, dt in layers]
        if self._offset:
            for i in (0, 3, 4)[: len(out) - 2]:  # height; ceiling and floor (inf and NaN stay)
                out[i] += self._offset
        return tuple(out)

    # ----------------------------------------------------------------------------------- fusion

    def add_evidence(self, points: TerrainPoints, free_space: FreeSpaceRays | None = None,
                     floors: TerrainFloors | None = None) -> InsertStats:
        """One frame's evidence, in order: the free space its lines of sight crossed
        (:meth:`carve`), its converged points (:meth:`insert`, whose statistics are returned), then
        the floors of its features not yet converged (:meth:`raise_floors`): a point replaces its
        cell's floor, and the features still unconverged raise theirs again after it; last, the
        floors of the features that ended, where nothing near them backs them
        (:meth:`withdraw_ended_floors`, counted in the returned ``lone_floors``)."""
        if free_space is not None and len(free_space):
            self.carve(free_space)
        stats = self.insert(points) if len(points) else InsertStats()
        if floors is not None and len(floors):
            self.raise_floors(floors)
        if floors is not None and floors.n_ended:
            stats = replace(stats, lone_floors=self.withdraw_ended_floors(floors.ended_ids))
        return stats

    def add_flow(self, surface: TerrainPoints, floors: TerrainFloors) -> InsertStats:
        """One frame of the dense flow's evidence (docs/mapper.md, "Surfaces seen by dense flow"):
        its flat surfaces' heights (:meth:`insert`, keeping the floors, which no feature's bound
        foresaw, and raising no cell: a height far above a cell is an outlier), then the floors of
        the cells that rose (:meth:`raise_floors`)."""
        stats = self.insert(surface, keep_floors=True, raises=False) if len(surface) else InsertStats()
        if len(floors):
            self.raise_floors(floors)
        return stats

    def insert(self, points: TerrainPoints, keep_floors: bool = False, raises: bool = True) -> InsertStats:
        """Fuse a batch of converged points (docs/terrain.md, "Fusion"): each cell keeps its top
        surface. A changed cell's floor goes (a feature's bound, now its point), unless
        ``keep_floors``: evidence no feature's bound foresaw (the flow's surfaces, docs/terrain.md,
        "Floors") leaves the floors to the features that set them. With ``raises`` False a point
        far above its cell is an outlier, neither a higher surface nor a pending one: evidence of a
        flat surface's height (the flow's) is as likely too high as too low, so only the features'
        points raise a cell to a higher surface.

        Invalid points are counted in ``rejected_invalid``; points whose horizontal sigma
        exceeds ``max_horizontal_sigma_m`` in ``rejected_imprecise``; points that changed no cell's
        height (below, or above and not yet confirmed) in ``rejected_outlier``. A malformed message
        (wrong shapes) raises ValueError."""
        pos = np.asarray(points.positions_ned_m, dtype=np.float64)
        cov = np.asarray(points.covariances, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"TerrainPoints.positions_ned_m must be (N, 3), got {pos.shape}")
        if cov.shape != (len(pos), 3, 3):
            raise ValueError(f"TerrainPoints.covariances must be ({len(pos)}, 3, 3), got {cov.shape}")
        ok = fusion.valid_points(pos, cov, self.max_abs_coordinate_m)
        n_invalid = int(len(pos) - np.count_nonzero(ok))
        precise = ok.copy()
        precise[ok] = fusion.precise_points(cov[ok], self.max_horizontal_sigma_m)
        n_imprecise = int(np.count_nonzero(ok & ~precise))
        if not precise.all():
            pos, cov = pos[precise], cov[precise]
        if len(pos) == 0:
            return InsertStats(rejected_invalid=n_invalid, rejected_imprecise=n_imprecise)

        c, t2 = self.cell_size_m, self._cells_per_tile
        height = -pos[:, 2] - self._offset  # in the map's frame
        var_z = np.maximum(cov[:, 2, 2], self.min_height_sigma_m**2)
        p, ci, cj, w = fusion.horizontal_spread(
            pos[:, 0], pos[:, 1], cov[:, :2, :2], c, self.spread_sigma, self.max_spread_cells
        )
        hm = height[p]
        r = fusion.measurement_variance(var_z[p], w)
        keys, local_in_tile = self._cells(ci, cj)
        slots = self._slots_of(keys)
        missing = slots < 0
        if missing.any():
            new_keys, where = np.unique(keys[missing], return_inverse=True)
            slots[missing] = self._ensure_tiles(new_keys)[where]
        # Compact the tiles of this batch to 0..B-1 without sorting the pairs.
        in_batch = np.zeros(self._n_tiles, dtype=bool)
        in_batch[slots] = True
        batch_slots = np.flatnonzero(in_batch)
        rank = np.zeros(self._n_tiles, dtype=np.int64)
        rank[batch_slots] = np.arange(len(batch_slots))
        batch_tile = rank[slots]
        pool_flat = slots * t2 + local_in_tile
        t_s = float(points.t_s)
        if self._epoch is None and np.isfinite(t_s):
            self._epoch = t_s
        now = t_s - self._epoch if self._epoch is not None else np.nan  # NaN: a batch of no time
        h0 = self._h.reshape(-1)[pool_flat]
        v0 = self._v.reshape(-1)[pool_flat]
        n0 = self._n.reshape(-1)[pool_flat]
        if self.frame is not None and np.isfinite(now):
            old = (n0 >= self.gate_min_count) & (self._u.reshape(-1)[pool_flat] <= now - self.frame.min_age_s)
            shift = self.frame.update(now, hm[old] - h0[old], w[old])
            if shift:
                self.shift_heights(shift)
                hm, height = hm - shift, height - shift  # the same points, in the moved map's frame
        side = fusion.gate_side(hm, r, h0, v0, n0, self.gate_sigma, self.gate_min_count, self.below_gate_sigma)
        n_lone = 0
        if np.isfinite(self.lone_rise_m):
            # A point alone far above everything near it waits in the empty cells it reaches
            # (docs/terrain.md, "A lone point").
            in_empty = n0 == 0
            candidates = np.zeros(len(pos), dtype=bool)
            candidates[p[in_empty]] = True
            lone = self._lone_points(pos[:, 0], pos[:, 1], height, np.sqrt(var_z), np.flatnonzero(candidates))
            side[in_empty & lone[p]] = 1
            n_lone = int(np.count_nonzero(lone))
        agree, above, below = side == 0, side > 0, side < 0

        # Number the cells this batch touches 0..K-1 (batch tile * T^2 + cell in tile, compacted),
        # so every per-cell sum below is a bincount of length K.
        local = batch_tile * t2 + local_in_tile
        size = len(batch_slots) * t2
        seen = np.zeros(size, dtype=bool)
        seen[local] = True
        touched = np.flatnonzero(seen)
        cell_rank = np.zeros(size, dtype=np.int64)
        cell_rank[touched] = np.arange(len(touched))
        cell = cell_rank[local]
        k = len(touched)
        cell_flat = batch_slots[touched // t2] * t2 + touched % t2
        inv_r = 1.0 / r

        # Agreeing pairs: the Kalman update. Pairs below: counted; persistent, they bring the cell down.
        agree_r, below_r = agree * inv_r, below * inv_r
        info = np.bincount(cell, weights=agree_r, minlength=k)
        info_h = np.bincount(cell, weights=agree_r * hm, minlength=k)
        n_agree = np.bincount(cell, weights=agree, minlength=k)
        w_agree = np.bincount(cell, weights=agree * w, minlength=k)
        w_new = self._w.reshape(-1)[cell_flat].astype(np.float64)
        h_new = self._h.reshape(-1)[cell_flat].astype(np.float64)
        v_new = self._v.reshape(-1)[cell_flat].astype(np.float64)
        n_new = self._n.reshape(-1)[cell_flat].astype(np.float64)
        pending = self._p.reshape(-1)[cell_flat].astype(np.float64)
        d_new = self._d.reshape(-1)[cell_flat].astype(np.float64)
        update = n_agree > 0
        reset = np.zeros(k, dtype=bool)
        if below.any():
            below_w = np.bincount(cell, weights=below * w, minlength=k)
            d_new = fusion.disagreement_update(d_new, w_agree, below_w)
            reset = d_new >= self.reset_evidence
            if reset.any():  # the lower heights become the cell's evidence, on an unknown prior
                info[reset] = np.bincount(cell, weights=below_r, minlength=k)[reset]
                info_h[reset] = np.bincount(cell, weights=below_r * hm, minlength=k)[reset]
                n_agree[reset] = np.bincount(cell, weights=below, minlength=k)[reset]
                w_agree[reset] = below_w[reset]
                v_new[reset], n_new[reset], d_new[reset], pending[reset], w_new[reset] = np.inf, 0.0, 0.0, np.nan, 0.0
                update |= reset
        elif update.any():
            d_new[update] = 0.0
        h1, v1 = fusion.fuse_information(h_new[update], v_new[update], info[update], info_h[update], self.process_noise_m2)
        h_new[update], v_new[update] = h1, v1
        # An empty cell's first evidence settles a lone point it held as pending at or below it.
        with np.errstate(invalid="ignore"):
            settled = update & (n_new == 0) & (pending <= h_new + self.gate_sigma * np.sqrt(v_new))
        pending[settled] = np.nan
        n_new[update] += n_agree[update]
        w_new[update] += w_agree[update]

        # Pairs above: a higher surface, taken once confirmed; else it waits as the pending height.
        raised = np.zeros(k, dtype=bool)
        if above.any() and raises:
            up = np.flatnonzero(above)
            h1, r1, h2, r2 = fusion.highest_two(cell[up], hm[up], r[up], k)
            raised, h_r, v_r, pending = fusion.confirm_raise(h1, r1, h2, r2, pending, self.gate_sigma)
            h_new[raised], v_new[raised], n_new[raised], d_new[raised] = h_r[raised], v_r[raised], 2.0, 0.0
            w_new[raised] = 1.0  # a top surface: its pair's variance stands, as one point's
            # A confirmed surface above the free space seen before is newer than it: the old lines
            # of sight no longer bound the cell (docs/terrain.md, "Free space").
            above_ceiling = raised & (h_new > self._c.reshape(-1)[cell_flat])
            if above_ceiling.any():
                self._c.reshape(-1)[cell_flat[above_ceiling]] = np.inf

        self._h.reshape(-1)[cell_flat] = h_new
        self._v.reshape(-1)[cell_flat] = v_new
        self._n.reshape(-1)[cell_flat] = np.minimum(n_new, _COUNT_MAX)
        self._w.reshape(-1)[cell_flat] = w_new
        self._d.reshape(-1)[cell_flat] = d_new
        self._p.reshape(-1)[cell_flat] = pending
        changed = update | raised
        if np.isfinite(now):
            self._u.reshape(-1)[cell_flat[changed]] = now
        if changed.any():
            if not keep_floors:
                # The cell's own evidence replaces the floor (docs/terrain.md, "Floors"): a floor
                # left by a feature that has since converged elsewhere, or died, goes with it.
                self._f.reshape(-1)[cell_flat[changed]] = -np.inf
                self._drop_pending_floors(cell_flat[changed])
            hc = h_new[changed]
            self._h_lo = min(self._h_lo, float(hc.min()))
            self._h_hi = max(self._h_hi, float(hc.max()))

        # Every tile of the batch holds at least one touched cell.
        self._dirty.update(self._slot_key[s] for s in batch_slots.tolist())
        used_pair = np.where(reset[cell], below, agree) | (above & raised[cell])
        used_points = np.bincount(p, weights=used_pair, minlength=len(pos)) > 0
        n_used = int(np.count_nonzero(used_points))
        return InsertStats(
            inserted=n_used,
            rejected_invalid=n_invalid,
            rejected_outlier=int(len(pos) - n_used),
            rejected_imprecise=n_imprecise,
            cells_touched=k,
            cells_raised=int(np.count_nonzero(raised)),
            cells_reset=int(np.count_nonzero(reset & ~raised)),
            lone_points=n_lone,
        )

    def _lone_points(self, north_m: np.ndarray, east_m: np.ndarray, height: np.ndarray, sigma_m: np.ndarray,
                     candidates: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the batch's points (``north_m``, ``east_m``, ``height`` in the map's
        frame, height sigma ``sigma_m``, each (N,)) whose index is in ``candidates`` stand alone
        (docs/terrain.md, "A lone point"): more than ``max(lone_rise_m, gate_sigma sigma)`` above
        every height near them. Near = the 3x3 blocks of ``lone_block_cells`` cells around the
        point's own block (a point sees 1 to 2 blocks of terrain on every side); the heights = the
        map's there (mapped cells, pending heights, floors) and the batch's other points."""
        lone = np.zeros(len(height), dtype=bool)
        if len(candidates) == 0:
            return lone
        b = self.lone_block_cells
        ci, cj = self.cell_index(north_m, east_m)
        bi, bj = np.floor_divide(ci, b), np.floor_divide(cj, b)
        # The batch: the highest two points of each block (a point is not its own support).
        bkeys, bcell = np.unique(pack_key(bi, bj), return_inverse=True)
        h1, h2 = fusion.highest_two_per_cell(bcell, height, len(bkeys))
        # The candidates' distinct blocks and the 3x3 blocks around each: (U, 9), their own first.
        ublocks, of_candidate = np.unique(bcell[candidates], return_inverse=True)
        ubi, ubj = unpack_key(bkeys[ublocks])
        ni, nj = ubi[:, None] + _AROUND_DI, ubj[:, None] + _AROUND_DJ
        nkeys = pack_key(ni, nj)
        at = np.minimum(np.searchsorted(bkeys, nkeys), len(bkeys) - 1)
        around = np.where(bkeys[at] == nkeys, h1[at], -np.inf)
        around[:, 0] = -np.inf  # the candidate's own block: its batch's other points, below
        own = bcell[candidates]
        hc = height[candidates]
        support = np.fmax(around.max(axis=1)[of_candidate], np.where(hc >= h1[own], h2[own], h1[own]))
        rise = np.maximum(self.lone_rise_m, self.gate_sigma * sigma_m[candidates])
        alone = hc > support + rise
        if alone.any():
            # The map, for the candidates their batch does not support.
            need, of_alone = np.unique(of_candidate[alone], return_inverse=True)
            mapped = self._highest_around_blocks(ubi[need], ubj[need])[of_alone]
            alone[alone] = hc[alone] > mapped + rise[alone]
        lone[candidates] = alone
        return lone

    def _highest_around_blocks(self, bi: np.ndarray, bj: np.ndarray) -> np.ndarray:
        """(U,) the highest height the map holds (mapped cell, pending height, floor; -inf none) in
        the 3x3 blocks of ``lone_block_cells`` cells around each block (``bi``, ``bj``) (U,)."""
        b, per_tile = self.lone_block_cells, self.tile_cells // self.lone_block_cells
        mi, mj = bi[:, None] + _AROUND_DI, bj[:, None] + _AROUND_DJ
        tx, ty = np.floor_divide(mi, per_tile), np.floor_divide(mj, per_tile)
        tile_keys, where = np.unique(pack_key(tx, ty).ravel(), return_inverse=True)
        slots = self._slots_of(tile_keys)
        top = np.full((len(tile_keys), per_tile * per_tile), -np.inf)
        have = np.flatnonzero(slots >= 0)
        if len(have):
            s = slots[have]
            with np.errstate(invalid="ignore"):
                cell_top = np.fmax(np.fmax(np.where(self._n[s] > 0, self._h[s], np.nan), self._p[s]), self._f[s])
            top[have] = np.nan_to_num(cell_top.reshape(len(s), per_tile, b, per_tile, b).max(axis=(2, 4)),
                                      nan=-np.inf).reshape(len(s), -1)
        local = (mi - tx * per_tile) * per_tile + (mj - ty * per_tile)
        return top[where.reshape(mi.shape), local].max(axis=1)

    def carve(self, rays: FreeSpaceRays) -> CarveStats:
        """Visibility carving (docs/terrain.md, "Free space"): every segment of ``rays`` crossed
        the columns of the cells below it at the segment's height there, so the terrain in each
        is lower. Per cell the ceiling keeps the lowest such height.

        The segment is sampled every half cell, horizontally, from ``carve_start_m`` off the camera
        (nearer, a line of sight at the camera's own height bounds nothing) to
        ``carve_end_margin_m`` short of its end (a feature's own cell, and a wall whose face it
        lies on, are never carved). A ray passing more than ``gate_sigma`` sigma +
        ``carve_margin_m`` under a cell's height contradicts it: each feature that does counts
        ``reset_evidence / carve_rays`` of disagreement (the evidence-from-below counter, which any
        agreeing point clears), and a cell that reaches ``reset_evidence`` loses its height: a
        phantom does not survive the lines of sight of ``carve_rays`` features through it (a feature
        counts once: :meth:`_new_contradicting_features`). A pending higher height a ray passed
        under is dropped, and so is a floor (:meth:`raise_floors`). Heights, pending heights and
        floors are taken away only where the segment's lateral sigma (its horizontal distance from
        the camera times ``rays.angle_sigma_rad``) is at most ``carve_lateral_sigma_m``: farther, the
        line of sight may have passed beside the cell (a thin mast 2.6 m to its side at 30 m, for a
        heading 5 deg off); every sample lowers ceilings. Invalid rays (non-finite, beyond
        ``max_abs_coordinate_m``) are skipped."""
        o = np.asarray(rays.origin_ned_m, dtype=np.float64).reshape(3)
        ends = np.asarray(rays.ends_ned_m, dtype=np.float64).reshape(-1, 3)
        if rays.feature_ids is not None and np.shape(rays.feature_ids) != (len(ends),):
            raise ValueError(f"free space: feature_ids must have shape ({len(ends)},), got {np.shape(rays.feature_ids)}")
        lim = self.max_abs_coordinate_m
        if len(ends) == 0 or not (np.isfinite(o).all() and np.abs(o).max() <= lim):
            return CarveStats()
        good = np.isfinite(ends).all(axis=1) & (np.abs(ends) <= lim).all(axis=1)
        ends = ends[good]
        use_idx = np.flatnonzero(good)
        d_ne = ends[:, :2] - o[:2]
        length = np.sqrt((d_ne * d_ne).sum(axis=1))
        reach = length - self.carve_end_margin_m
        use = reach > max(self.carve_start_m, 0.0)  # a segment must reach past where carving starts
        if not use.any():
            return CarveStats(rays=int(len(ends)))
        if not use.all():
            ends, d_ne, length, reach, use_idx = ends[use], d_ne[use], length[use], reach[use], use_idx[use]
        step = 0.5 * self.cell_size_m
        start = self.carve_start_m
        n_s = int(np.ceil((reach.max() - start) / step)) + 1
        raw = start + step * np.arange(n_s)[None, :]
        s = np.minimum(raw, reach[:, None])  # (K, S) horizontal distance
        # A shorter segment's samples beyond its end all sit at the end: one of them is enough.
        take = raw < reach[:, None] + step
        ray = np.broadcast_to(np.arange(len(ends))[:, None], s.shape)[take]
        frac = s[take] / length[ray]
        north = o[0] + frac * d_ne[ray, 0]
        east = o[1] + frac * d_ne[ray, 1]
        alt = -o[2] + frac * (o[2] - ends[ray, 2]) - self._offset  # in the map's frame
        cells, inv = self._pool_cells(north, east)
        low = np.full(len(cells), np.inf)
        np.minimum.at(low, inv, alt)
        c_old = self._c.reshape(-1)[cells]
        lowered = low < c_old
        self._c.reshape(-1)[cells[lowered]] = low[lowered]
        # Evidence is taken away only where the line of sight is known to have crossed the cell:
        # its lateral sigma (horizontal distance x the attitude's sigma) within carve_lateral_sigma_m.
        sure = s[take] * max(float(rays.angle_sigma_rad), 0.0) <= self.carve_lateral_sigma_m
        if not sure.all():
            alt = np.where(sure, alt, np.inf)
            low = np.full(len(cells), np.inf)
            np.minimum.at(low, inv, alt)

        h = self._h.reshape(-1)[cells].astype(np.float64)
        v = self._v.reshape(-1)[cells].astype(np.float64)
        p = self._p.reshape(-1)[cells].astype(np.float64)
        with np.errstate(invalid="ignore"):
            thr = h - self.gate_sigma * np.sqrt(v) - self.carve_margin_m  # a segment below this contradicts the cell
            under = (self._n.reshape(-1)[cells] > 0) & (low < thr)
            drop_pending = low < p
        if drop_pending.any():
            self._p.reshape(-1)[cells[drop_pending]] = np.nan
        drop_floor = low < self._f.reshape(-1)[cells]
        if drop_floor.any():  # a line of sight passed below the least the terrain was to reach
            self._f.reshape(-1)[cells[drop_floor]] = -np.inf
        if len(self._pf_cells):
            self._drop_pending_floors(cells[low < self._pending_floors(cells)])
        cleared = np.zeros(0, dtype=np.int64)
        if under.any():
            u = cells[under]
            looks = np.ones(len(u))
            if rays.feature_ids is not None:
                looks = self._new_contradicting_features(u, under, inv, alt < thr[inv], np.asarray(rays.feature_ids)[use_idx][ray])
            u, looks = u[looks > 0], looks[looks > 0]
            d = self._d.reshape(-1)[u] + looks * (self.reset_evidence / self.carve_rays)
            gone = d >= self.reset_evidence * (1.0 - 1e-6)  # the layer is float32: thirds do not sum exactly
            d[gone] = 0.0
            self._d.reshape(-1)[u] = d
            cleared = u[gone]
            for k in cleared.tolist():
                self._contradicted_by.pop(k, None)
            if len(cleared):
                self._h.reshape(-1)[cleared] = np.nan
                self._v.reshape(-1)[cleared] = np.inf
                self._n.reshape(-1)[cleared] = 0
                self._w.reshape(-1)[cleared] = 0.0
                self._p.reshape(-1)[cleared] = np.nan
                self._f.reshape(-1)[cleared] = -np.inf
                self._u.reshape(-1)[cleared] = -np.inf
                self._drop_pending_floors(cleared)
                self._dirty.update(self._slot_key[int(k)] for k in np.unique(cleared // self._cells_per_tile).tolist())
        return CarveStats(rays=int(len(ends)), cells_lowered=int(np.count_nonzero(lowered)),
                          cells_passed_under=int(np.count_nonzero(under)), cells_cleared=int(len(cleared)),
                          pending_dropped=int(np.count_nonzero(drop_pending)), floors_dropped=int(np.count_nonzero(drop_floor)))

    def _new_contradicting_features(self, u: np.ndarray, under: np.ndarray, inv: np.ndarray, sample_below: np.ndarray,
                                    sample_ids: np.ndarray) -> np.ndarray:
        """Per cell of ``u`` (the carved cells a segment passed under, ``cells[under]``): how many
        features not counted against it before passed under it this frame (:meth:`carve`).

        A feature counts once per cell while the cell's disagreement stands (the memory of a cell
        whose disagreement an agreeing point cleared is stale and forgotten): the same feature
        seen again says what it said before, so a feature tracked wrongly (its range past the
        surface it lies on: occluded, or sliding along an outline) cannot clear a surface alone,
        however many frames it lasts. inv, sample_below, sample_ids: each segment sample's cell
        (index into the carved cells), whether it passed under that cell's contradiction threshold,
        and its feature."""
        below = under[inv] & sample_below
        rank = np.full(len(under), -1, dtype=np.int64)
        rank[under] = np.arange(len(u))
        pairs = np.unique(np.stack([rank[inv[below]], sample_ids[below]], axis=1), axis=0)
        looks = np.zeros(len(u))
        d_now = self._d.reshape(-1)[u]
        memory = self._contradicted_by
        fresh = d_now <= 0.0  # no disagreement stands: whatever the memory holds is stale
        for r, fid in pairs.tolist():
            cell = int(u[r])
            seen = memory.get(cell)
            if seen is None or fresh[r]:
                seen = memory[cell] = set()
                fresh[r] = False
            if fid not in seen:
                seen.add(fid)
                looks[r] += 1.0
        if len(memory) > _CONTRADICTION_MEMORY:
            d_all = self._d.reshape(-1)
            for cell in [c for c in memory if d_all[c] <= 0.0]:
                del memory[cell]
        return looks

    def raise_floors(self, floors: TerrainFloors) -> int:
        """Lower bounds on the terrain's height (docs/terrain.md, "Floors"): the floor of the cell
        of each row of ``floors`` becomes at least that row's height once a second bound confirms
        it, in the same batch or a later one (:func:`fusion.confirm_floor`: the floor rises to the
        second highest bound; the highest waits). A floor is not evidence of
        where the surface is (the map's height and variance are untouched, nor is it published):
        it is the least the terrain there reaches, which the avoidance law keeps clear of until the
        cell's own evidence says more. A line of sight passing below it drops it (:meth:`carve`),
        and a bound more than ``carve_margin_m`` above the cell's ceiling (a line of sight crossed
        it lower before) lifts nothing, nor waits. With ``floors.feature_ids`` a floor follows the
        feature that set it: once that feature bounds another cell, the floor goes
        (:meth:`_withdraw_left_floors`); a row with a negative id belongs to no feature (a rise seen
        by dense flow) and its floor stays until a point or a line of sight ends it. Invalid rows (non-finite, beyond
        ``max_abs_coordinate_m``) are skipped. Returns the number of cells whose floor rose."""
        pts = np.asarray(floors.positions_ned_m, dtype=np.float64).reshape(-1, 3)
        good = np.isfinite(pts).all(axis=1) & (np.abs(pts) <= self.max_abs_coordinate_m).all(axis=1)
        ids = None if floors.feature_ids is None else np.asarray(floors.feature_ids, dtype=np.int64).reshape(-1)[good]
        pts = pts[good]
        if len(pts) == 0:
            return 0
        cells, inv = self._pool_cells(pts[:, 0], pts[:, 1])
        if ids is not None:
            owned = ids >= 0  # a negative id: a bound no feature owns (dense flow's rises)
            if owned.any():
                self._withdraw_left_floors(ids[owned], cells[inv[owned]])
        # A line of sight already crossed the cell below the bound: the terrain there is lower (the
        # same evidence that drops a floor in carve, seen in the other order).
        under_ceiling = -pts[:, 2] - self._offset <= self._c.reshape(-1)[cells][inv] + self.carve_margin_m
        if not under_ceiling.all():
            pts = pts[under_ceiling]
            ids = None if ids is None else ids[under_ceiling]
            if len(pts) == 0:
                return 0
            cells, inv = np.unique(cells[inv[under_ceiling]], return_inverse=True)  # the rows' cells, kept
        h1, h2 = fusion.highest_two_per_cell(inv, -pts[:, 2] - self._offset, len(cells))
        floor, pending = fusion.confirm_floor(h1, h2, self._pending_floors(cells))
        # A bound in a neighbouring cell, of this batch or waiting, confirms too, at the lower of the
        # two: a feature's estimate moves by a cell or more between frames while it converges.
        first = np.zeros(len(cells), dtype=np.int64)
        first[inv[::-1]] = np.arange(len(inv))[::-1]
        ci, cj = self.cell_index(pts[first, 0], pts[first, 1])
        keys, local = self._cells((ci + _NEIGHBOUR_DI[:, None]).ravel(), (cj + _NEIGHBOUR_DJ[:, None]).ravel())
        slots = self._slots_of(keys)
        flat = np.where(slots >= 0, slots * self._cells_per_tile + local, -1)  # (8 K,) -1: no tile
        at = np.minimum(np.searchsorted(cells, flat), len(cells) - 1)
        near = np.fmax(self._pending_floors(flat), np.where(cells[at] == flat, h1[at], -np.inf))
        support = near.reshape(len(_NEIGHBOUR_DI), len(cells)).max(axis=0)
        floor = np.fmax(floor, np.fmin(h1, support))
        old = self._f.reshape(-1)[cells]
        raised = floor > old
        self._f.reshape(-1)[cells[raised]] = floor[raised]
        if ids is not None and raised.any():  # the feature of each raised cell's highest bound owns it
            order = np.lexsort((pts[:, 2], inv))  # by cell, then highest first (NED down ascending)
            top = np.full(len(cells), -1, dtype=np.int64)
            top[inv[order[::-1]]] = ids[order[::-1]]
            keep = ~np.isin(self._fo_cells, cells[raised])
            mine = raised & (top >= 0)  # an unowned bound's floor is nobody's to move
            c = np.concatenate([self._fo_cells[keep], cells[mine]])
            o = np.concatenate([self._fo_ids[keep], top[mine]])
            order = np.argsort(c)
            self._fo_cells, self._fo_ids = c[order], o[order]
        waits = pending > np.fmax(old, floor)
        self._drop_pending_floors(cells)
        c = np.concatenate([self._pf_cells, cells[waits]])
        h = np.concatenate([self._pf_height, pending[waits]])
        order = np.argsort(c)
        self._pf_cells, self._pf_height = c[order], h[order]
        return int(np.count_nonzero(raised))

    def _withdraw_left_floors(self, ids: np.ndarray, cells_now: np.ndarray) -> None:
        """A feature bounding another cell now (``ids`` (K,) with their cells ``cells_now``) no longer
        says anything of the cell it raised a floor in before: that floor goes (docs/terrain.md,
        "Floors"). Entries whose floor has gone otherwise are forgotten."""
        if not len(self._fo_cells):
            return
        alive = np.isfinite(self._f.reshape(-1)[self._fo_cells])
        self._fo_cells, self._fo_ids = self._fo_cells[alive], self._fo_ids[alive]
        if not len(self._fo_cells):
            return
        order = np.argsort(ids)
        sid, scell = ids[order], cells_now[order]
        at = np.minimum(np.searchsorted(sid, self._fo_ids), len(sid) - 1)
        reporting = sid[at] == self._fo_ids
        # a feature has one row per batch; a row in the same cell keeps the floor it owns
        left = reporting & (scell[at] != self._fo_cells)
        if left.any():
            self._f.reshape(-1)[self._fo_cells[left]] = -np.inf
            self._fo_cells, self._fo_ids = self._fo_cells[~left], self._fo_ids[~left]

    def withdraw_ended_floors(self, ended_ids: np.ndarray) -> int:
        """The features ``ended_ids`` (E,) left the mapper (docs/terrain.md, "A floor whose feature
        ended"): a floor one of them raised, and still owns, says nothing any more. It goes if it
        stands alone: more than ``lone_rise_m`` above every height the map holds (mapped cell,
        pending height, another floor) in the 3x3 blocks of ``lone_block_cells`` cells around its
        cell's block. The ended features' floors do not back each other (each is judged with all
        of them gone). One backed by a height near it stays, unowned, as a floor of a feature that
        died did before: the warning of a face's top whose feature did not live to converge.
        Returns the number of floors withdrawn."""
        ended_ids = np.asarray(ended_ids, dtype=np.int64).reshape(-1)
        if not len(self._fo_cells) or not len(ended_ids):
            return 0
        ended = np.isin(self._fo_ids, ended_ids)
        if not ended.any():
            return 0
        cells = self._fo_cells[ended]
        self._fo_cells, self._fo_ids = self._fo_cells[~ended], self._fo_ids[~ended]
        floors = self._f.reshape(-1)[cells]
        owned = np.isfinite(floors)  # a floor since dropped (a point, a line of sight) is not theirs
        cells, floors = cells[owned], floors[owned]
        if not len(cells):
            return 0
        self._f.reshape(-1)[cells] = -np.inf  # judged without them
        t, b = self.tile_cells, self.lone_block_cells
        txy = np.array([self._slot_key[s] for s in (cells // self._cells_per_tile).tolist()], dtype=np.int64)
        local = cells % self._cells_per_tile
        bi = np.floor_divide(txy[:, 0] * t + local // t, b)
        bj = np.floor_divide(txy[:, 1] * t + local % t, b)
        lone = floors > self._highest_around_blocks(bi, bj) + self.lone_rise_m
        self._f.reshape(-1)[cells[~lone]] = floors[~lone]
        return int(np.count_nonzero(lone))

    def _pending_floors(self, cells: np.ndarray) -> np.ndarray:
        """The pending floor (m) of each pool cell of ``cells`` (K,), -inf none."""
        out = np.full(len(cells), -np.inf)
        if len(self._pf_cells):
            i = np.minimum(np.searchsorted(self._pf_cells, cells), len(self._pf_cells) - 1)
            hit = self._pf_cells[i] == cells
            out[hit] = self._pf_height[i[hit]]
        return out

    def _drop_pending_floors(self, cells: np.ndarray) -> None:
        if len(self._pf_cells) and len(cells):
            keep = ~np.isin(self._pf_cells, cells)
            self._pf_cells, self._pf_height = self._pf_cells[keep], self._pf_height[keep]

    @property
    def frame_shift_m(self) -> float:
        """How far (m, up) the map has been moved to follow the navigation's frame: a height in the
        map's own frame (a tile published with ``in_map_frame``) plus this is the height in the
        navigation's frame now (docs/terrain.md, "The navigation's frame")."""
        return self._offset

    @property
    def frame_shifts(self) -> int:
        """How many times the map has been moved to follow the navigation's frame."""
        return self._shifts

    def shift_heights(self, up_m: float) -> None:
        """Move the whole map up by ``up_m`` (m): every height, pending height, ceiling and floor,
        as one frame (docs/terrain.md, "The navigation's frame"); variances and counts stay. The
        map's own frame does not move (no tile changes in it): only its offset to the navigation's."""
        if not np.isfinite(up_m):
            raise ValueError(f"shift_heights: the move must be finite, got {up_m}")
        self._offset += float(up_m)
        self._shifts += 1

    # ---------------------------------------------------------------------------------- queries

    def cell_index(self, north_m, east_m) -> tuple[np.ndarray, np.ndarray]:
        """Global cell indices (floor(x / c)) of positions, as int64 arrays."""
        c = self.cell_size_m
        return (np.floor(np.asarray(north_m, dtype=np.float64) / c).astype(np.int64),
                np.floor(np.asarray(east_m, dtype=np.float64) / c).astype(np.int64))

    def height_at(self, north_m, east_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height (m, NaN unknown), variance (m^2, inf unknown) and count of the cells holding the
        given positions; inputs broadcast, outputs have their shape. Non-finite positions: unknown."""
        n, e = np.broadcast_arrays(np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64))
        finite = np.isfinite(n) & np.isfinite(e) & (np.abs(n) <= self.max_abs_coordinate_m) & (np.abs(e) <= self.max_abs_coordinate_m)
        ci, cj = self.cell_index(np.where(finite, n, 0.0), np.where(finite, e, 0.0))
        h, v, cnt = self._gather(ci.ravel(), cj.ravel())
        f = finite.ravel()
        h[~f], v[~f], cnt[~f] = np.nan, np.inf, 0
        return h.reshape(n.shape), v.reshape(n.shape), cnt.reshape(n.shape)

    def corridor(self, origin_ne, direction_ne, length_m: float, half_width_m: float) -> Corridor:
        """Cells whose centre is within ``half_width_m`` of the segment from ``origin_ne`` along the
        unit ``direction_ne`` for ``length_m`` (a disc when the length is 0), sorted along track.

        The candidates are generated row by row along the segment's major axis: in a row the cells
        within ``w`` of the line span at most ``2 w / |d_major|`` across it, so the work is
        proportional to the corridor's area, not to its bounding box.
        """
        o = np.asarray(origin_ne, dtype=np.float64).reshape(2)
        d = np.asarray(direction_ne, dtype=np.float64).reshape(2)
        length, w, c = float(length_m), float(half_width_m), self.cell_size_m
        if not (np.isfinite(o).all() and np.isfinite(d).all() and np.isfinite(length) and np.isfinite(w)):
            raise ValueError("corridor: origin, direction, length and half width must be finite")
        if length < 0 or w < 0:
            raise ValueError(f"corridor: length ({length}) and half width ({w}) must be >= 0")
        norm = float(np.hypot(*d))
        if norm == 0.0:
            if length > 0:
                raise ValueError("corridor: direction is zero")
            d = np.array([1.0, 0.0])
        else:
            d = d / norm
        major = 0 if abs(d[0]) >= abs(d[1]) else 1
        minor = 1 - major
        end = o + length * d
        lo_m, hi_m = min(o[major], end[major]), max(o[major], end[major])
        rows = np.arange(np.floor((lo_m - w) / c), np.floor((hi_m + w) / c) + 1, dtype=np.int64)
        x = (rows + 0.5) * c
        slope = d[minor] / d[major]
        y_line = o[minor] + (np.minimum(np.maximum(x, lo_m), hi_m) - o[major]) * slope
        reach = w / abs(d[major])
        j_lo = np.ceil((y_line - reach) / c - 0.5).astype(np.int64)
        j_hi = np.floor((y_line + reach) / c - 0.5).astype(np.int64)
        k = int(max(0, (j_hi - j_lo).max(initial=0))) + 1
        jj = j_lo[:, None] + np.arange(k)[None, :]
        ok = jj <= j_hi[:, None]
        ii = np.broadcast_to(rows[:, None], jj.shape)[ok]
        jj = jj[ok]
        cells = [None, None]
        cells[major], cells[minor] = ii, jj
        ci, cj = cells
        cn, ce = (ci + 0.5) * c, (cj + 0.5) * c
        rn, re = cn - o[0], ce - o[1]
        along = rn * d[0] + re * d[1]
        s = np.minimum(np.maximum(along, 0.0), length)
        inside = (rn - s * d[0]) ** 2 + (re - s * d[1]) ** 2 <= w * w
        keep = np.flatnonzero(inside)
        keep = keep[np.argsort(along[keep], kind="stable")]
        ci, cj, cn, ce, along = ci[keep], cj[keep], cn[keep], ce[keep], along[keep]
        cross = np.abs((cn - o[0]) * d[1] - (ce - o[1]) * d[0])
        h, v, cnt, ceiling, floor, weight = self._gather(ci, cj, bounds=True)
        return Corridor(cn, ce, along, cross, h, v, cnt, ceiling, v * np.where(weight > 0, np.minimum(weight, 1.0), 1.0), floor)

    def ray_range(self, origin_ned: np.ndarray, rays_ned: np.ndarray, max_range_m: float) -> np.ndarray:
        """(N,) range (m) along each unit ray from ``origin_ned`` (3,) to the first known terrain, NaN
        where none within ``max_range_m``: the mapper's depth prior (seed 000, eq. 16).

        The ray is marched at half a cell only through the altitude band that holds known terrain
        (a conservative [min, max] of every known height), and the crossing is interpolated
        linearly between the last sample above the terrain and the first at or below it. A ray
        that leaves the band downwards over unmapped ground gets NaN: where it met the ground is
        not known, and a far "hit" on mapped cells beyond would be a wrong prior.
        """
        o = np.asarray(origin_ned, dtype=np.float64).reshape(3)
        rays = np.asarray(rays_ned, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(rays), np.nan)
        if self._n_tiles == 0 or not np.isfinite(self._h_hi) or len(rays) == 0 or not np.isfinite(o).all():
            return out
        alt0 = -o[2] - self._offset  # the band of known heights is kept in the map's frame
        rz = rays[:, 2]  # altitude along the ray: alt(t) = alt0 - t * rz
        good = np.isfinite(rays).all(axis=1)
        down, up = rz > 0, rz < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = (alt0 - self._h_hi) / rz  # where the ray crosses the highest known height
            t_lo = (alt0 - self._h_lo) / rz  # ... and the lowest
        t_in = np.where(down, np.maximum(t_hi, 0.0), np.where(alt0 <= self._h_hi, 0.0, np.inf))
        t_out = np.minimum(np.where(down, t_lo, np.where(up, t_hi, np.inf)), max_range_m)
        live = good & (t_in <= t_out)
        if not live.any():
            return out
        idx = np.flatnonzero(live)
        step = 0.5 * self.cell_size_m
        # Start half a step early so a crossing right at t_in has a sample above it.
        start = np.maximum(t_in[idx] - step, 0.0)
        n_steps = int(np.ceil((t_out[idx] - start).max() / step)) + 2
        best = np.full(len(idx), np.nan)
        chunk = max(1, 200_000 // n_steps)
        for a in range(0, len(idx), chunk):
            sl = slice(a, a + chunk)
            ray = rays[idx[sl]]
            t = start[sl, None] + step * np.arange(n_steps)[None, :]
            t = np.minimum(t, t_out[idx[sl], None] + step)
            pts = o[None, None, :] + t[..., None] * ray[:, None, :]
            h, _, _ = self.height_at(pts[..., 0], pts[..., 1])
            gap = -pts[..., 2] - h  # > 0 above terrain, <= 0 at or below, NaN unknown
            hit = gap <= 0
            first = np.argmax(hit, axis=1)
            any_hit = hit[np.arange(len(first)), first]
            rows = np.flatnonzero(any_hit)
            f = first[rows]
            t_hit = t[rows, f]
            prev = np.maximum(f - 1, 0)
            g0, g1 = gap[rows, prev], gap[rows, f]
            interp = (f > 0) & np.isfinite(g0) & (g0 > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                frac = np.where(interp, g0 / (g0 - g1), 1.0)
            t0 = t[rows, prev]
            t_hit = np.where(interp, t0 + frac * (t_hit - t0), t_hit)
            res = np.full(len(first), np.nan)
            res[rows] = np.where(t_hit <= max_range_m, t_hit, np.nan)
            best[sl] = res
        out[idx] = best
        return out

    # ------------------------------------------------------------------------------ tiles & I/O

    def pop_dirty(self) -> list[tuple[int, int]]:
        """Keys of the tiles changed since the last call, sorted (for publishing)."""
        keys = sorted(self._dirty)
        self._dirty.clear()
        return keys

    def keys(self) -> list[tuple[int, int]]:
        return sorted(self._slot_key)

    def __len__(self) -> int:
        return self._n_tiles

    def __contains__(self, key) -> bool:
        return bool(self._slots_of(pack_key(np.array([key[0]]), np.array([key[1]])))[0] >= 0)

    def tile(self, key: tuple[int, int], *, with_disagreement: bool = False, in_map_frame: bool = False) -> Tile:
        """A copy of one tile's layers (with the internal ones, disagreement, pending and ceiling,
        when asked); KeyError if the tile does not exist. Heights, ceilings and floors are in the
        navigation's frame now, or with ``in_map_frame`` in the map's own frame, which moving the
        map leaves alone (what is published: add ``frame_shift_m`` for the navigation's)."""
        tx, ty = int(key[0]), int(key[1])
        slot = int(self._slots_of(pack_key(np.array([tx]), np.array([ty])))[0])
        if slot < 0:
            raise KeyError(f"no terrain tile {key}")
        up = np.float32(0.0 if in_map_frame else self._offset)

        def heights(layer: np.ndarray) -> np.ndarray:
            return layer[slot] + up if up else layer[slot].copy()

        return Tile(
            tx, ty, heights(self._h), self._v[slot].copy(), self._n[slot].copy(), self.cell_size_m,
            self._d[slot].copy() if with_disagreement else None,
            heights(self._p) if with_disagreement else None,
            heights(self._c) if with_disagreement else None,
            self._w[slot].copy() if with_disagreement else None,
            heights(self._f) if with_disagreement else None,
        )

    def tiles(self, *, with_disagreement: bool = False, in_map_frame: bool = False) -> Iterator[Tile]:
        for key in self.keys():
            yield self.tile(key, with_disagreement=with_disagreement, in_map_frame=in_map_frame)

    def put_tile(self, tile: Tile, *, in_map_frame: bool = False) -> None:
        """Replace (or create) a tile from its layers, e.g. one decoded from the wire or a snapshot;
        its heights in the navigation's frame now, or in the map's own with ``in_map_frame``
        (:meth:`tile`)."""
        if tile.tile_cells != self.tile_cells or tile.cell_size_m != self.cell_size_m:
            raise ValueError(
                f"tile {tile.key} has T={tile.tile_cells}, cell {tile.cell_size_m} m; "
                f"this grid has T={self.tile_cells}, cell {self.cell_size_m} m"
            )
        slot = int(self._ensure_tiles(pack_key(np.array([tile.tx]), np.array([tile.ty])))[0])
        down = np.float32(0.0 if in_map_frame else self._offset)
        self._h[slot], self._v[slot], self._n[slot] = tile.height - down, tile.variance, tile.count
        self._d[slot] = 0.0 if tile.disagreement is None else tile.disagreement
        self._p[slot] = np.nan if tile.pending is None else tile.pending - down
        self._c[slot] = np.inf if tile.ceiling is None else tile.ceiling - down
        self._w[slot] = np.minimum(tile.count, 1).astype(np.float32) if tile.weight is None else tile.weight
        self._f[slot] = -np.inf if tile.floor is None else tile.floor - down
        self._u[slot] = -np.inf  # evidence of another time: old (a frame the navigation has left)
        in_slot = self._pf_cells // self._cells_per_tile == slot
        self._pf_cells, self._pf_height = self._pf_cells[~in_slot], self._pf_height[~in_slot]
        mine = self._fo_cells // self._cells_per_tile == slot
        self._fo_cells, self._fo_ids = self._fo_cells[~mine], self._fo_ids[~mine]
        known = tile.count > 0
        if known.any():
            hk = self._h[slot][known]
            self._h_lo = min(self._h_lo, float(np.nanmin(hk)))
            self._h_hi = max(self._h_hi, float(np.nanmax(hk)))
        self._dirty.add(tile.key)

    def memory_bytes(self) -> int:
        """Bytes held by the map: the tile pool as allocated plus the key index."""
        pool = sum(layer.nbytes for layer in self._layers())
        side = self._pf_cells.nbytes + self._pf_height.nbytes + self._fo_cells.nbytes + self._fo_ids.nbytes
        return int(pool + side + self._keys.nbytes + self._key_slots.nbytes + 64 * len(self._slot_key))

    def observed_area_m2(self) -> float:
        """Area (m^2) of the cells holding evidence."""
        return float(np.count_nonzero(self._n[: self._n_tiles])) * self.cell_size_m**2

    def save_snapshot(self, path: str | Path) -> None:
        """Write the whole map atomically (docs/terrain.md, "Snapshot format")."""
        from companion.method.terrain.persistence import write_snapshot

        write_snapshot(self, path)

    @classmethod
    def load_snapshot(cls, path: str | Path, cfg: TerrainConfig | None = None) -> "TerrainGrid":
        """Read a snapshot written by :meth:`save_snapshot`; fusion parameters come from ``cfg``.
        A truncated, corrupted or incompatible file raises SnapshotError and builds nothing."""
        from companion.method.terrain.persistence import read_snapshot

        return read_snapshot(path, cfg)


def grids_equal(a: TerrainGrid, b: TerrainGrid) -> bool:
    """Same geometry, same tiles, bit-exact layers (including the fusion state)."""
    if (a.cell_size_m, a.tile_cells) != (b.cell_size_m, b.tile_cells) or a.keys() != b.keys():
        return False
    return all(a.tile(k, with_disagreement=True).same_as(b.tile(k, with_disagreement=True)) for k in a.keys())

