"""Terrain evidence grid (seed 000, section II.E): fusion, tiles, wire codec, snapshots."""

from companion.terrain.codec import decode_tile, encode_tile
from companion.terrain.grid import Corridor, InsertStats, TerrainGrid
from companion.terrain.persistence import SnapshotError
from companion.terrain.tile import Tile

__all__ = ["Corridor", "InsertStats", "SnapshotError", "TerrainGrid", "Tile", "decode_tile", "encode_tile"]
