"""Terrain evidence grid (seed 000, section II.E): fusion, tiles, wire codec, snapshots."""

from companion.method.terrain.codec import decode_tile, encode_tile
from companion.method.terrain.grid import Corridor, InsertStats, TerrainGrid
from companion.method.terrain.persistence import SnapshotError
from companion.method.terrain.tile import Tile

__all__ = ["Corridor", "InsertStats", "SnapshotError", "TerrainGrid", "Tile", "decode_tile", "encode_tile"]
