"""One square tile of the terrain evidence grid (the unit of storage, publication and persistence).

A tile with indices ``(tx, ty)`` and ``T`` cells of size ``c`` covers north
``[tx*T*c, (tx+1)*T*c)`` and east ``[ty*T*c, (ty+1)*T*c)`` of the local NED frame. Its layers
are ``(T, T)`` arrays indexed ``[i, j]`` with ``i`` the north cell and ``j`` the east cell inside
the tile, so cell ``[i, j]`` covers north ``[(tx*T+i)*c, (tx*T+i+1)*c)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True, eq=False)
class Tile:
    """Layers of one tile.

    height: (T, T) float32, terrain altitude (m, up = -z); NaN where the cell has no evidence.
    variance: (T, T) float32, variance of ``height`` (m^2); +inf where unknown.
    count: (T, T) uint32, evidence count (points that contributed to the cell).
    cell_size_m: edge of a cell (m).
    disagreement: optional (T, T) float32, evidence from below the cell not yet contradicted (points);
    pending: optional (T, T) float32, a higher height seen once and waiting for confirmation (m, NaN
        none). Both are internal fusion state (docs/terrain.md, "Fusion"), carried by snapshots so
        a restart resumes exactly; never published.
    ceiling: optional (T, T) float32, the lowest height a line of sight crossed the cell at (m, +inf
        none; docs/terrain.md, "Free space"); weight: optional (T, T) float32, the points' shares
        of the cell that agree with its height (the evidence in points); floor: optional (T, T)
        float32, the least the terrain in the cell reaches (m, -inf none; docs/terrain.md,
        "Floors"). All three carried by snapshots, never published.
    revision: the publisher's count of this tile's publications, when it publishes deltas (codec
        flag bit2; docs/terrain.md, "Tile deltas"); None otherwise. Not a layer: ``same_as``
        ignores it.
    """

    tx: int
    ty: int
    height: np.ndarray
    variance: np.ndarray
    count: np.ndarray
    cell_size_m: float = 1.0
    disagreement: np.ndarray | None = None
    pending: np.ndarray | None = None
    ceiling: np.ndarray | None = None
    weight: np.ndarray | None = None
    floor: np.ndarray | None = None
    revision: int | None = None

    def __post_init__(self) -> None:
        t = self.height.shape
        if len(t) != 2 or t[0] != t[1] or t[0] < 1:
            raise ValueError(f"tile layers must be square (T, T), got height {t}")
        optional = tuple(n for n in ("disagreement", "pending", "ceiling", "weight", "floor") if getattr(self, n) is not None)
        for name in ("variance", "count") + optional:
            if getattr(self, name).shape != t:
                raise ValueError(f"tile layer '{name}' has shape {getattr(self, name).shape}, expected {t}")
        if not (np.isfinite(self.cell_size_m) and self.cell_size_m > 0):
            raise ValueError(f"tile cell size must be positive and finite, got {self.cell_size_m}")

    @property
    def key(self) -> tuple[int, int]:
        return (self.tx, self.ty)

    @property
    def tile_cells(self) -> int:
        return int(self.height.shape[0])

    @property
    def origin_ne(self) -> tuple[float, float]:
        """North and east (m) of the tile's south-west corner (its lowest north/east)."""
        edge = self.tile_cells * self.cell_size_m
        return (self.tx * edge, self.ty * edge)

    @property
    def known(self) -> np.ndarray:
        """(T, T) bool: cells with evidence."""
        return self.count > 0

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """North and east (m) of every cell centre, each (T, T)."""
        n0, e0 = self.origin_ne
        k = (np.arange(self.tile_cells) + 0.5) * self.cell_size_m
        return np.meshgrid(n0 + k, e0 + k, indexing="ij")

    def same_as(self, other: "Tile") -> bool:
        """Bit-exact equality of indices, cell size and every layer (NaN payloads included)."""
        layers = ("height", "variance", "count")
        if (self.tx, self.ty, self.cell_size_m) != (other.tx, other.ty, other.cell_size_m):
            return False
        for name in ("disagreement", "pending", "ceiling", "weight", "floor"):
            if (getattr(self, name) is None) != (getattr(other, name) is None):
                return False
            if getattr(self, name) is not None:
                layers += (name,)
        return all(
            getattr(self, n).dtype == getattr(other, n).dtype
            and getattr(self, n).tobytes() == getattr(other, n).tobytes()
            for n in layers
        )
